"""Does ``b3dgs-suggest`` point at what the capture lacks (issue 54 §3)? Suggestions on the held-out-sector split: where
they point (hit rate) and what adding the nearest real views gains (outcome).

    python -m bench.suggest --seeds 0 1 2                  # 7 scenes x 3 seeds; resumable from the archive
    python -m bench.suggest --scenes fox --seeds 0 --max-steps 60 --n 4 --name suggest_smoke   # a smoke run
    python -m bench.suggest --table-only                   # the table from the archive, on any machine

Protocol: ``experiment=study`` with ``data.test_split=sector+interleaved`` (as ``bench/ood_sector.py``): one standard
run per scene and seed holds out a contiguous sector of 1/8 of the cameras (no training camera looks from there) and
every 8th view of the rest. ``b3dgs-suggest run=RUN n=N policy=P`` for P in info_gain (greedy_conditioned), cover,
distance (farthest) and uniform, from the same generated candidates.

- **Hit rate**: the share of a policy's suggestions whose direction from the scene centre falls in the sector's angular
  range, i.e. whose nearest camera direction (over the training and held-out cameras, seen from the centre) is a sector
  camera's; **chance**: the same share over every candidate that was scored (those kept after the drops).
- **Outcome**: a policy's first K suggestions, in rank order, are snapped to the nearest (camera centre) real held-out
  camera not yet taken, so every policy adds K real views; the run is retrained from scratch on the training views plus
  those, and PSNR / LPIPS are taken on the sector views and on all held-out views that no policy added (one evaluation
  set for every policy of a scene and seed). ``none`` is the run without added views on the same sets. K is N, or fewer
  where the held-out views are few (:func:`views_added`: all policies' added views together take at most half of
  them, so the rest can score them); a scene and seed where no sector view is left is recorded as skipped.

Per policy: macro means over scenes (seed means), and paired over scenes (``b3dgs.report.stats.paired_stats``: exact
sign-flip p): info_gain hit rate − chance, − distance, − cover; outcome deltas info_gain − uniform, − distance, − cover.
Every finished piece is archived (``--archive``, default ``bench/results/suggest_runs``: the base run's config and
metrics, each policy's suggest.json, the hits and each retrained row's metrics), so the campaign resumes across sessions
and ``--table-only`` rebuilds the table anywhere.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from bench.common import (QUICK, RESULTS, SECTOR_SPLIT, SEVEN, archive_files, check_same_parameters, model_overrides,
                          read_json, scene_names, scene_overrides, steps_overrides, threads_overrides, train_run,
                          write_results)

POLICIES = {"info_gain": "info_gain", "cover": "cover", "distance": "farthest", "uniform": "uniform"}
ARCHIVED = ("config.yaml", "metrics.json")


def _centres(cams) -> np.ndarray:
    return np.stack([c.center.double().cpu().numpy() for c in cams])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def in_sector(directions: np.ndarray, centre: np.ndarray, scene) -> np.ndarray:
    """(K,) bool: whether each unit direction from ``centre`` is nearest (largest cosine) to a sector camera's direction
    among the training and held-out cameras' (the sector's angular range, however it is shaped)."""
    cams = list(scene.train) + list(scene.test)
    sector = set(scene.test_groups["sector"])
    dirs = _unit(_centres(cams) - centre)
    near = np.argmax(np.asarray(directions, np.float64) @ dirs.T, axis=1)
    return np.array([cams[i].name in sector for i in near], dtype=bool)


def hits(rec: dict, scene) -> dict:
    """Hit rate of one suggest.json and the chance share of its scored candidates."""
    centre = np.asarray(rec["centre"], np.float64)
    sug = np.asarray([s["direction"] for s in rec["suggestions"]], np.float64)
    cand = np.asarray(list(rec["candidate_directions"].values()), np.float64)
    return {"n": len(sug), "hit_rate": float(in_sector(sug, centre, scene).mean()),
            "chance": float(in_sector(cand, centre, scene).mean()), "candidates": len(cand)}


def views_added(n: int, held_out: int, policies: int) -> int:
    """The views each policy adds (K): ``n``, or fewer so that the ``policies``' added views together take at most half
    of the ``held_out`` views; at least 1."""
    return max(1, min(n, held_out // (2 * policies)))


def snap(rec: dict, scene, n: int) -> list[str]:
    """The held-out cameras nearest (camera centre) to the suggestions in rank order, each taken once."""
    test = list(scene.test)
    tc = _centres(test)
    taken: list[str] = []
    for s in rec["suggestions"][:n]:
        c = -np.asarray(s["viewmat"])[:3, :3].T @ np.asarray(s["viewmat"])[:3, 3]
        order = np.argsort(np.linalg.norm(tc - c, axis=1))
        taken.append(next(test[i].name for i in order if test[i].name not in taken))
    return taken


def _metrics(module, views: dict, eval_sets: dict) -> dict:
    from b3dgs.metrics.lpips import get_lpips
    from b3dgs.metrics.views import evaluate_views

    lp, _ = get_lpips()
    module.eval()
    out = {}
    for name, names in eval_sets.items():
        m = evaluate_views(module, [views[v] for v in names], lpips_model=lp, with_ssim=False)
        out[name] = {"psnr": m.get("psnr"), "lpips": m.get("lpips"), "views": len(names)}
    return out


def evaluate(run_dir: Path, eval_sets: dict) -> dict:
    """The finished run's metrics on each of ``eval_sets`` (nothing added)."""
    from b3dgs.runs import load_run

    run = load_run(run_dir)
    return {"added": [], **_metrics(run.module, {c.name: c for c in run.scene.test}, eval_sets)}


