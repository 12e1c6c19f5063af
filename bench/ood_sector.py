"""OOD with a real support deficit (issue 42): do the regimes' per-view uncertainty, and the information a held-out
view would give the SH posterior, single out a held-out sector from views between the training cameras?

    python -m bench.ood_sector --jobs 2 --threads 1        # 7 scenes, seed 0; resumable from the archive
    python -m bench.ood_sector --scenes fox --seeds 0
    python -m bench.ood_sector --table-only                # the table from the archive, on any machine

Protocol: ``experiment=study`` with ``data.test_split=sector+interleaved``: one model per scene and seed holds out a
contiguous sector of 1/8 of the cameras (OOD: no training camera looks from there) and every 8th view of the rest (ID:
between training views), so both kinds of held-out view are scored by the same model. Per scene and seed: the NIW run
(its training is standard's: NIW only observes) with uq.json for ``--regimes``, the deep ensemble of the standard runs
of ``--ensemble-seeds``, and the information each held-out view would add to the SH posterior
(``acquisition=info_gain``: ``params``, the BALD/FisherRF-style gain; ``predictive`` with the held-out views as
targets), COVER's uncovered share and the distance to the nearest training camera (the trivial detector).

Per detector: AUROC for sector (positive) against interleaved views of one model, per scene (seed mean), macro mean
over scenes, and paired against the ensemble and the distance (sign-flip p over scenes). Beside it, the interleaved
split's support-deficit AUROC of the canonical runs (``bench/results/report/report.json``, the same regimes).
Every finished piece is archived (``--archive``, default ``bench/results/ood_sector_runs``: run configs, metrics,
uq.json, per-view scores), so the study resumes across sessions and ``--table-only`` rebuilds the table anywhere.
"""
from __future__ import annotations

import argparse
import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from bench.common import (QUICK, RESULTS, SECTOR_SPLIT, SEVEN, archive_files, model_overrides, read_json,
                          scene_names, scene_overrides, steps_overrides, threads_overrides, train_run, write_results)

REGIMES = ["proxy", "constant", "ppu", "native", "sh"]
SCORES = ["info_gain_params", "info_gain_predictive", "cover", "distance"]  # per held-out view, from the NIW run
ARCHIVED = ("config.yaml", "metrics.json", "curve.json", "uq.json")


def view_scores(run_dir: Path, score_max_side: int = 64) -> dict:
    """Per held-out view of the run: its kind (sector / interleaved), the distance from its centre to the nearest
    training camera over the scene extent, and the acquisition scores of ``SCORES`` (the model's point estimate)."""
    import torch

    from b3dgs.acquisition import ScoringContext
    from b3dgs.neighbours import nearest_distances
    from b3dgs.runs import load_run
    from b3dgs_plugins.acquisition.cover import CoverPolicy
    from b3dgs_plugins.acquisition.info_gain import InfoGainPolicy

    run = load_run(run_dir)
    scene, test = run.scene, list(run.scene.test)
    groups = getattr(scene, "test_groups", None)
    if not groups:
        from b3dgs.errors import B3dgsError

        raise B3dgsError(f"{run_dir}: the run's scene has no sector and interleaved test views",
                         "train it with data.test_split=sector+interleaved")
    kind = {n: k for k, names in groups.items() for n in names}
    cen = lambda cams: np.stack([c.center.double().cpu().numpy() for c in cams])  # noqa: E731
    dist = nearest_distances(cen(test), cen(scene.train)) / (scene.extent if scene.extent > 0 else 1.0)
    ctx = ScoringContext([run.module], scene.train, score_max_side=score_max_side, extent=scene.extent, seed=0)
    with torch.no_grad():
        scores = {"info_gain_params": InfoGainPolicy(objective="params").score(ctx, test),
                  "info_gain_predictive": InfoGainPolicy(objective="predictive").score(ctx, test),
                  "cover": CoverPolicy().score(ctx, test)}
    return {"views": [{"name": c.name, "kind": kind[c.name], "distance": float(d),
                       **{k: float(v[i]) for k, v in scores.items()}} for i, (c, d) in enumerate(zip(test, dist))],
            "score_max_side": score_max_side}


def _auroc(pos: list[float], neg: list[float]):
    from sklearn.metrics import roc_auc_score

    if not pos or not neg:
        return None
    return float(roc_auc_score([1] * len(pos) + [0] * len(neg), list(pos) + list(neg)))


