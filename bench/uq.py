"""Uncertainty comparison in the shape of the paper's Table 3, plus the constant-variance baseline and
calibrated native UQ (issue 10), on the shared scenes.

Rows (per scene and seed; the ensemble per scene):

* ``standard (proxy)``, ``niw (proxy)``: the shared position-jitter proxy on the canonical runs;
* ``standard (constant)``, ``niw (constant)``: var = the model's training-residual MSE everywhere (no
  posterior, no samples) -- what a constant adds up to;
* ``niw (native)``: the paper's native posterior UQ, var = u_p + σ̂²;
* ``niw_calib (native)``, ``niw_calib (proxy)``, ``niw (native calibrated)``, ``niw (native conformal)``:
  on NIW runs trained with ``data.calib_every=16`` in their own run dirs (``<out>/<scene>/niw_calib/s<seed>``,
  so the canonical runs keep all their training views); ``native calibrated`` fits var = s·u_p + a on
  the held-out calibration views, ``native conformal`` a split-conformal interval; ``niw_calib (native)``
  and ``niw_calib (proxy)`` are the same runs uncalibrated, for paired comparisons;
* ``ensemble (M)``: a deep ensemble of the standard runs;
* ``PPU (standard)``: the PPU-style residual head on the frozen standard runs.

    python -m bench.uq [--scenes ethiopian_head fox] [--seeds 0 1 2] [--samples 50]
    python -m bench.uq --scenes synthetic --seeds 0 --max-steps 50 --train-overrides data.max_side=32 \\
        --samples 4 --out outputs/dev_uq --name dev_uq            # smoke test

Runs are trained (or reused when finished) through ``bench/common.train_run``; every evaluation writes
its ``uq.json`` to ``<out>/<scene>/uq_eval/<group>/s<seed>/`` and is reused when its settings match, so an
interrupted invocation resumes. Writes bench/results/<name>.json and a markdown table (atomically):
scene means over seeds, macro means over scenes, the epistemic decomposition, the calibration fits and
the checks of issue 10.
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from bench.common import QUICK, machine, model_overrides, read_json, scene_overrides, table, train_run, write_results

VERSION = 2  # bump when what an evaluation measures changes: cached uq.json files are then recomputed
PAPER = {  # Table 3 of the paper (13 scenes, 30k steps, GPU): for side-by-side reading
    "standard (proxy)": {"psnr": 27.322, "lpips": 0.2113, "ause_rmse": 0.0214, "ece": 0.0457, "cov95_err": 0.795, "time_s": 804},
    "niw (proxy)": {"psnr": 27.332, "lpips": 0.2111, "ause_rmse": 0.0213, "ece": 0.0450, "cov95_err": 0.795, "time_s": 815},
    "niw (native)": {"psnr": 27.332, "lpips": 0.2111, "ause_rmse": 0.0288, "ece": 0.5991, "cov95_err": 0.047, "time_s": 815},
    "ensemble (3)": {"psnr": 27.895, "lpips": 0.2070, "ause_rmse": 0.0191, "ece": 0.0277, "cov95_err": 0.454, "time_s": 2413},
}
KEYS = ["psnr", "lpips", "ause_rmse", "ause_mae", "ece", "cov95", "cov95_err", "nll", "spearman", "mean_epistemic",
        "aleatoric", "mse", "mean_var", "var_ratio", "epistemic_fraction", "epi_ause_rmse", "epi_spearman_sq",
        "epi_view_spearman", "uq_time_s", "train_time_s"]
FIT_KEYS = ["sigma2", "sigma2_plugin", "a", "s", "aleatoric_ratio", "fit_at_bound", "conformal_q", "conformal_multiplier"]
# (run group, its method and extra training overrides, [(regime, row label)])
GROUPS = {
    "standard": ("standard", [], [("proxy", "standard (proxy)"), ("constant", "standard (constant)"),
                                  ("ppu", "PPU (standard)")]),
    "niw": ("niw", [], [("proxy", "niw (proxy)"), ("constant", "niw (constant)"), ("native", "niw (native)")]),
    "niw_calib": ("niw", ["data.calib_every={calib_every}"],
                  [("native", "niw_calib (native)"), ("proxy", "niw_calib (proxy)"),
                   ("native_calibrated", "niw (native calibrated)"), ("native_conformal", "niw (native conformal)")]),
}


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
    fit = r.get("fit") or {}
    out.update({k: fit[k] for k in FIT_KEYS if k in fit})
    if fit.get("calib_views"):
        out["calib_views"] = fit["calib_views"]
    return out


def merge_overrides(*lists: list[str]) -> list[str]:
    """Hydra overrides with later ones winning per key (hydra refuses two values for one key)."""
    out: dict[str, str] = {}
    for lst in lists:
        for o in lst:
            out[o.split("=", 1)[0]] = o
    return list(out.values())


def main() -> None:
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from b3dgs.eval import evaluate_uq

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["ethiopian_head", "fox"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--groups", nargs="+", default=list(GROUPS), choices=list(GROUPS),
                    help="which run groups to evaluate (default: all)")
    ap.add_argument("--ensemble-seeds", type=int, nargs="+", default=None,
                    help="seeds of the standard runs forming the ensemble (default: --seeds)")
    ap.add_argument("--ensemble-scenes", nargs="+", default=None, help="scenes that get an ensemble row (default: all)")
    ap.add_argument("--samples", type=int, default=50)
    ap.add_argument("--jitter", type=float, default=0.002)
    ap.add_argument("--calib-every", type=int, default=16, help="data.calib_every of the niw_calib runs")
    ap.add_argument("--out", default="outputs/bench")
    ap.add_argument("--name", default="uq", help="bench/results/<name>.json and .md")
    ap.add_argument("--max-views", type=int, default=None)
    ap.add_argument("--max-steps", type=int, default=None,
                    help="trainer.max_steps of the runs (smoke tests; needs its own --out, not outputs/bench)")
    ap.add_argument("--train-overrides", nargs="*", default=[],
                    help="extra b3dgs-train overrides for every run (smoke tests, e.g. data.max_side=32)")
    ap.add_argument("--jitter-sweep", type=float, nargs="*", default=[0.0005, 0.002, 0.008, 0.032],
                    help="proxy jitter scales evaluated on each scene's seed-0 standard run (evidence for how the "
                         "proxy's coverage depends on its one free parameter); pass nothing to skip")
    args = ap.parse_args()
    if (args.max_steps is not None or args.train_overrides) and Path(args.out) == Path("outputs/bench"):
        ap.error("--max-steps / --train-overrides train other runs than the benchmark's: pass another --out "
                 "(e.g. --out outputs/dev_uq)")

    def regimes(names, jitter=None):
        cfg = OmegaConf.create({
            "proxy": {"_target_": "b3dgs_plugins.uq.proxy.ProxyUQ", "samples": args.samples, "jitter": jitter or args.jitter},
            "native": {"_target_": "b3dgs_plugins.uq.native.NativeUQ", "samples": args.samples},
            "native_calibrated": {"_target_": "b3dgs_plugins.uq.native_calibrated.NativeCalibratedUQ",
                                  "samples": args.samples, "seed": 0},
            "native_conformal": {"_target_": "b3dgs_plugins.uq.native_calibrated.NativeConformalUQ",
                                 "samples": args.samples, "level": 0.95, "seed": 0},
            "constant": {"_target_": "b3dgs_plugins.uq.constant.ConstantUQ"},
            "ensemble": {"_target_": "b3dgs_plugins.uq.ensemble.EnsembleUQ"},
            "ppu": {"_target_": "b3dgs_plugins.uq.ppu.PPUHead", "steps": 300, "lr": 5e-3, "width": 16},
        })
        return {n: instantiate(cfg[n]) for n in names}

    def evaluate(run_dirs, names, seed, out_dir, jitter=None, panels=3):
        key = {"version": VERSION, "runs": [str(r) for r in run_dirs], "regimes": list(names), "seed": seed,
               "samples": args.samples, "jitter": jitter or args.jitter, "max_views": args.max_views}

        res = read_json(out_dir / "uq.json", {})
        if (res.get("_meta") or {}).get("bench_key") == key:  # written with these settings
            return res
        t0 = time.perf_counter()
        print(f"  evaluating {', '.join(names)} on {', '.join(map(str, run_dirs))} ...", flush=True)
        res = evaluate_uq([str(r) for r in run_dirs], regimes(names, jitter), seed=seed, max_views=args.max_views,
                          out_dir=out_dir, panels=panels, meta={"bench_key": key})
        print(f"  done in {time.perf_counter() - t0:.0f} s -> {out_dir / 'uq.json'}", flush=True)
        return res

    def train(scene, group, seed):
        method, extra, _ = GROUPS[group]
        run_dir = Path(args.out) / scene / group / f"s{seed}"
        steps = [f"trainer.max_steps={args.max_steps}"] if args.max_steps is not None else []
        over = merge_overrides(scene_overrides(scene), QUICK, [*model_overrides(method), f"seed={seed}"],
                               [o.format(calib_every=args.calib_every) for o in extra], steps, args.train_overrides)
        if not (run_dir / "metrics.json").exists():
            print(f"  training {run_dir} ({' '.join(over)}) ...", flush=True)
        train_run(run_dir, over)
        return run_dir

    rows = []
    t_start = time.perf_counter()
    for scene in args.scenes:
        std_runs = []
        for seed in args.seeds:
            for group in args.groups:
                print(f"[{scene} s{seed} {group}] ({time.perf_counter() - t_start:.0f} s so far)", flush=True)
                run_dir = train(scene, group, seed)
                if group == "standard":
                    std_runs.append(str(run_dir))
                names = [n for n, _ in GROUPS[group][2]]
                res = evaluate([run_dir], names, seed, Path(args.out) / scene / "uq_eval" / group / f"s{seed}")
                for regime, label in GROUPS[group][2]:
                    rows.append({"scene": scene, "seed": seed, "row": label, **pick(res, regime)})
                    r = rows[-1]
                    print(f"    {label}: Cov@95 {r.get('cov95', float('nan')):.3f}, AUSE {r.get('ause_rmse', float('nan')):.4f}, "
                          f"epistemic ρ {r.get('epi_spearman_sq') if r.get('epi_spearman_sq') is not None else 'n/a'}",
                          flush=True)
        if args.ensemble_scenes is not None and scene not in args.ensemble_scenes:
            std_runs = []
        elif args.ensemble_seeds:
            std_runs = [str(train(scene, "standard", seed)) for seed in args.ensemble_seeds]
        elif "standard" not in args.groups:
            std_runs = []
        if len(std_runs) >= 2:
            print(f"[{scene} ensemble of {len(std_runs)}]", flush=True)
            res = evaluate(std_runs, ["ensemble"], 0, Path(args.out) / scene / "uq_eval" / "ensemble")
            rows.append({"scene": scene, "seed": "all", "row": f"ensemble ({len(std_runs)})", **pick(res, "ensemble")})

    sweep = []
    for scene in args.scenes if (args.jitter_sweep and "standard" in args.groups) else []:
        run_dir = train(scene, "standard", args.seeds[0])
        for jit in args.jitter_sweep:
            res = evaluate([run_dir], ["proxy"], 0, Path(args.out) / scene / "proxy_sweep" / f"j{jit:g}", jitter=jit, panels=0)
            sweep.append({"scene": scene, "jitter": jit, **pick(res, "proxy")})
            print(f"[{scene} proxy jitter {jit:g}] Cov@95 {sweep[-1]['cov95']:.3f}", flush=True)

    def mean(vals):
        vals = [v for v in vals if isinstance(v, (int, float)) and not isinstance(v, bool)]
        return statistics.mean(vals) if vals else None

    keys = KEYS + FIT_KEYS
    scene_means = []
    for scene in args.scenes:
        for name in dict.fromkeys(r["row"] for r in rows):
            sel = [r for r in rows if r["scene"] == scene and r["row"] == name]
            if sel:
                scene_means.append({"scene": scene, "row": name, "n_seeds": len(sel),
                                    **{k: mean([r.get(k) for r in sel]) for k in keys}})
    macro = []
    for name in dict.fromkeys(r["row"] for r in scene_means):
        sel = [r for r in scene_means if r["row"] == name]
        macro.append({"row": name, **{k: mean([r.get(k) for r in sel]) for k in keys}})

    def get(scene, row, key):
        return next((r.get(key) for r in scene_means if r["scene"] == scene and r["row"] == row), None)

    checks = []
    for scene in args.scenes:
        c = {"scene": scene,
             "cov95 native": get(scene, "niw (native)", "cov95"), "cov95 constant": get(scene, "niw (constant)", "cov95"),
             "epistemic share": get(scene, "niw (native)", "epistemic_fraction"),
             "calibrated |cov95-0.95|": get(scene, "niw (native calibrated)", "cov95_err"),
             "AUSE calibrated": get(scene, "niw (native calibrated)", "ause_rmse"),
             "AUSE proxy (niw)": get(scene, "niw (proxy)", "ause_rmse"),
             "AUSE proxy (niw_calib)": get(scene, "niw_calib (proxy)", "ause_rmse")}
        if c["cov95 native"] is not None and c["cov95 constant"] is not None:
            c["native - constant"] = c["cov95 native"] - c["cov95 constant"]
        if c["calibrated |cov95-0.95|"] is not None:
            c["cov ok (<=0.02)"] = c["calibrated |cov95-0.95|"] <= 0.02
        if c["AUSE calibrated"] is not None and c["AUSE proxy (niw_calib)"] is not None:
            c["AUSE <= proxy (paired)"] = c["AUSE calibrated"] <= c["AUSE proxy (niw_calib)"]
        checks.append(c)

    cols = ["row", "psnr", "lpips", "ause_rmse", "ece", "cov95", "cov95_err", "nll", "spearman", "uq_time_s", "train_time_s"]
    text = "Scene means over seeds:\n" + table(scene_means, ["scene", "n_seeds"] + cols)
    text += "\n\nMacro means over scenes (ours):\n" + table(macro, cols)
    text += ("\n\nEpistemic part alone (scene means): mean u_p, its share of the predictive variance, its AUSE, its "
             "Spearman ρ with the per-pixel squared error and ρ of per-view mean u_p with per-view MSE:\n") + table(
                 [r for r in scene_means if r.get("epistemic_fraction") is not None],
                 ["scene", "row", "mean_epistemic", "aleatoric", "epistemic_fraction", "epi_ause_rmse",
                  "epi_spearman_sq", "epi_view_spearman"])
    text += "\n\nCalibration evidence (scene means): held-out MSE, mean predictive variance, their ratio, " \
            "the aleatoric term and the mean epistemic part:\n" + table(
                scene_means, ["scene", "row", "mse", "mean_var", "var_ratio", "aleatoric", "mean_epistemic", "cov95"])
    fits = [r for r in rows if any(r.get(k) is not None for k in ("a", "conformal_q", "sigma2"))]
    if fits:
        text += ("\n\nFitted scalars per run (constant: σ̂² = training-residual MSE; calibrated: var = s·u_p + a on the "
                 "calibration views, aleatoric_ratio = a / plug-in σ̂²; conformal: q and (q/1.96)²):\n") + table(
                     fits, ["scene", "seed", "row", "sigma2", "sigma2_plugin", "a", "s", "aleatoric_ratio", "fit_at_bound",
                            "conformal_q", "conformal_multiplier"])
        views = {(r["scene"], r["seed"]): r["calib_views"] for r in rows if r.get("calib_views")}
        if views:
            text += "\n\nCalibration views (held out of the niw_calib runs' training, never test views):\n" + "\n".join(
                f"- {s} s{seed}: {', '.join(v)}" for (s, seed), v in views.items())
    text += "\n\nIssue 10 checks (scene means):\n" + table(checks, list(dict.fromkeys(k for c in checks for k in c)))
    if sweep:
        text += "\n\nProxy coverage against its jitter scale (seed-0 standard runs):\n" + table(
            sweep, ["scene", "jitter", "cov95", "cov95_err", "ause_rmse", "ece", "var_ratio"])
    paper_rows = [{"row": k, **v} for k, v in PAPER.items()]
    text += "\n\nPaper Table 3 (13 scenes, 30k steps, for reference):\n" + table(
        paper_rows, ["row", "psnr", "lpips", "ause_rmse", "ece", "cov95_err", "time_s"])
    write_results(args.name, {"machine": machine(), "rows": rows, "scene_means": scene_means, "macro": macro,
                              "checks": checks, "paper": PAPER, "samples": args.samples, "jitter": args.jitter,
                              "calib_every": args.calib_every, "proxy_jitter_sweep": sweep}, text)


if __name__ == "__main__":
    main()
