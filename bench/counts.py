"""The NIW counts on the canonical grid: ``posterior.niw.count=weight|fisher|fisher3`` and the directional SH
posterior (``uq=[native_sh]``: the canonical native plus ``posterior.sh``) against the paper's count, the deep ensemble
and the constant baseline, over the seven scenes x seeds 0 1 2.

    python -m bench.counts --jobs 2 --threads 1           # retrain what is missing, score, merge, tabulate
    python -m bench.counts --table-only                   # tables from the archive only

Posterior re-evaluation without retraining: a count is a function of the trained Gaussians (one pass over the
training views, :meth:`b3dgs.module.SplatModule.view_sums`), so each canonical NIW run is scored under every count
as the uq regimes ``native_<count>`` (conf/uq/native_<count>.yaml, c = 1 like the canonical ``native``). The
archive (bench/results/runs) keeps no checkpoints, so a run without the new regimes is trained again into
``--out`` (the canonical quick protocol; NIW only observes training, so the run is the archived one bit for bit:
its final parameter digest must equal the archived metrics.json's, else the row is refused and reported); its new
regimes are merged into the archived uq.json (same views and seed, checked). Resumable: finished rows are skipped.

Output: bench/results/counts.{json,md}: per regime, the macro means over scenes (of seed means) of the support-deficit
OOD AUROC (b3dgs.report.ood), AUSE, |Cov@95 − 0.95|, NLL and the epistemic Spearman ρ with the squared error, and
paired scene-level differences (bootstrap CI, exact sign-flip p, per-scene signs) of each count against the paper's
count, the deep ensemble and the constant σ̂² baseline.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Optional

import numpy as np

from b3dgs.errors import B3dgsError
from bench.common import (QUICK, RESULTS, SEVEN, bench_child, check_same_parameters, model_overrides, read_json,
                          scene_overrides, train_run, write_results)
COUNTS = ["weight", "fisher", "fisher3", "sh"]  # scored as the uq regimes native_<name>
ALONE = ["sh"]  # --alone: uq regimes scored under their own name (sh: the SH posterior without the NIW geometry)
#: every regime --alone accepts (native_plus_sh: uq=native's c = 0.1 plus the SH posterior)
ALONE_CHOICES = ["sh", "native_plus_sh"]
#: regimes with one value per scene, not per seed: the deep ensemble (3 members: the standard runs of seeds 0 1 2)
SCENE_LEVEL = {"ensemble"}
#: (uq.json key, higher is better) of the calibration columns
COLUMNS = [("ause_rmse", False), ("cov95_err", False), ("nll", False), ("epi_spearman_sq", True)]


def regime_names(args) -> list[str]:
    """The uq regimes this run scores: ``native_<count>`` for every ``--counts``, then every ``--alone``."""
    return [f"native_{c}" for c in args.counts] + list(args.alone)


def score_one(run_dir: Path, archive_dir: Path, names: list[str], samples: int) -> None:
    """Score ``names`` on the trained run and merge them into the archived uq.json (views and seed checked)."""
    from b3dgs.eval import evaluate_uq
    from b3dgs.io import write_json
    from bench.studies import uq_regimes  # conf/report.yaml's uq_settings set none of the regimes scored here

    have = json.loads((archive_dir / "uq.json").read_text())
    seed = int(have.get("_meta", {}).get("seed", 0))
    with tempfile.TemporaryDirectory(prefix=".uq.", dir=run_dir) as tmp:
        res = evaluate_uq([str(run_dir)], uq_regimes(names, samples, seed), seed=seed, panels=0, out_dir=Path(tmp))
    views_old, views_new = have.get("_meta", {}).get("views"), res.get("_meta", {}).get("views")
    if views_old is not None and views_new is not None and views_old != views_new:
        raise RuntimeError(f"{run_dir}: the new regimes score other views than {archive_dir / 'uq.json'}")
    have = json.loads((archive_dir / "uq.json").read_text())  # re-read: another job may have merged meanwhile
    # the regimes belong to the archived run (same parameters): its training time, not the retraining's
    train_s = json.loads((archive_dir / "metrics.json").read_text()).get("train_time_s")
    have.update({k: {**v, "train_time_s": train_s} if isinstance(v, dict) and "train_time_s" in v else v
                 for k, v in res.items() if k in names})
    write_json(archive_dir / "uq.json", have)


def run_row(args, scene: str, seed: int) -> Optional[str]:
    archive_dir = Path(args.archive) / scene / "niw" / f"s{seed}"
    names = [n for n in regime_names(args) if n not in read_json(archive_dir / "uq.json", {})]
    if not names:
        return None
    run_dir = Path(args.out) / scene / "niw" / f"s{seed}"
    over = scene_overrides(scene) + QUICK + [*model_overrides("niw"), f"seed={seed}", f"threads={args.threads}"]
    m = train_run(run_dir, over, timeout_s=4 * 3600)
    try:
        check_same_parameters(m, archive_dir / "metrics.json", f"{scene} s{seed}")
    except B3dgsError as e:
        return f"not merged: {e}"
    got = m["checkpoint"]["params_sha256"]
    import subprocess

    cmd, env = bench_child("counts", "--score-one", str(run_dir), str(archive_dir), str(args.samples),
                           str(args.threads), *names)
    res = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if res.returncode != 0:
        return f"{scene} s{seed}: scoring failed: {res.stderr[-1500:]}"
    print(f"{scene} s{seed}: merged {', '.join(names)} (parameters match the archive: {got})", flush=True)
    return None


def table(args) -> dict:
    """Macro means and paired differences from the archived uq.json files."""
    from b3dgs.report.collect import load_runs
    from b3dgs.report.ood import ood_study
    from b3dgs.report.stats import paired_stats

    runs = [r for r in load_runs([str(Path(args.archive))], on_duplicate="newest")[0]
            if r.scene in args.scenes and r.seed in args.seeds and r.method in ("niw", "standard")
            and r.study == "canonical"]
    niw = [r for r in runs if r.method == "niw"]
    ens = [r for r in runs if r.method == "standard" and "ensemble" in r.uq]
    regs = ["native"] + regime_names(args) + ["proxy", "constant", "ppu"]
    ood = ood_study(niw + ens, regimes=regs + ["ensemble"])
    per = {}  # regime -> scene -> metric -> {seed: value}
    for row in ood["runs"]:
        per.setdefault(row["regime"], {}).setdefault(row["scene"], {}).setdefault("auroc", {})[row["seed"]] = row["auroc"]
    for r, scored in [(r, regs) for r in niw] + [(r, ["ensemble"]) for r in ens]:
        for reg in scored:
            if reg in r.uq:
                for key, _ in COLUMNS:
                    v = r.value(key, reg)
                    if v is not None:
                        per.setdefault(reg, {}).setdefault(r.scene, {}).setdefault(key, {})[r.seed] = v
    means = {reg: {sc: {k: float(np.mean(list(v.values()))) for k, v in d.items()} for sc, d in by.items()}
             for reg, by in per.items()}
    metrics = [("auroc", True)] + COLUMNS
    macro = {reg: {k: (float(np.mean([d[k] for d in by.values() if k in d])) if any(k in d for d in by.values())
                       else None) for k, _ in metrics}
             | {"n_scenes": len(by), "n_runs": sum(max(len(v) for v in d.values()) for d in per[reg].values())}
             for reg, by in means.items()}
    paired = []
    for a in regime_names(args):
        for b in ("native", "ensemble", "constant"):
            for k, hi in metrics:
                # each scene is one unit: the mean over the seeds both regimes have (a count scored on seed 0 only is
                # paired with the other regime's seed 0, never with its 3-seed mean); the deep ensemble is one per
                # scene (its members are the standard runs of every seed), so it faces a's mean over all a's seeds
                d, n_seeds = {}, {}
                for sc in sorted(per.get(a, {})):
                    va, vb = per[a][sc].get(k, {}), per.get(b, {}).get(sc, {}).get(k, {})
                    if b in SCENE_LEVEL and va and vb:
                        d[sc] = float(np.mean(list(va.values())) - np.mean(list(vb.values())))
                        n_seeds[sc] = len(va)
                        continue
                    both = sorted(set(va) & set(vb))
                    if both:
                        d[sc] = float(np.mean([va[x] - vb[x] for x in both]))
                        n_seeds[sc] = len(both)
                if len(d) < 2:
                    continue
                st = paired_stats(list(d.values()), higher_is_better=hi)
                paired.append({"a": a, "b": b, "metric": k, "per_scene": d, "n_seeds": n_seeds, **st})
    # the grid's (scene, seed) units a regime has no score for (e.g. a run whose retraining did not reproduce)
    missing = {reg: [f"{sc} s{sd}" for sd in args.seeds for sc in args.scenes
                     if sd not in per.get(reg, {}).get(sc, {}).get("auroc", {})
                     and any(sd in per.get(reg, {}).get(x, {}).get("auroc", {}) for x in args.scenes)]
               for reg in regime_names(args)}
    return {"macro": macro, "per_scene": means, "paired": paired, "ood_skipped": ood["skipped"],
            "missing": {k: v for k, v in missing.items() if v}}


def write(args, res: dict, problems: list[str]) -> None:
    names = {"auroc": "OOD AUROC ↑", "ause_rmse": "AUSE ↓", "cov95_err": "\\|Cov@95 − 0.95\\| ↓", "nll": "NLL ↓",
             "epi_spearman_sq": "ρ(u, err²) ↑"}
    lines = ["# NIW counts on the canonical grid", "",
             f"{', '.join(args.scenes)} x seeds {' '.join(map(str, args.seeds))}; quick protocol; native regimes with "
             f"{args.samples} posterior samples at c = 1 (the canonical `native` is the paper's count; `native_sh` is "
             "`native` plus the directional SH posterior, plugins/posterior/sh.py; `native_plus_sh`, where scored, is "
             "today's `uq=native` at c = 0.1 plus that posterior); ensemble: the "
             "3-member deep ensemble of the standard runs; OOD: support-deficit AUROC of the per-view mean variance "
             "(ID = best-supported third of the test views, OOD = worst third). Macro means over scenes of seed means.",
             "", "| regime | " + " | ".join(names[k] for k in names) + " | scenes | runs |", "|---|" + "---|" * (len(names) + 2)]
    for reg, row in res["macro"].items():
        cells = ["—" if row.get(k) is None else f"{row[k]:.4g}" for k in names]
        lines.append(f"| {reg} | " + " | ".join(cells) + f" | {row['n_scenes']} | {row['n_runs']} |")
    lines += ["", "## Paired differences over scenes (a − b; each scene one unit: the mean over the seeds both have)", "",
              "| a | b | metric | mean Δ | 95 % CI | p (two-sided) | a better / worse | seeds | per scene |",
              "|---|---|---|---|---|---|---|---|---|"]
    for p in res["paired"]:
        ci = p["ci"]
        cis = "—" if ci.get("low") is None else f"[{ci['low']:+.3g}, {ci['high']:+.3g}]"
        pp = "—" if p["p_two_sided"] is None else f"{p['p_two_sided']:.3g}"
        signs = " ".join(f"{s[:10]}{'+' if v > 0 else '−' if v < 0 else '0'}" for s, v in p["per_scene"].items())
        ns = sorted(set(p["n_seeds"].values()))
        seeds = f"{ns[0]}" if len(ns) == 1 else f"{ns[0]}–{ns[-1]}"
        lines.append(f"| {p['a']} | {p['b']} | {names.get(p['metric'], p['metric'])} | {p['mean']:+.4g} | {cis} | {pp} | "
                     f"{p['wins']} / {p['losses']} | {seeds} | {signs} |")
    if res.get("missing"):
        lines += ["", "## Runs without a score (in a seed the regime was scored on)", ""]
        lines += [f"- {reg}: {', '.join(v)}" for reg, v in res["missing"].items()]
    if problems:
        lines += ["", "## Rows not merged", ""] + [f"- {x}" for x in problems]
    write_results("counts", {**res, "problems": problems, "samples": args.samples}, "\n".join(lines), args.results_root)
    print(f"wrote {Path(args.results_root) / 'counts.md'}")


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--score-one":  # internal: one run's scoring in its own process
        import torch

        run_dir, archive_dir, samples, threads, *names = sys.argv[2:]
        torch.set_num_threads(int(threads))
        score_one(Path(run_dir), Path(archive_dir), names, int(samples))
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=SEVEN)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--counts", nargs="+", default=COUNTS, choices=COUNTS,
                    help="variants to score, as uq=[native_<name>] (sh: the directional SH posterior added to native)")
    ap.add_argument("--alone", nargs="*", default=ALONE, choices=ALONE_CHOICES,
                    help="uq regimes scored under their own name (sh: the SH posterior without the NIW geometry; "
                         "native_plus_sh: uq=native at c = 0.1 plus the SH posterior)")
    ap.add_argument("--samples", type=int, default=50)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="outputs/bench_counts")
    ap.add_argument("--archive", default=str(RESULTS / "runs"))
    ap.add_argument("--table-only", action="store_true")
    ap.add_argument("--results-root", default=str(RESULTS), help="where counts.{json,md} go (default bench/results)")
    args = ap.parse_args()
    problems: list[str] = []
    if not args.table_only:
        rows = [(scene, seed) for seed in args.seeds for scene in args.scenes]
        with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as ex:
            for p in ex.map(lambda r: run_row(args, *r), rows):
                if p:
                    print("PROBLEM", p, flush=True)
                    problems.append(p)
    write(args, table(args), problems)


if __name__ == "__main__":
    main()