def scene_aurocs(archive: Path, scene: str, seed: int) -> dict:
    """{detector: AUROC of sector against interleaved views} for one scene and seed, from the archive."""
    views = read_json(archive / scene / f"views_s{seed}.json")
    if views is None:
        return {}
    kind = {v["name"]: v["kind"] for v in views["views"]}
    out = {}
    for det in SCORES:
        out[det] = _auroc([v[det] for v in views["views"] if v["kind"] == "sector"],
                          [v[det] for v in views["views"] if v["kind"] == "interleaved"])
    uq_files = {f"niw ({r})": (archive / scene / "niw" / f"s{seed}" / "uq.json", r) for r in REGIMES}
    uq_files["standard (ensemble)"] = (archive / scene / "ensemble" / "uq.json", "ensemble")
    for label, (path, regime) in uq_files.items():
        entry = (read_json(path) or {}).get(regime)
        if not entry:
            continue
        pv = {v["name"]: v["mean_var"] for v in entry.get("per_view") or [] if isinstance(v.get("mean_var"), (int, float))}
        out[label] = _auroc([u for n, u in pv.items() if kind.get(n) == "sector"],
                            [u for n, u in pv.items() if kind.get(n) == "interleaved"])
    return out


def interleaved_aurocs(report_json: Path, seeds: list[int]) -> dict:
    """{(scene, row): mean AUROC over ``seeds``} of the canonical runs' support-deficit study (interleaved split)."""
    rep = read_json(report_json) or {}
    acc: dict = {}
    for r in (rep.get("ood") or {}).get("runs", []):
        if r.get("seed") in seeds and r.get("auroc") is not None:
            acc.setdefault((r["scene"], r["row"]), []).append(r["auroc"])
    return {k: float(np.mean(v)) for k, v in acc.items()}


