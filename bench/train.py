"""Standard 3DGS at the quick protocol on the shared scenes: PSNR against training time.

    python bench/train.py [--scenes ethiopian_head fox] [--seeds 0] [--out outputs/bench]

Writes bench/results/train.json (final metrics and the curves) and bench/results/train.png.
Runs are resumable: a finished run dir is reused.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import QUICK, ensure_lpips, RESULTS, machine, scene_overrides, table, train_run, write_results  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["ethiopian_head", "fox"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--out", default="outputs/bench")
    ap.add_argument("--extra", nargs="*", default=[], help="extra Hydra overrides for every run")
    args = ap.parse_args()
    rows, curves = [], {}
    for seed in args.seeds:
        for scene in args.scenes:
            run_dir = Path(args.out) / scene / "standard" / f"s{seed}"
            m = train_run(run_dir, scene_overrides(scene) + QUICK + ["model=standard", f"seed={seed}", *args.extra])
            m = ensure_lpips(run_dir, m)
            rows.append({"scene": scene, "seed": seed, "psnr": m["psnr"], "ssim": m["ssim"], "lpips": m["lpips"],
                         "num_gaussians": m["num_gaussians"], "train_time_s": m["train_time_s"],
                         "render_fps": m["render_fps"]})
            curves[f"{scene}/s{seed}"] = json.loads((run_dir / "curve.json").read_text())["points"]
            print(rows[-1], flush=True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=110)
    for key, pts in curves.items():
        ax.plot([p["train_time_s"] for p in pts], [p["psnr"] for p in pts], "o-", label=key, ms=3)
    ax.set_xlabel("training time (s)")
    ax.set_ylabel("test PSNR (dB)")
    ax.legend(fontsize=7)
    ax.set_title("Standard 3DGS, quick protocol (256 px, 3000 steps)", fontsize=9)
    fig.tight_layout()
    RESULTS.mkdir(parents=True, exist_ok=True)
    fig.savefig(RESULTS / "train.png")
    text = table(rows, ["scene", "seed", "psnr", "ssim", "lpips", "num_gaussians", "train_time_s", "render_fps"])
    write_results("train", {"machine": machine(), "rows": rows, "curves": curves}, text)


if __name__ == "__main__":
    main()
