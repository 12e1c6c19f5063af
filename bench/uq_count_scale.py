"""What sets the spread of the NIW posterior (issue 10 §2): the count scale c in N̂ ← c·N̂ (Eq. 2-3),
the covariance mode of the draws and the scatter C_k, swept on trained NIW runs without retraining.

    python -m bench.uq_count_scale --runs outputs/bench/ethiopian_head/niw/s0 outputs/bench/fox/niw/s0 \\
        [--scales 1 0.1 0.01 0.001] [--cov-modes relative absolute] [--scatter zero rendered] [--samples 50]

Each run is loaded once; for every setting the NIW block's ``count_scale`` / ``cov_mode`` are set on the
loaded block and its posterior is refreshed from the stored summaries (N̂, m0, S0: the checkpoint's
state), then ``uq=native`` is scored on the test views (var = u_p + σ̂², σ̂² the run's plug-in). Axes:

* ``--scales``: c (1 = the paper, as trained);
* ``--cov-modes``: how a draw replaces the rendered covariance (``relative``: L W Lᵀ, spread set by ν_n
  alone; ``absolute``: the IW draw Σ itself; ``none``: centres only);
* ``--scatter``: C_k in Eq. 3. ``zero`` is the paper's online path (C_k = 0, so E[Σ] ≈ S0/(c N̂) and
  Var[μ] ≈ S0/(c N̂)²); ``rendered`` takes the pseudo-observations to be spread like the Gaussian itself,
  C_k = c N̂_k Σ_k (Σ_k the point-estimate covariance), so E[Σ] → Σ_k and Var[μ] ≈ Σ_k/(c N̂). This axis
  lives in this script only (a subclass of the block); it would move into the block if it wins.

Per setting: mean u_p, the epistemic part's AUSE (RMSE) and Spearman ρ with the per-pixel squared error
and ρ of per-view mean u_p with per-view MSE, the epistemic fraction of the variance, Cov@95 and NLL
(σ̂² added), and the PSNR of the posterior-mean render (μ = m_n) against the point estimate's (within
0.1 dB?). Runs trained with ``data.calib_every`` also get ``uq=native_calibrated`` per setting.

Resumable: every setting's ``uq.json`` goes to ``--out/<scene>/<run>/<setting>/`` and is reused when its
``_meta.setting`` matches. Writes bench/results/<--name>.json and .md (atomically).
"""
from __future__ import annotations

import argparse
import json
import statistics
import time
from dataclasses import dataclass, fields
from pathlib import Path

from bench.common import machine, read_json, table, write_results

VERSION = 1  # bump when the measurement changes, so cached settings are recomputed
COLS = ["mean_epistemic", "epistemic_fraction", "epi_ause_rmse", "epi_spearman_sq", "epi_view_spearman",
        "ause_rmse", "cov95", "cov95_err", "nll", "ece", "aleatoric"]


def scatter_block(blk):
    """A copy of NIW block ``blk`` whose refresh uses the scatter C_k = c N̂_k Σ_k (see the module docstring)."""
    import torch

    from b3dgs_plugins.posterior import niw as niwm
    from b3dgs.render.projection import covariance_3d
    from b3dgs_plugins.posterior.niw import NIWBlock

    @dataclass
    class RenderedScatterNIW(NIWBlock):
        @torch.no_grad()
        def _refresh(self, state, splats) -> None:
            xbar = splats["means"].detach().double()
            n, dev = xbar.shape[0], xbar.device
            k0 = torch.full((n,), float(self.kappa0), dtype=torch.float64, device=dev)
            nu0 = torch.full((n,), float(self.nu0), dtype=torch.float64, device=dev)
            cn = state["N"] * float(self.count_scale)
            C = cn[:, None, None] * covariance_3d(splats["quats"].detach(), splats["scales"].detach()).double()
            m_n, k_n, nu_n, S_n = niwm.niw_update(state["m0"], k0, nu0, state["S0"], cn, xbar, C)
            state["m_n"], state["kappa_n"], state["nu_n"], state["S_n"] = m_n, k_n, nu_n, S_n
            state["ediag"] = torch.diagonal(niwm.expected_cov(S_n, nu_n), dim1=-2, dim2=-1).clone()

    return RenderedScatterNIW(**{f.name: getattr(blk, f.name) for f in fields(blk)})


def niw_name(module) -> str:
    from b3dgs_plugins.posterior.niw import NIWBlock

    names = [k for k, b in module.posterior.items() if isinstance(b, NIWBlock)]
    if not names:
        raise SystemExit(f"{module} has no NIW block: pass NIW runs (outputs/bench/<scene>/niw/s0)")
    return names[0]


