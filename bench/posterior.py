"""Standard vs NIW vs DPMM at the quick protocol on the shared scenes, interleaved, several seeds.

    python -m bench.posterior [--scenes ethiopian_head fox] [--seeds 0 1 2] [--out outputs/bench]

Per (scene, seed) the three methods run back to back, so the overhead ratios compare runs made
under the same machine conditions. Writes bench/results/posterior.json and a table: PSNR, SSIM,
LPIPS, #Gaussians, FPS, train time, and per-method medians of the paired ratios against standard.
Runs are resumable (finished run dirs are reused) and shared with bench/uq.py.
"""
from __future__ import annotations

import argparse
import statistics
from pathlib import Path

from bench.common import (QUICK, ensure_lpips, machine, model_overrides, scene_overrides, table, train_run,
                          write_results)

METHODS = ["standard", "niw", "dpmm"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["ethiopian_head", "fox"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--methods", nargs="+", default=METHODS)
    ap.add_argument("--out", default="outputs/bench")
    ap.add_argument("--extra", nargs="*", default=[])
    args = ap.parse_args()
    rows = []
    for seed in args.seeds:
        for scene in args.scenes:
            for method in args.methods:
                run_dir = Path(args.out) / scene / method / f"s{seed}"
                m = train_run(run_dir, scene_overrides(scene) + QUICK
                              + [*model_overrides(method), f"seed={seed}", *args.extra])
                m = ensure_lpips(run_dir, m)
                rows.append({"scene": scene, "seed": seed, "method": method, "psnr": m["psnr"], "ssim": m["ssim"],
                             "lpips": m["lpips"], "num_gaussians": m["num_gaussians"], "fps": m["render_fps"],
                             "train_time_s": m["train_time_s"], "removed": m.get("removed", {}),
                             "block_time_s": m.get("block_time_s", {}), "run_dir": str(run_dir)})
                print({k: rows[-1][k] for k in ("scene", "seed", "method", "psnr", "num_gaussians", "train_time_s")},
                      flush=True)
    paired = []
    for method in args.methods:
        if method == "standard":
            continue
        for scene in args.scenes:
            ratios, dpsnr, gauss, block = [], [], [], []
            for seed in args.seeds:
                base = next((r for r in rows if (r["scene"], r["seed"], r["method"]) == (scene, seed, "standard")), None)
                cur = next((r for r in rows if (r["scene"], r["seed"], r["method"]) == (scene, seed, method)), None)
                if base and cur:
                    ratios.append(cur["train_time_s"] / base["train_time_s"])
                    dpsnr.append(cur["psnr"] - base["psnr"])
                    gauss.append(cur["num_gaussians"] / base["num_gaussians"])
                    block.append(100 * sum(cur["block_time_s"].values()) / cur["train_time_s"])
            if ratios:
                paired.append({"method": method, "scene": scene, "n": len(ratios),
                               "time_overhead_pct": round(100 * (statistics.median(ratios) - 1), 2),
                               "dpsnr_mean": round(statistics.mean(dpsnr), 3),
                               "gauss_ratio_median": round(statistics.median(gauss), 3),
                               # wall time inside the blocks' hooks, measured within the run (noise-free)
                               "block_time_pct": round(statistics.median(block), 2)})
    text = table(rows, ["scene", "seed", "method", "psnr", "ssim", "lpips", "num_gaussians", "fps", "train_time_s"])
    text += "\n\nPaired against standard (same scene and seed, run back to back):\n"
    text += table(paired, ["method", "scene", "n", "time_overhead_pct", "block_time_pct", "dpsnr_mean",
                           "gauss_ratio_median"])
    write_results("posterior", {"machine": machine(), "rows": rows, "paired": paired}, text)


if __name__ == "__main__":
    main()