def table(archive: Path, scenes: list[str], seeds: list[int]) -> tuple[dict, str]:
    from b3dgs.report.stats import paired_stats

    per = {}  # detector -> scene -> seed-mean AUROC
    for sc in scenes:
        rows: dict = {}
        for s in seeds:
            for det, a in scene_aurocs(archive, sc, s).items():
                if a is not None:
                    rows.setdefault(det, []).append(a)
        for det, v in rows.items():
            per.setdefault(det, {})[sc] = float(np.mean(v))
    inter = interleaved_aurocs(RESULTS / "report" / "report.json", seeds)
    order = [f"niw ({r})" for r in REGIMES] + ["standard (ensemble)"] + SCORES
    lines = ["# OOD with a real support deficit: a held-out sector against views between training cameras", "",
             "`python -m bench.ood_sector` (data.test_split=sector+interleaved, experiment=study, seeds "
             f"{', '.join(map(str, seeds))}). AUROC of each detector for sector (positive) against interleaved held-out "
             "views of one model, per scene (seed mean); `interleaved split` is the canonical runs' support-deficit "
             "AUROC over the same scenes (best- against worst-supported third of the every-8th test views, "
             "bench/results/report). "
             "Paired: AUROC difference over scenes, exact sign-flip p.", "",
             "| detector | scenes | sector AUROC (macro) | interleaved split (macro) | − ensemble | p | − distance | p | "
             + " | ".join(scenes) + " |",
             "|---|---|---|---|---|---|---|---|" + "---|" * len(scenes)]
    payload = {"scenes": scenes, "seeds": seeds, "per_scene": per, "rows": {}}
    for det in [d for d in order if d in per]:
        vals = per[det]
        iv = [inter[(sc, det)] for sc in vals if (sc, det) in inter]  # the same scenes as the sector column
        row = {"n": len(vals), "macro": float(np.mean(list(vals.values()))),
               "interleaved_macro": float(np.mean(iv)) if iv else None}
        cells = []
        for base in ("standard (ensemble)", "distance"):
            common = [sc for sc in scenes if sc in vals and sc in per.get(base, {})]
            if det == base or len(common) < 2:
                cells += ["", ""]
                continue
            st = paired_stats([vals[sc] - per[base][sc] for sc in common])
            row[f"minus_{base}"] = st
            cells += [f"{st['mean']:+.3f} ({st['wins']}/{st['losses']})", f"{st['p_two_sided']:.3g}"]
        payload["rows"][det] = row
        fmt = lambda x: "" if x is None else f"{x:.3f}"  # noqa: E731
        lines.append(f"| {det} | {row['n']} | {row['macro']:.3f} | {fmt(row['interleaved_macro'])} | "
                     + " | ".join(cells) + " | " + " | ".join(fmt(vals.get(sc)) for sc in scenes) + " |")
    lines += ["", "Detectors: `niw (regime)` the per-view mean predictive variance of each uq.json regime of the NIW "
              "run; `standard (ensemble)` the deep ensemble's; `info_gain_params` / `info_gain_predictive` the "
              "information the view would add to the SH posterior (acquisition=info_gain; predictive: the held-out "
              "views as targets); `cover` COVER's uncovered share; `distance` the nearest training camera over the "
              "scene extent."]
    return payload, "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=SEVEN, choices=scene_names())
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--ensemble-seeds", type=int, nargs="+", default=[0, 1, 2],
                    help="the seeds of the standard runs forming each scene's deep ensemble")
    ap.add_argument("--regimes", nargs="+", default=REGIMES)
    ap.add_argument("--uq-samples", type=int, default=50)
    ap.add_argument("--out", default="outputs/bench/ood_sector")
    ap.add_argument("--archive", default=str(RESULTS / "ood_sector_runs"))
    ap.add_argument("--name", default="ood_sector", help="bench/results/<name>.{json,md}")
    ap.add_argument("--max-steps", type=int, default=None, help="override the quick protocol's steps (smoke tests)")
    ap.add_argument("--extra", nargs="*", default=[], help="extra Hydra overrides for every run")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--results-root", default=str(RESULTS))
    ap.add_argument("--table-only", action="store_true")
    args = ap.parse_args()
    out, archive = Path(args.out), Path(args.archive)
    protocol, threads = list(QUICK) + SECTOR_SPLIT + steps_overrides(args.max_steps), threads_overrides(args.threads)

    def run_dir(scene, method, seed):
        return out / scene / method / f"s{seed}"

    def complete(scene):
        return (archive / scene / "ensemble" / "uq.json").is_file() and all(
            (archive / scene / f"views_s{s}.json").is_file() and (archive / scene / "niw" / f"s{s}" / "uq.json").is_file()
            for s in args.seeds)

    def one_scene(sc):
        """Trains what the scene lacks here (a run finished here is reused), then its scores and ensemble: the
        scene's pieces need the checkpoints, so a scene is archived as a whole once all of them exist."""
        from b3dgs.io import write_json
        from bench.studies import ensure_ensemble, ensure_regimes

        runs = [("niw", s) for s in args.seeds] + [("standard", s) for s in args.ensemble_seeds]
        for m, s in runs:
            d = run_dir(sc, m, s)
            met = train_run(d, scene_overrides(sc) + protocol + model_overrides(m) + [f"seed={s}"] + args.extra + threads)
            if m == "niw":
                ensure_regimes(d, args.regimes, args.uq_samples, s)
            archive_files(d, archive / sc / m / f"s{s}", ARCHIVED)
            print(f"{sc} {m} s{s}: PSNR {met['psnr']:.3f}, {met['train_time_s']:.0f} s", flush=True)
        for s in args.seeds:
            write_json(archive / sc / f"views_s{s}.json", view_scores(run_dir(sc, "niw", s)))
        ens = out / sc / "ensemble"
        ensure_ensemble([run_dir(sc, "standard", e) for e in args.ensemble_seeds], ens)
        write_json(archive / sc / "ensemble" / "uq.json", json.loads((ens / "uq.json").read_text()))
        print(f"{sc}: held-out view scores and the ensemble of {len(args.ensemble_seeds)} standard runs", flush=True)

    if not args.table_only:
        todo = [sc for sc in args.scenes if not complete(sc)]
        print(f"{len(args.scenes)} scenes, {len(args.scenes) - len(todo)} complete in {archive}, {len(todo)} to do",
              flush=True)
        with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as ex:
            list(ex.map(one_scene, todo))
    payload, text = table(archive, args.scenes, args.seeds)
    write_results(args.name, payload, text, root=Path(args.results_root))


if __name__ == "__main__":
    main()