def retrain(overrides: list[str], added: list[str], eval_sets: dict, run_dir: Path) -> dict:
    """Train from scratch on the training views plus ``added`` (held-out views, with their images), then PSNR / SSIM
    / LPIPS on each of ``eval_sets`` (name -> held-out view names)."""
    from dataclasses import replace

    from b3dgs.lifecycle import data_module
    from b3dgs.study.active import compose_config
    from b3dgs.study.rounds import fit_round

    cfg = compose_config("train", overrides)
    scene = data_module(cfg.data).scene
    by = {c.name: c for c in scene.test}
    grown = replace(scene, train=list(scene.train) + [by[n] for n in added],
                    test=[c for c in scene.test if c.name not in set(added)])
    import shutil

    from b3dgs.io import write_json

    last, tag = run_dir / "checkpoints" / "last.ckpt", run_dir / "added.json"
    if run_dir.exists() and read_json(tag) != list(added):  # a run of other added views: never resumed, trained again
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    write_json(tag, list(added))
    module = fit_round(cfg, grown, run_dir, int(cfg.trainer.max_steps), ckpt_path=str(last) if last.is_file() else None)
    return {"added": list(added), **_metrics(module, by, eval_sets)}


def table(archive: Path, scenes: list[str], seeds: list[int]) -> tuple[dict, str]:
    from b3dgs.report.stats import paired_stats

    hit, out, shape, skipped = {}, {}, {}, []  # policy -> scene -> seed mean; scene -> (K, sector, all) per seed
    for sc in scenes:
        acc_h: dict = {}
        acc_o: dict = {}
        for s in seeds:
            for pol, h in (read_json(archive / sc / f"s{s}" / "hits.json") or {}).items():
                acc_h.setdefault(pol, []).append((h["hit_rate"], h["chance"]))
            if (archive / sc / f"s{s}" / "outcome_skipped.json").is_file():
                skipped.append(f"{sc} s{s}")
            recs = {pol: read_json(archive / sc / f"s{s}" / f"outcome_{pol}.json") for pol in [*POLICIES, "none"]}
            # a scene-seed's outcome counts once every policy's record of the K rule (views_added; older ones
            # superseded) is in, so that the policies are compared on the same seeds while a campaign runs
            if all(r is not None and "views_added" in r for r in recs.values()):
                for pol, r in recs.items():
                    acc_o.setdefault(pol, []).append([r[k][m] for k in ("sector", "all") for m in ("psnr", "lpips")])
                    shape.setdefault(sc, {})[s] = (r["views_added"], len(r["eval_sector"]), len(r["eval_all"]))
        for pol, v in acc_h.items():
            hit.setdefault(pol, {})[sc] = np.mean(np.asarray(v), axis=0).tolist()
        for pol, v in acc_o.items():
            out.setdefault(pol, {})[sc] = np.mean(np.asarray(v, dtype=float), axis=0).tolist()
    lines = ["# Where to take the next photos: b3dgs-suggest on the held-out-sector split", "",
             f"`python -m bench.suggest` (data.test_split=sector+interleaved, experiment=study, seeds "
             f"{', '.join(map(str, seeds))}). Hit rate: share of suggestions pointing into the held-out sector (nearest "
             "camera direction from the scene centre is a sector camera's); chance: that share over the scored "
             "candidates. Macro over scenes (seed means); paired over scenes, exact sign-flip p.", "",
             "| policy | scenes | hit rate | chance | hit − chance | p | " + " | ".join(scenes) + " |",
             "|---|---|---|---|---|---|" + "---|" * len(scenes)]
    payload: dict = {"scenes": scenes, "seeds": seeds, "hit": hit, "outcome": out, "paired": {}}
    for pol in [p for p in POLICIES if p in hit]:
        v = hit[pol]
        st = paired_stats([v[sc][0] - v[sc][1] for sc in v]) if len(v) >= 2 else None
        payload["paired"][f"{pol} hit − chance"] = st
        lines.append(f"| {pol} | {len(v)} | {np.mean([x[0] for x in v.values()]):.3f} | "
                     f"{np.mean([x[1] for x in v.values()]):.3f} | "
                     + (f"{st['mean']:+.3f} ({st['wins']}/{st['losses']}) | {st['p_two_sided']:.3g} | " if st else " | | ")
                     + " | ".join("" if sc not in v else f"{v[sc][0]:.2f}/{v[sc][1]:.2f}" for sc in scenes) + " |")
    lines += ["", "| paired (hit rate) | n | mean | wins/losses | p |", "|---|---|---|---|---|"]
    for base in ("distance", "cover"):
        common = [sc for sc in scenes if sc in hit.get("info_gain", {}) and sc in hit.get(base, {})]
        if len(common) >= 2:
            st = paired_stats([hit["info_gain"][sc][0] - hit[base][sc][0] for sc in common])
            payload["paired"][f"info_gain − {base} (hit rate)"] = st
            lines.append(f"| info_gain − {base} | {st['n']} | {st['mean']:+.3f} | {st['wins']}/{st['losses']} | "
                         f"{st['p_two_sided']:.3g} |")
    lines += ["", "Outcome: each policy's first K suggestions snapped to the nearest unused held-out camera, added, retrained "
              "from scratch; metrics on the sector views and on all held-out views no policy added (`none`: nothing "
              "added). K is N, or fewer where the held-out views are few (all policies' added views take at most half "
              "of them); per scene below.",
              "", "| policy | scenes | sector PSNR | sector LPIPS | all PSNR | all LPIPS |", "|---|---|---|---|---|---|"]
    for pol in [p for p in [*POLICIES, "none"] if p in out]:
        m = np.mean(np.asarray(list(out[pol].values())), axis=0)
        lines.append(f"| {pol} | {len(out[pol])} | {m[0]:.3f} | {m[1]:.4f} | {m[2]:.3f} | {m[3]:.4f} |")
    lines += ["", "| paired (outcome) | metric | n | mean | wins/losses | p |", "|---|---|---|---|---|---|"]
    for base in ("uniform", "distance", "cover"):
        common = [sc for sc in scenes if sc in out.get("info_gain", {}) and sc in out.get(base, {})]
        if len(common) < 2:
            continue
        for j, (metric, hib) in enumerate((("sector PSNR", True), ("sector LPIPS", False), ("all PSNR", True),
                                           ("all LPIPS", False))):
            st = paired_stats([out["info_gain"][sc][j] - out[base][sc][j] for sc in common], higher_is_better=hib)
            payload["paired"][f"info_gain − {base} ({metric})"] = st
            lines.append(f"| info_gain − {base} | {metric} | {st['n']} | {st['mean']:+.4f} | {st['wins']}/{st['losses']} "
                         f"| {st['p_two_sided']:.3g} |")
    if shape:  # per scene: what was added and what scored it, and each policy's sector PSNR
        pols = [p for p in [*POLICIES, "none"] if p in out]
        lines += ["", "| scene | views added (K) | sector views scored | all views scored | sector PSNR: "
                  + " | ".join(pols) + " |", "|---|---|---|---|---" + "|---" * (len(pols) - 1) + "|"]
        for sc, per in shape.items():
            k, ns, na = (" / ".join(str(v[i]) for v in per.values()) for i in range(3))
            lines.append(f"| {sc} | {k} | {ns} | {na} | "
                         + " | ".join("" if sc not in out[p] else f"{out[p][sc][0]:.2f}" for p in pols) + " |")
    payload["outcome_shape"], payload["outcome_skipped"] = shape, skipped
    if skipped:
        lines += ["", "Outcome skipped (no sector view left to score): " + ", ".join(skipped) + "."]
    return payload, "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=SEVEN, choices=scene_names())
    ap.add_argument("--seeds", type=int, nargs="+", default=None,
                    help="default: 0 to run; the table: every seed in the archive")
    ap.add_argument("--n", type=int, default=8, help="suggestions per policy (and views added)")
    ap.add_argument("--policies", nargs="+", default=list(POLICIES), choices=list(POLICIES))
    ap.add_argument("--suggest-extra", nargs="*", default=[], help="extra b3dgs-suggest overrides (e.g. score_max_side=32)")
    ap.add_argument("--no-outcome", action="store_true", help="the hit rates only (no retraining)")
    ap.add_argument("--out", default="outputs/bench/suggest")
    ap.add_argument("--archive", default=str(RESULTS / "suggest_runs"))
    ap.add_argument("--name", default="suggest", help="bench/results/<name>.{json,md}")
    ap.add_argument("--max-steps", type=int, default=None, help="override the quick protocol's steps (smoke tests)")
    ap.add_argument("--extra", nargs="*", default=[], help="extra Hydra overrides for every training")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--results-root", default=str(RESULTS))
    ap.add_argument("--table-only", action="store_true")
    args = ap.parse_args()
    out, archive = Path(args.out), Path(args.archive)
    steps, threads = steps_overrides(args.max_steps), threads_overrides(args.threads)

    def one(sc: str, seed: int) -> None:
        from b3dgs.io import write_json
        from b3dgs.runs import load_run

        overrides = scene_overrides(sc) + list(QUICK) + SECTOR_SPLIT + model_overrides("standard") + steps + \
            [f"seed={seed}"] + args.extra + threads
        base = out / sc / "base" / f"s{seed}"
        arch = archive / sc / f"s{seed}"
        met = train_run(base, overrides)
        check_same_parameters(met, arch / "base" / "metrics.json", f"{sc} s{seed} base")  # suggestions came from it
        archive_files(base, arch / "base", ARCHIVED)
        print(f"{sc} s{seed}: base PSNR {met['psnr']:.3f}", flush=True)
        recs = {}
        for pol in args.policies:
            f = arch / f"suggest_{pol}.json"
            if not f.is_file():
                d = out / sc / f"s{seed}" / f"suggest_{pol}"
                cmd = [sys.executable, "-m", "b3dgs.suggest", f"run={base}", f"policy={POLICIES[pol]}", f"n={args.n}",
                       f"seed={seed}", f"out={d}", *threads, *args.suggest_extra]
                res = subprocess.run(cmd, capture_output=True, text=True, timeout=7200)
                if res.returncode != 0:
                    raise RuntimeError(f"b3dgs-suggest failed ({' '.join(cmd)}):\n{res.stderr[-3000:]}")
                write_json(f, json.loads((d / "suggest.json").read_text()))
            recs[pol] = json.loads(f.read_text())
        scene = load_run(base).scene
        write_json(arch / "hits.json", {pol: hits(r, scene) for pol, r in recs.items()})
        print(f"{sc} s{seed}: hit rates " + ", ".join(f"{p} {hits(r, scene)['hit_rate']:.2f}" for p, r in recs.items()),
              flush=True)
        if args.no_outcome:
            return
        k = views_added(args.n, len(scene.test), len(recs))
        added = {pol: snap(r, scene, k) for pol, r in recs.items()}
        used = set().union(*added.values())
        sector = [n for n in scene.test_groups["sector"] if n not in used]
        every = [c.name for c in scene.test if c.name not in used]
        if not sector:
            write_json(arch / "outcome_skipped.json", {"views_added": k, "added": added, "reason": (
                f"the {k} view(s) each policy adds take every sector view ({len(scene.test_groups['sector'])})")})
            print(f"{sc} s{seed}: outcome skipped, no sector view left to score", flush=True)
            return
        for pol in [*args.policies, "none"]:
            f = arch / f"outcome_{pol}.json"
            prev = read_json(f)
            if prev is not None and prev.get("eval_sector") == sector and prev.get("eval_all") == every:
                continue
            sets = {"sector": sector, "all": every}
            r = evaluate(base, sets) if pol == "none" else retrain(overrides, added[pol], sets,
                                                                   out / sc / f"s{seed}" / f"train_{pol}")
            write_json(f, {**r, "views_added": k, "eval_sector": sector, "eval_all": every})
            print(f"{sc} s{seed} {pol}: sector PSNR {r['sector']['psnr']:.3f}, all {r['all']['psnr']:.3f}", flush=True)

    if not args.table_only:
        for sc in args.scenes:
            for s in args.seeds or [0]:
                one(sc, s)
    seeds = args.seeds or sorted({int(p.name[1:]) for p in archive.glob("*/s*") if p.name[1:].isdigit()}) or [0]
    payload, text = table(archive, args.scenes, seeds)
    write_results(args.name, payload, text, root=Path(args.results_root))


if __name__ == "__main__":
    main()