def psnr_of(module, cams, params=None) -> float:
    import torch

    from b3dgs.metrics.image import psnr

    vals = []
    with torch.no_grad():
        for c in cams:
            img = module.render_camera(c, params=params).rgb.clamp(0, 1) if params is not None else module.render_eval(c)
            vals.append(float(psnr(img.cpu(), c.image)))
    return statistics.mean(vals)


def main() -> None:
    import torch

    from b3dgs.eval import evaluate_uq
    from b3dgs.runs import load_run
    from b3dgs.uq.regime import render_params
    from b3dgs_plugins.uq.native import NativeUQ
    from b3dgs_plugins.uq.native_calibrated import NativeCalibratedUQ

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", nargs="+", required=True, help="trained NIW run dirs (e.g. outputs/bench/fox/niw/s0)")
    ap.add_argument("--scales", type=float, nargs="+", default=[1.0, 1e-1, 1e-2, 1e-3])
    ap.add_argument("--cov-modes", nargs="+", default=["relative", "absolute"], choices=["relative", "absolute", "none"])
    ap.add_argument("--scatter", nargs="+", default=["zero", "rendered"], choices=["zero", "rendered"])
    ap.add_argument("--samples", type=int, default=50)
    ap.add_argument("--max-views", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="outputs/bench/count_scale", help="where each setting's uq.json goes")
    ap.add_argument("--name", default="uq_count_scale", help="bench/results/<name>.json and .md")
    args = ap.parse_args()

    rows = []
    settings = [(c, mode, sc) for sc in args.scatter for mode in args.cov_modes for c in args.scales]
    for run_dir in args.runs:
        run_dir = Path(run_dir)
        run = None  # loaded on the first setting that is not cached
        for i, (c, mode, sc) in enumerate(settings):
            scene_name = json.loads((run_dir / "metrics.json").read_text()).get("scene") or run_dir.parent.parent.name
            tag = f"c{c:g}_{mode}_{sc}"
            out_dir = Path(args.out) / scene_name / f"{run_dir.parent.name}_{run_dir.name}" / tag
            setting = {"version": VERSION, "run": str(run_dir), "count_scale": c, "cov_mode": mode, "scatter": sc,
                       "samples": args.samples, "max_views": args.max_views, "seed": args.seed}
            res = read_json(out_dir / "uq.json", {})
            res = res if (res.get("_meta") or {}).get("setting") == setting else None
            t0 = time.perf_counter()
            if res is None:
                if run is None:
                    run = load_run(run_dir)
                    name = niw_name(run.module)
                    base_blk = run.module.posterior[name]
                    trained = (base_blk.count_scale, base_blk.cov_mode)
                    cams = run.scene.test[:args.max_views] if args.max_views else run.scene.test
                    psnr_point = psnr_of(run.module, cams)
                m = run.module
                blk = scatter_block(base_blk) if sc == "rendered" else base_blk
                blk.count_scale, blk.cov_mode = float(c), mode
                m.posterior[name] = blk
                pm = blk.posterior_mean(splats=m.splats, state=m.states[name], params=render_params(m))
                psnr_mean = psnr_of(m, cams, params=pm)
                with torch.no_grad():
                    shift = (pm["means"] - m.splats["means"]).norm(dim=-1)
                regimes = {"native": NativeUQ(samples=args.samples)}
                if getattr(run.scene, "calib", None):
                    regimes["native_calibrated"] = NativeCalibratedUQ(samples=args.samples, seed=args.seed)
                meta = {"setting": setting, "psnr_point": psnr_point, "psnr_posterior_mean": psnr_mean,
                        "posterior_mean_shift_median": float(shift.median()), "mean_count": float(m.states[name]["N"].mean())}
                res = evaluate_uq([str(run_dir)], regimes, seed=args.seed, max_views=args.max_views, panels=0,
                                  out_dir=out_dir, loaded=[run], meta=meta)
                m.posterior[name] = base_blk
                base_blk.count_scale, base_blk.cov_mode = trained
            meta = res["_meta"]
            first = len(rows)
            for regime in [k for k in res if k != "_meta"]:
                r = res[regime]
                row = {"scene": scene_name, "run": run_dir.name, "regime": regime, "count_scale": c, "cov_mode": mode,
                       "scatter": sc, **{k: r.get(k) for k in COLS},
                       "psnr_point": meta["psnr_point"], "psnr_post_mean": meta["psnr_posterior_mean"],
                       "d_psnr": meta["psnr_posterior_mean"] - meta["psnr_point"],
                       "mean_shift": meta["posterior_mean_shift_median"], "mean_count": meta["mean_count"]}
                row["within_0.1dB"] = abs(row["d_psnr"]) <= 0.1
                if regime == "native_calibrated":
                    row.update(fit_s=r["fit"].get("s"), fit_a=r["fit"].get("a"))
                rows.append(row)
            for row in rows[first:]:
                print(f"[{run_dir} {i + 1}/{len(settings)}] {tag} {row['regime']}: " + ", ".join(
                    f"{k}={row[k]:.4g}" for k in ("mean_epistemic", "epi_spearman_sq", "cov95", "d_psnr")
                    if isinstance(row.get(k), float)) + f" ({time.perf_counter() - t0:.1f} s)", flush=True)

    cols = ["scene", "regime", "scatter", "cov_mode", "count_scale", "mean_epistemic", "epistemic_fraction",
            "epi_ause_rmse", "epi_spearman_sq", "epi_view_spearman", "ause_rmse", "cov95", "cov95_err", "nll",
            "d_psnr", "within_0.1dB"]
    text = ("NIW posterior spread against the count scale c (N̂ ← c·N̂), the draws' covariance mode and the "
            f"scatter C_k; uq=native, S={args.samples}, var = u_p + σ̂² (d_psnr: posterior-mean render minus "
            "point estimate, dB):\n" + table(rows, cols))
    if any("fit_s" in r for r in rows):
        text += "\n\nCalibrated native on the same settings (runs with calibration views):\n" + table(
            [r for r in rows if r["regime"] == "native_calibrated"],
            ["scene", "scatter", "cov_mode", "count_scale", "fit_s", "fit_a", "cov95", "cov95_err", "nll", "epi_ause_rmse"])
    paired = paired_against_one(rows)
    if paired:
        text += ("\n\nEach count scale against c = 1 (the default), paired by scene: per-scene mean over its runs (seeds) "
                 "of the difference c - 1, then the mean over scenes with the bootstrap CI and the exact sign-flip p "
                 "(`b3dgs.report.stats.paired_stats`); 'better' counts scenes where the difference goes the "
                 "metric's good way:\n" + table(paired, ["regime", "scatter", "cov_mode", "count_scale", "metric",
                                                         "mean_diff", "ci_low", "ci_high", "p_two_sided", "better",
                                                         "n_scenes"]))
    write_results(args.name, {"machine": machine(), "samples": args.samples, "runs": args.runs, "rows": rows,
                              "paired_vs_c1": paired}, text)


