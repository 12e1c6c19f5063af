"""Uncertainty comparison in the shape of the paper's Table 3: standard (proxy), NIW (proxy),
NIW (native) and a 3-member deep ensemble of standard runs, on the shared scenes; plus the
PPU-style residual head on the standard runs (a supplementary row, as in the paper).

    python bench/posterior.py --methods standard niw     # trains (or reuses) the runs first
    python bench/uq.py [--scenes ethiopian_head fox] [--seeds 0 1 2] [--samples 50]

Writes bench/results/uq.json and a table (scene means over seeds, then macro means over scenes).
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import QUICK, machine, scene_overrides, table, train_run, write_results  # noqa: E402

PAPER = {  # Table 3 of the paper (13 scenes, 30k steps, GPU): for side-by-side reading
    "standard (proxy)": {"psnr": 27.322, "lpips": 0.2113, "ause_rmse": 0.0214, "ece": 0.0457, "cov95_err": 0.795, "time_s": 804},
    "niw (proxy)": {"psnr": 27.332, "lpips": 0.2111, "ause_rmse": 0.0213, "ece": 0.0450, "cov95_err": 0.795, "time_s": 815},
    "niw (native)": {"psnr": 27.332, "lpips": 0.2111, "ause_rmse": 0.0288, "ece": 0.5991, "cov95_err": 0.047, "time_s": 815},
    "ensemble (3)": {"psnr": 27.895, "lpips": 0.2070, "ause_rmse": 0.0191, "ece": 0.0277, "cov95_err": 0.454, "time_s": 2413},
}
KEYS = ["psnr", "lpips", "ause_rmse", "ause_mae", "ece", "cov95", "cov95_err", "nll", "spearman", "mean_epistemic",
        "aleatoric", "mse", "mean_var", "var_ratio", "uq_time_s", "train_time_s"]


def pick(res: dict, regime: str) -> dict:
    """The table columns of one regime, plus the calibration evidence: held-out MSE, the mean predictive
    variance and their ratio (1 for calibrated Gaussian intervals; > 1 means the intervals are too narrow)."""
    r = res[regime]
    out = {k: r.get(k) for k in KEYS if k in r}
    views = r.get("per_view") or []
    if views:
        out["mse"] = statistics.mean(v["rmse"] ** 2 for v in views)
        out["mean_var"] = statistics.mean(v["mean_var"] for v in views)
        out["var_ratio"] = out["mse"] / out["mean_var"] if out["mean_var"] > 0 else None
        out["aleatoric"] = statistics.mean(float(v.get("aleatoric") or 0.0) for v in views)
    out["uq_time_s"] = r["time_s"]
    out["train_time_s"] = r["train_time_s"]
    return out


def main() -> None:
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from b3dgs.eval import evaluate_uq

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["ethiopian_head", "fox"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--ensemble-seeds", type=int, nargs="+", default=None,
                    help="seeds of the standard runs forming the ensemble (default: --seeds)")
    ap.add_argument("--ensemble-scenes", nargs="+", default=None, help="scenes that get an ensemble row (default: all)")
    ap.add_argument("--samples", type=int, default=50)
    ap.add_argument("--jitter", type=float, default=0.002)
    ap.add_argument("--out", default="outputs/bench")
    ap.add_argument("--max-views", type=int, default=None)
    ap.add_argument("--jitter-sweep", type=float, nargs="*", default=[0.0005, 0.002, 0.008, 0.032],
                    help="proxy jitter scales evaluated on each scene's seed-0 standard run (evidence for how the "
                         "proxy's coverage depends on its one free parameter); pass nothing to skip")
    args = ap.parse_args()

    def regimes(names):
        cfg = OmegaConf.create({
            "proxy": {"_target_": "plugins.uq.proxy.ProxyUQ", "samples": args.samples, "jitter": args.jitter},
            "native": {"_target_": "plugins.uq.native.NativeUQ", "samples": args.samples},
            "ensemble": {"_target_": "plugins.uq.ensemble.EnsembleUQ"},
            "ppu": {"_target_": "plugins.uq.ppu.PPUHead", "steps": 300, "lr": 5e-3, "width": 16},
        })
        return {n: instantiate(cfg[n]) for n in names}

    rows = []
    for scene in args.scenes:
        std_runs = []
        for seed in args.seeds:
            runs = {}
            for method in ("standard", "niw"):
                run_dir = Path(args.out) / scene / method / f"s{seed}"
                train_run(run_dir, scene_overrides(scene) + QUICK + [f"model={method}", f"seed={seed}"])
                runs[method] = run_dir
            std_runs.append(str(runs["standard"]))
            r = evaluate_uq([str(runs["standard"])], regimes(["proxy", "ppu"]), seed=seed, max_views=args.max_views)
            rows.append({"scene": scene, "seed": seed, "row": "standard (proxy)", **pick(r, "proxy")})
            rows.append({"scene": scene, "seed": seed, "row": "standard (ppu head)", **pick(r, "ppu")})
            r = evaluate_uq([str(runs["niw"])], regimes(["proxy", "native"]), seed=seed, max_views=args.max_views)
            rows.append({"scene": scene, "seed": seed, "row": "niw (proxy)", **pick(r, "proxy")})
            rows.append({"scene": scene, "seed": seed, "row": "niw (native)", **pick(r, "native")})
            print(rows[-4:], flush=True)
        if args.ensemble_scenes is not None and scene not in args.ensemble_scenes:
            std_runs = []
        elif args.ensemble_seeds:
            std_runs = []
            for seed in args.ensemble_seeds:
                run_dir = Path(args.out) / scene / "standard" / f"s{seed}"
                train_run(run_dir, scene_overrides(scene) + QUICK + ["model=standard", f"seed={seed}"])
                std_runs.append(str(run_dir))
        if len(std_runs) >= 2:
            r = evaluate_uq(std_runs, regimes(["ensemble"]), seed=0, max_views=args.max_views,
                            out_dir=Path(args.out) / scene / "ensemble")
            rows.append({"scene": scene, "seed": "all", "row": f"ensemble ({len(std_runs)})", **pick(r, "ensemble")})
            print(rows[-1], flush=True)

    sweep = []
    for scene in args.scenes if args.jitter_sweep else []:
        run_dir = Path(args.out) / scene / "standard" / f"s{args.seeds[0]}"
        for jit in args.jitter_sweep:
            reg = {"proxy": instantiate(OmegaConf.create(
                {"_target_": "plugins.uq.proxy.ProxyUQ", "samples": args.samples, "jitter": jit}))}
            r = evaluate_uq([str(run_dir)], reg, seed=0, max_views=args.max_views,
                            out_dir=Path(args.out) / scene / "proxy_sweep" / f"j{jit:g}", panels=0)
            sweep.append({"scene": scene, "jitter": jit, **pick(r, "proxy")})
            print(sweep[-1], flush=True)

    def mean(vals):
        vals = [v for v in vals if isinstance(v, (int, float))]
        return statistics.mean(vals) if vals else None

    scene_means = []
    for scene in args.scenes:
        for name in dict.fromkeys(r["row"] for r in rows):
            sel = [r for r in rows if r["scene"] == scene and r["row"] == name]
            if sel:
                scene_means.append({"scene": scene, "row": name, **{k: mean([r.get(k) for r in sel]) for k in KEYS}})
    macro = []
    for name in dict.fromkeys(r["row"] for r in scene_means):
        sel = [r for r in scene_means if r["row"] == name]
        macro.append({"row": name, **{k: mean([r.get(k) for r in sel]) for k in KEYS}})
    cols = ["row", "psnr", "lpips", "ause_rmse", "ece", "cov95", "cov95_err", "nll", "spearman", "uq_time_s", "train_time_s"]
    text = "Scene means over seeds:\n" + table(scene_means, ["scene"] + cols)
    text += "\n\nMacro means over scenes (ours):\n" + table(macro, cols)
    text += "\n\nCalibration evidence (scene means): held-out MSE, mean predictive variance, their ratio, " \
            "the aleatoric term and the mean sample spread u_p:\n" + table(
                scene_means, ["scene", "row", "mse", "mean_var", "var_ratio", "aleatoric", "mean_epistemic", "cov95"])
    if sweep:
        text += "\n\nProxy coverage against its jitter scale (seed-0 standard runs):\n" + table(
            sweep, ["scene", "jitter", "cov95", "cov95_err", "ause_rmse", "ece", "var_ratio"])
    paper_rows = [{"row": k, **v} for k, v in PAPER.items()]
    text += "\n\nPaper Table 3 (13 scenes, 30k steps, for reference):\n" + table(
        paper_rows, ["row", "psnr", "lpips", "ause_rmse", "ece", "cov95_err", "time_s"])
    write_results("uq", {"machine": machine(), "rows": rows, "scene_means": scene_means, "macro": macro,
                         "paper": PAPER, "samples": args.samples, "jitter": args.jitter, "proxy_jitter_sweep": sweep},
                  text)


if __name__ == "__main__":
    main()
