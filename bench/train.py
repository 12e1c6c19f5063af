"""Training at the quick protocol on the shared scenes: PSNR against training time, per model and device.

    python -m bench.train [--scenes ethiopian_head fox] [--seeds 0] [--models standard] [--out outputs/bench]
    python -m bench.train --device cuda --scenes fox --models standard niw dpmm     # on a GPU machine

Writes bench/results/train.json (train_cuda.json for --device cuda: final metrics, the curves and the
device) and the matching .png. Runs are resumable: a finished run dir is reused. With several models,
the table adds each model's training time relative to standard of the same scene and seed.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from bench.common import (QUICK, RESULTS, ensure_lpips, machine, model_overrides, pyplot, scene_overrides, table,
                          train_run, write_results)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["ethiopian_head", "fox"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--out", default="outputs/bench")
    ap.add_argument("--models", nargs="+", default=["standard"], help="standard, niw, dpmm")
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                    help="cpu: renderer=cpu; cuda: renderer=gsplat (the GPU path of renderer=auto)")
    ap.add_argument("--extra", nargs="*", default=[], help="extra Hydra overrides for every run")
    ap.add_argument("--results", default=str(RESULTS), help="where train[_cuda].{json,md,png} go")
    args = ap.parse_args()
    renderer = {"cpu": "cpu", "cuda": "gsplat"}[args.device]
    suffix = "" if args.device == "cpu" else f"_{args.device}"
    rows, curves = [], {}
    for seed in args.seeds:
        for scene in args.scenes:
            for model in args.models:
                run_dir = Path(args.out) / scene / f"{model}{suffix}" / f"s{seed}"
                m = train_run(run_dir, scene_overrides(scene) + QUICK + [*model_overrides(model), f"seed={seed}",
                                                                          f"renderer={renderer}", *args.extra])
                m = ensure_lpips(run_dir, m)
                rend = m.get("renderer")
                blocks_s = sum((m.get("block_time_s") or {}).values())
                rows.append({"scene": scene, "model": model, "seed": seed, "device": args.device,
                             "renderer": rend.get("name") if isinstance(rend, dict) else rend,
                             "psnr": m["psnr"], "ssim": m["ssim"], "lpips": m["lpips"],
                             "num_gaussians": m["num_gaussians"], "train_time_s": m["train_time_s"],
                             # the in-run timer's share of the training time spent in the posterior blocks' hooks
                             "block_share": round(blocks_s / m["train_time_s"], 4) if m["train_time_s"] else None,
                             "render_fps": m["render_fps"]})
                curves[f"{scene}/{model}/s{seed}"] = json.loads((run_dir / "curve.json").read_text())["points"]
                print(rows[-1], flush=True)
                write(args, rows, curves, suffix)  # after every run: a stopped benchmark keeps what finished


def write(args, rows: list[dict], curves: dict, suffix: str) -> None:
    base = {(r["scene"], r["seed"]): r["train_time_s"] for r in rows if r["model"] == "standard"}
    for r in rows:
        b = base.get((r["scene"], r["seed"]))
        r["time_vs_standard"] = round(r["train_time_s"] / b, 4) if b else None
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=110)
    for key, pts in curves.items():
        ax.plot([p["train_time_s"] for p in pts], [p["psnr"] for p in pts], "o-", label=key, ms=3)
    ax.set_xlabel("training time (s)")
    ax.set_ylabel("test PSNR (dB)")
    ax.legend(fontsize=7)
    results = Path(args.results)
    results.mkdir(parents=True, exist_ok=True)
    ax.set_title(f"Quick protocol (256 px, 3000 steps) on {args.device}", fontsize=9)
    fig.tight_layout()
    from b3dgs.io import save_figure

    save_figure(fig, results / f"train{suffix}.png")
    text = table(rows, ["scene", "model", "seed", "device", "renderer", "psnr", "ssim", "lpips", "num_gaussians",
                        "train_time_s", "time_vs_standard", "block_share", "render_fps"])
    write_results(f"train{suffix}", {"machine": machine(), "device": args.device, "rows": rows, "curves": curves},
                  text, root=results)


if __name__ == "__main__":
    main()