#: metrics of the paired table and whether lower is better
PAIRED = {"cov95_err": True, "ause_rmse": True, "nll": True, "epi_ause_rmse": True, "epi_spearman_sq": False}


def paired_against_one(rows: list[dict]) -> list[dict]:
    """Every count scale c != 1 against c = 1 on the same runs, per (regime, scatter, cov_mode) and metric."""
    from b3dgs.report.stats import paired_stats

    out = []
    key = lambda r: (r["regime"], r["scatter"], r["cov_mode"])  # noqa: E731
    ref = {(key(r), r["scene"], r["run"]): r for r in rows if r["count_scale"] == 1.0}
    for (regime, sc, mode) in dict.fromkeys(key(r) for r in rows):
        for c in sorted({r["count_scale"] for r in rows if key(r) == (regime, sc, mode) and r["count_scale"] != 1.0},
                        reverse=True):
            for metric, lower in PAIRED.items():
                per_scene: dict[str, list[float]] = {}
                for r in rows:
                    b = ref.get(((regime, sc, mode), r["scene"], r["run"]))
                    if key(r) == (regime, sc, mode) and r["count_scale"] == c and b is not None \
                            and r.get(metric) is not None and b.get(metric) is not None:
                        per_scene.setdefault(r["scene"], []).append(r[metric] - b[metric])
                if len(per_scene) < 2:
                    continue
                d = [statistics.fmean(v) for v in per_scene.values()]
                st = paired_stats(d, higher_is_better=not lower)
                out.append({"regime": regime, "scatter": sc, "cov_mode": mode, "count_scale": c, "metric": metric,
                            "mean_diff": st["mean"], "ci_low": st["ci"]["low"], "ci_high": st["ci"]["high"],
                            "p_two_sided": st["p_two_sided"], "better": f"{sum((x < 0) if lower else (x > 0) for x in d)}"
                            f"/{len(d)}", "n_scenes": len(d)})
    return out


if __name__ == "__main__":
    main()
