"""The active-view study (``b3dgs-study active``) on the shared scenes, and its cross-scene table.

    python -m bench.active_view                              # the seven scenes, seeds 0 1 2, quick protocol
    python -m bench.active_view --aggregate-only             # only rebuild the tables and plots
    python -m bench.active_view --scenes fox --seeds 0 --jobs 1
    python -m bench.active_view --scenes ethiopian_head fox lego fern flower dtu_scan24 dtu_scan65 --seeds 0
    python -m bench.active_view --smoke                      # the embedded scene, tiny protocol (minutes)

Budget ladders: scenes with at least 40 train views run 16 -> 32 (``bench/results/active_view.md``);
smaller ones (fern, flower) run 8 -> 16 (``initial_views=8 acquire=8``) and get their own table
(``bench/results/active_view_8to16.md``): the two ladders are never pooled.

Batch options: ``--batches topk greedy_conditioned diverse`` (the default) gives every score-based
policy a row per option (``native+greedy_conditioned``, ``ensemble+diverse``, ...); the topk rows are the
rows the study always had. ``--batches topk`` runs only those.

One worker per scene (``--jobs`` scenes at a time, ``threads=1`` each, so two scenes use the two cores);
its seeds run one after another (the seeds of one scene share phase-1 models, so they never run at once).
Every study is resumable (finished rows are never retrained), so an interrupted run of this script
picks up where it stopped; the rows' small files are copied to ``--archive`` (default
bench/results/active_view_runs/, committed) every minute and restored at the start, so the study resumes on another
machine too (phase-1 models of unfinished rows are retrained there). Writes ``bench/results/active_view.{json,md}`` and
``bench/results/active_view/`` (per-scene study.md, plots, and the cross-scene plots).
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from omegaconf import OmegaConf

from b3dgs.io import save_figure, write_json
from b3dgs.report.document import fmt, markdown_table
from b3dgs.report.stats import mean_sem, p_floor, sign_flip_p

from bench.common import (ARCHIVED_FAMILY_POSTERIOR, RESULTS, ROOT, compose, machine, n_train_views, PeriodicSync,
                          pyplot, read_json, restore, scene_names, scene_overrides, sync_results, write_results)

STUDY_SCENES = list(OmegaConf.load(ROOT / "conf" / "report.yaml").studies.scenes)
NAME = "active_view"

# The paper's Table 2 (13 scenes x 3 seeds, 16 -> 32 views, 10k + 20k iterations on a GPU): PSNR, SSIM, LPIPS, time.
PAPER = {"uniform": (19.940, 0.6307, 0.3485, 873.9), "ensemble": (20.389, 0.6367, 0.3428, 1531.2),
         "ppu": (20.487, 0.6457, 0.3376, 960.9), "uniform@niw": (20.011, 0.6305, 0.3486, 1009.2),
         "proxy": (20.441, 0.6519, 0.3341, 888.7), "native": (20.842, 0.6577, 0.3282, 1233.1)}
PAPER_PAIRED = {"native-ensemble": "+0.453 (29/39 scene-seeds, 10/13 scenes)", "native-proxy": "+0.401",
                "native-ppu": "+0.355", "ensemble-uniform": "+0.449"}
PAIRS = (("native", "ensemble"), ("native", "proxy"), ("native", "ppu"), ("native", "uniform@niw"),
         ("ensemble", "uniform"), ("fisher", "ensemble"), ("farthest", "uniform"), ("oracle", "uniform"),
         # batch selection: does batch-aware native beat (a) top-k native, (b) the ensemble, (c) farthest?
         ("native+greedy_conditioned", "native"), ("native+greedy_conditioned", "ensemble"),
         ("native+greedy_conditioned", "farthest"), ("native+greedy_conditioned", "native+diverse"),
         ("native+diverse", "native"), ("native+diverse", "farthest"), ("ensemble+diverse", "ensemble"),
         ("proxy+diverse", "proxy"), ("ppu+diverse", "ppu"), ("oracle+diverse", "oracle"), ("oracle+diverse", "farthest"))
STUDY_PAIRS = (*PAIRS[:2], *PAIRS[8:11], PAIRS[12])  # the per-scene tables' pairs when the campaign ran
PAPER_JACCARD = {"native|proxy": 0.056, "native|ensemble": 0.059}
ORDER = ("uniform", "farthest", "ensemble", "ppu", "fisher", "uniform@niw", "proxy", "native", "oracle")
BATCHES = ("topk", "greedy_conditioned", "diverse")  # a policy's batch rows follow its top-k row in this order


def row_order(table: dict) -> list[str]:
    """Table 2's order: standard rows, NIW rows, then the oracle; other policies after their family's; a
    policy's batch rows (``native+diverse``) right after its top-k row."""
    def key(p):
        base, _, batch = p.partition("+")
        return (table[p]["oracle"], table[p]["family"] != "standard", ORDER.index(base) if base in ORDER else len(ORDER),
                base, BATCHES.index(batch) if batch in BATCHES else (0 if not batch else len(BATCHES)), p)

    return sorted(table, key=key)


# Budget ladders: a scene needs more train views than initial + acquired for the candidates to leave a
# choice; scenes with fewer than MIN_VIEWS_16_32 train views (fern 17, flower 21 of the seven) run 8 -> 16 and are
# reported in their own table (bench/results/active_view_8to16.md), never pooled with the 16 -> 32 scenes.
LADDERS = {"16to32": (16, 16), "8to16": (8, 8)}
MIN_VIEWS_16_32 = 40


def ladder_of(n_train: int) -> str:
    """The budget ladder of a scene with n_train training views."""
    return "16to32" if n_train >= MIN_VIEWS_16_32 else "8to16"


def scene_ladders(scenes: list[str]) -> dict[str, str]:
    """scene -> its ladder, from the scene's training-view count (loads each scene's cameras once)."""
    return {sc: ladder_of(n_train_views(scene_overrides(sc))) for sc in scenes}


def _mean(v: list) -> float | None:
    return float(np.mean(v)) if v else None


def run_scene(scene: str, seeds: list[int], study_out: Path, extra: list[str], score_side: str = "64",
              scene_args: list[str] | None = None) -> dict:
    """Run the study for ``scene``, one seed after another; returns {seed: wall seconds} of the seeds run.
    ``scene_args``: the data overrides (default ``scene=<scene>``)."""
    logs = study_out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    walls = {}
    for seed in seeds:
        cmd = [sys.executable, "-m", "b3dgs.study.active", "active",
               *(scene_args or scene_overrides(scene)), "renderer=cpu", f"seeds=[{seed}]",
               f"out_dir={study_out}", "threads=1", f"acquisition.score_max_side={score_side}",
               ARCHIVED_FAMILY_POSTERIOR, *extra]
        t0 = time.perf_counter()
        with open(logs / f"{scene}_s{seed}.log", "a") as log:
            r = subprocess.run(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
        walls[seed] = time.perf_counter() - t0
        print(f"{scene} s{seed}: exit {r.returncode}, {walls[seed] / 60:.1f} min (log {logs / f'{scene}_s{seed}.log'})",
              flush=True)
        if r.returncode != 0:
            raise SystemExit(f"the study failed on {scene} seed {seed}: see {logs / f'{scene}_s{seed}.log'}")
    return walls


def compute_per_seed(out: Path, scene_summary: dict) -> dict:
    """Compute each seed of one scene costs: the phase-1 models it is the first to use (the ensemble's
    members s+1, s+2 are charged to the first seed that needs them), every row's second round (a shared
    row costs nothing) and its scoring. Evaluation time is not recorded per row and is left out."""
    charged: set = set()
    res = {}
    for seed in scene_summary["seeds"]:
        rows = [r for r in scene_summary["runs"] if int(r["seed"]) == seed]
        p1 = 0.0
        for r in rows:
            for i in range(int(r.get("members", 1))):
                key = (r["family"], seed + i)
                path = out / "phase1" / f"{key[0]}_s{key[1]}" / "phase1.json"
                if key not in charged and path.exists():
                    charged.add(key)
                    p1 += float(json.loads(path.read_text())["train_time_s"])
        r2 = sum(float(r.get("round2_time_s") or 0) for r in rows if not r.get("training_shared_with"))
        sc = sum(float(r.get("scoring_time_s") or 0) for r in rows)
        res[seed] = {"phase1_s": p1, "round2_s": r2, "scoring_s": sc, "total_s": p1 + r2 + sc, "rows": len(rows)}
    return res


def camera_geometry(scene: str, scene_args: list[str] | None = None) -> tuple[dict, float]:
    """{view name: camera centre} for the scene's train and test views (:attr:`Camera.center64`: the tables rebuild
    with the same bits on any CPU), and the scene extent."""
    from b3dgs.data.scene import poses_only
    from b3dgs.lifecycle import data_module

    cfg = compose("study", scene_args or scene_overrides(scene))
    with poses_only():
        dm = data_module(cfg.data)
    cams = list(dm.scene.train) + list(dm.scene.test)
    return {c.name: c.center64 for c in cams}, float(dm.scene.extent)


def support_distance(train: list[str], test: list[str], centres: dict, extent: float) -> float:
    """Mean over test views of the distance from its camera centre to the nearest training camera centre,
    / extent (the report's OOD support score, :func:`b3dgs.report.ood.support_distances`, averaged): how well
    the final training set covers the test views."""
    from b3dgs.report.ood import support_distances

    return float(np.mean(support_distances([centres[n] for n in train], [centres[n] for n in test], extent)))


def pick_spacing(initial: list[str], picks: list[str], centres: dict, extent: float) -> float:
    """Mean over the picked views of the distance to the nearest other view of the final training set
    / extent: small when a policy acquires near-duplicates of each other or of the initial views."""
    from scipy.spatial import cKDTree

    allv = initial + picks
    pts = np.stack([centres[n] for n in allv])
    d, _ = cKDTree(pts).query(pts[len(initial):], k=2)  # k=2: the nearest one other than itself
    return float(np.mean(d[:, 1]) / extent)


def support_deficit(initial: list[str], candidates: list[str], centres: dict) -> dict[str, float]:
    """{candidate: distance from its camera centre to the nearest initial training camera centre}: how far a
    candidate is from where the cameras were (the farthest policy's score before any pick)."""
    from b3dgs.neighbours import nearest_distances

    if not initial or not candidates:
        return {}
    d = nearest_distances(np.stack([centres[n] for n in candidates]), np.stack([centres[n] for n in initial]))
    return {n: float(x) for n, x in zip(candidates, d)}


def add_support(per_scene: dict, scene_args: dict | None = None) -> dict:
    """Each row's test support distance after acquisition and the Spearman ρ of its candidate scores with the
    candidates' support deficit (:func:`support_deficit`: does the score know where the cameras were?), and per
    scene the Spearman correlation over the rows of one seed between PSNR and the support distance (mean over
    seeds): does coverage explain the ranking?"""
    from scipy.stats import spearmanr

    from b3dgs.study.active_tables import oracle_rho

    out = {}
    for scene, s in per_scene.items():
        meta = s["meta"]
        centres, extent = camera_geometry(scene, (scene_args or {}).get(scene))
        init = list(meta["initial_views"])
        deficit = support_deficit(init, list(meta.get("candidates") or []), centres)
        for r in s["runs"]:
            r["support_distance"] = support_distance(init + list(r["selected"]), meta["test_views"], centres, extent)
            r["pick_spacing"] = pick_spacing(init, list(r["selected"]), centres, extent)
            r["spearman_vs_support"] = oracle_rho(r.get("scores"), deficit)
        rhos = []
        for sd in s["seeds"]:
            rows = [r for r in s["runs"] if int(r["seed"]) == sd and r.get("psnr") is not None]
            dist = [r["support_distance"] for r in rows]
            if len(rows) >= 4 and len(set(dist)) > 1:  # constant distances (every row's picks as near): no rank
                rhos.append(float(spearmanr([r["psnr"] for r in rows], dist).statistic))
        rhos = [x for x in rhos if math.isfinite(x)]  # constant PSNRs: undefined too
        out[scene] = {"initial": support_distance(init, meta["test_views"], centres, extent),
                      "psnr_vs_support_spearman": _mean(rhos), "per_seed": rhos}
    return out


def aggregate(scenes: list[str], study_out: Path, walls: dict, scene_args: dict | None = None,
              results: Path | None = None) -> dict:
    """The cross-scene table of the studies under ``study_out`` (per-scene copies under ``results``, default
    ``bench/results/active_view/``; ``scene_args``: data overrides per scene where not ``scene=<scene>``)."""
    from b3dgs.study.active_tables import write_report

    per_scene = {}
    for scene in scenes:
        out = study_out / scene
        if not (out / "meta.json").exists():
            continue
        s = write_report(out, plots=True, store=None, pairs=STUDY_PAIRS)
        dst = (results or RESULTS / NAME) / scene
        dst.mkdir(parents=True, exist_ok=True)
        for f in [out / "study.md", out / "study.json", *(out / "plots").glob("*.png")]:
            shutil.copy2(f, dst / f.name)
        per_scene[scene] = s
    support = add_support(per_scene, scene_args)
    for scene, s in per_scene.items():  # a row's full cost: every phase-1 model it scored with, round 2, scoring
        for r in s["runs"]:
            p1 = 0.0
            for i in range(int(r.get("members", 1))):
                f = study_out / scene / "phase1" / f"{r['family']}_s{int(r['seed']) + i}" / "phase1.json"
                p1 += float(json.loads(f.read_text())["train_time_s"]) if f.exists() else 0.0
            r["cost_s"] = p1 + float(r.get("round2_time_s") or 0) + float(r.get("scoring_time_s") or 0)
    policies = list(dict.fromkeys(p for s in per_scene.values() for p in s["table"]))
    table = {}
    for p in policies:
        ents = [s["table"][p] for s in per_scene.values() if p in s["table"]]
        e = {"family": ents[0]["family"], "oracle": ents[0]["oracle"], "scenes": len(ents),
             "training_shared_with": ents[0].get("training_shared_with")}
        for k in ("psnr", "ssim", "lpips", "train_time_s", "scoring_time_s", "spearman_vs_oracle"):
            e[k] = _mean([x[k] for x in ents if x.get(k) is not None])
        mine = [[r for r in s["runs"] if r["policy"] == p] for s in per_scene.values()]  # the policy's rows per scene
        rho = [[r["spearman_vs_support"] for r in rs if r.get("spearman_vs_support") is not None] for rs in mine]
        e["spearman_vs_support"] = _mean([float(np.mean(v)) for v in rho if v])  # macro over scenes of seed means
        for k in ("support_distance", "pick_spacing", "cost_s"):  # macro over scenes of the policy's row means
            e[k] = _mean([float(np.mean([r[k] for r in rs])) for rs in mine if rs])
        # the batch selector's own time (beyond the policy's first scoring) and its exact re-scores per pick
        infos = [r.get("batch_info") or {} for rs in mine for r in rs]
        e["batch_time_s"] = _mean([i["batch_time_s"] for i in infos if i.get("batch_time_s") is not None])
        e["rescored_per_pick"] = _mean([x for i in infos for x in i.get("rescored_per_pick", [])])
        e["batch_fallback"] = sorted({i["fallback"] for i in infos if i.get("fallback")}) or None
        # SEM over seeds of the per-seed macro mean (the paper's teaser error bars)
        seeds = sorted({int(r["seed"]) for rs in mine for r in rs})
        per_seed = [float(np.mean(v)) for sd in seeds
                    if len(v := [r["psnr"] for rs in mine for r in rs if int(r["seed"]) == sd]) == len(ents)]
        e["psnr_sem_seeds"] = mean_sem(per_seed)[1]
        e["n_seeds"] = len(seeds)
        table[p] = e
    paired = {}
    for a, b in PAIRS:
        d, scene_means = [], []
        for scene, s in per_scene.items():
            by = {(r["policy"], int(r["seed"])): r for r in s["runs"]}
            ds = [by[(a, sd)]["psnr"] - by[(b, sd)]["psnr"] for sd in s["seeds"] if (a, sd) in by and (b, sd) in by]
            dl = [by[(a, sd)]["lpips"] - by[(b, sd)]["lpips"] for sd in s["seeds"] if (a, sd) in by and (b, sd) in by
                  and by[(a, sd)].get("lpips") is not None and by[(b, sd)].get("lpips") is not None]
            if ds:
                d += [(scene, x) for x in ds]
                scene_means.append((scene, float(np.mean(ds)), _mean(dl)))
        if d:
            vals = [x for _, x in d]
            m, sem = mean_sem(vals)
            lp = [x for _, _, x in scene_means if x is not None]
            sm = [x for _, x, _ in scene_means]
            paired[f"{a}-{b}"] = {"delta_psnr": m, "sem": sem, "wins": int(sum(x > 0 for x in vals)), "n": len(vals),
                                  "scene_sign_flip_p": sign_flip_p(sm), "p_floor": p_floor(len(sm)),
                                  "scene_wins": int(sum(x > 0 for _, x, _ in scene_means)), "n_scenes": len(scene_means),
                                  "delta_lpips": _mean(lp),
                                  "per_scene": {sc: x for sc, x, _ in scene_means}, "paper": PAPER_PAIRED.get(f"{a}-{b}")}
    jac = {}
    for k in ("native|proxy", "native|ensemble", "proxy|ensemble", "native|fisher", "native|oracle", "ensemble|oracle",
              "native|native+greedy_conditioned", "native|native+diverse", "native+greedy_conditioned|farthest",
              "native+diverse|farthest"):
        a, b = k.split("|")
        vals = [v for s in per_scene.values() if (v := s["jaccard"].get(k, s["jaccard"].get(f"{b}|{a}"))) is not None]
        if vals:
            jac[k] = {"mean": float(np.mean(vals)), "paper": PAPER_JACCARD.get(k)}
    compute = {f"{sc}/s{sd}": c for sc, s in per_scene.items() for sd, c in compute_per_seed(study_out / sc, s).items()}
    for key, w in walls.items():
        compute.setdefault(key, {})["wall_s"] = w
    return {"machine": machine(), "scenes": list(per_scene), "table": table, "paired": paired, "jaccard": jac,
            "support": support,
            "compute": compute, "per_scene": {sc: {k: v for k, v in s.items() if k != "runs"} for sc, s in per_scene.items()},
            "runs": {sc: s["runs"] for sc, s in per_scene.items()}}


def pooled_per_scene(results: list[dict], key: str) -> dict[str, float]:
    """Per scene, the seed-mean paired PSNR difference ``key`` (e.g. 'native-ensemble') of every ladder's aggregate in
    ``results``: a scene's difference compares two policies on that scene's own ladder, so each scene is one unit."""
    per: dict[str, float] = {}
    for res in results:
        per.update(res.get("paired", {}).get(key, {}).get("per_scene", {}))
    return per


def pooled_pairs(results: list[dict]) -> dict:
    """Each paired difference with every scene of every ladder as one unit (:func:`pooled_per_scene`): the sign-flip
    test over all scenes, whose floor two ladders reported apart cannot reach (5 scenes: 2/32 > 0.05; 7: 2/128)."""
    keys = [k for res in results for k in res.get("paired", {})]
    out = {}
    for k in dict.fromkeys(keys):
        per = pooled_per_scene(results, k)
        sm = list(per.values())
        out[k] = {"delta_psnr": float(np.mean(sm)), "sem": mean_sem(sm)[1], "scene_wins": int(sum(x > 0 for x in sm)),
                  "n_scenes": len(sm), "scene_sign_flip_p": sign_flip_p(sm), "p_floor": p_floor(len(sm)),
                  "per_scene": per}
    return out


def pooled_markdown(pooled: dict, ladders: dict) -> str:
    by = {}
    for sc, lad in ladders.items():
        by.setdefault(lad, []).append(sc)
    lines = ["", "## Paired differences over both ladders (each scene one unit)", "",
             "Scenes of the 8 → 16 ladder (`active_view_8to16.md`) pooled with these: a scene's seed-mean difference "
             "compares two policies on that scene's own ladder. Ladders: "
             + "; ".join(f"{lad} {', '.join(scs)}" for lad, scs in by.items()) + ".", ""]
    lines += markdown_table(
        ["pair", "ΔPSNR dB, mean over scenes (± SEM)", "scene wins", "sign-flip p over scenes (floor)", "per scene"],
        [[k.replace("-", " − "), f"{_f(v['delta_psnr'], sign=True)} ± {_f(v['sem'])}",
          f"{v['scene_wins']}/{v['n_scenes']}", f"{_f(v.get('scene_sign_flip_p'), 3)} ({_f(v.get('p_floor'), 3)})",
          ", ".join(f"{sc} {x:+.3f}" for sc, x in v["per_scene"].items())] for k, v in pooled.items()])
    return "\n".join(lines) + "\n"


def _f(v, nd=3, sign=False):
    return fmt(v, f".{nd}f", sign)


def markdown(res: dict) -> str:
    t = res["table"]
    seeds = sorted({int(r["seed"]) for runs in res["runs"].values() for r in runs})
    order = row_order(t)
    meta = next(iter(res.get("per_scene", {}).values()), {}).get("meta", {})
    n0, acq = len(meta.get("initial_views") or []) or 16, meta.get("acquire") or 16
    p1, tot = meta.get("phase1_steps") or 1000, meta.get("total_steps") or 3000
    proto = "quick protocol: 256 px, " if (p1, tot) == (1000, 3000) else ""
    lines = [f"# Active view selection, {n0} → {n0 + acq} views ({proto}{p1} + {tot - p1} steps, CPU)", "",
             f"Scenes {res['scenes']}, seeds {seeds}. Macro mean over scenes of per-scene seed means; ± is the SEM over "
             "seeds of the per-seed macro mean (the paper's teaser bars). Paper: Table 2 (13 scenes × 3 seeds, 10k + 20k "
             "iterations, GPU). Time: our phase 1 + second round of the row's model (s, 1 thread); scoring apart.", ""]
    rows = []
    for p in order:
        e = t[p]
        pp = PAPER.get(p)
        name = p + (" (ORACLE: uses ground truth, analysis only)" if e["oracle"] else "")
        if e.get("training_shared_with"):
            name += f" (same run as {', '.join(e['training_shared_with'])})"
        if e.get("batch_fallback"):
            name += f" (selected as {', '.join(e['batch_fallback'])}: cannot condition)"
        sem = e.get("psnr_sem_seeds")
        rows.append([e["family"], name, _f(e["psnr"]) + ("" if sem is None else f" ± {sem:.3f}"), _f(e["ssim"], 4),
                     _f(e["lpips"], 4), _f(e["spearman_vs_oracle"], 2), _f(e.get("spearman_vs_support"), 2),
                     _f(e.get("support_distance"), 3),
                     _f(e.get("pick_spacing"), 3), _f(e["train_time_s"], 0), _f(e["scoring_time_s"], 1),
                     _f(e.get("batch_time_s"), 1), _f(e.get("rescored_per_pick"), 1), _f(e.get("cost_s"), 0),
                     *([f"{pp[0]:.3f}", f"{pp[1]:.4f}", f"{pp[2]:.4f}", f"{pp[3]:.1f}"] if pp and "+" not in p
                       else ["—"] * 4)])
    lines += markdown_table(["family", "policy", "PSNR ↑", "SSIM ↑", "LPIPS ↓", "ρ score vs oracle error",
                             "ρ score vs support deficit", "test support dist. ↓", "pick spacing", "train s", "scoring s", "batch s",
                             "re-scores / pick", "cost s", "paper PSNR", "paper SSIM", "paper LPIPS", "paper time s"],
                            rows)
    lines += ["", "ρ: Spearman correlation, over the candidates, of the policy's score with the phase-1 model's current "
              "render error on each candidate (the oracle's score): how informative the score is. ρ vs support "
              "deficit: the same with each candidate's distance to the nearest initial training camera centre (the "
              "farthest policy's score): whether the score knows where the cameras were. "
              "'Same run as X': identical acquired views and a bit-identical training run (NIW only observes training). "
              "Cost: every phase-1 model the row scored with (the ensemble's 3), its second round and scoring "
              "(the paper's time column counts the ensemble's members too). Test support distance: mean over test views of the distance to the nearest final training camera "
              "centre / scene extent (the coverage the picks give). Pick spacing: mean over the 16 picks of the distance "
              "to the nearest other camera of the final training set / extent (small: near-duplicate picks). "
              "Rows `policy+batch` (issue 22) select with that batch option from the same scores (scoring s includes "
              "the batch selection); batch s: the selector's time beyond the first scoring (greedy_conditioned: "
              "conditioning renders, weight renders for the ratio, exact re-scores); re-scores / pick: exact candidate "
              "scorings per pick after the first (at most max_rescore = 4).", ""]
    lines += markdown_table(
        ["scene", "support dist. of the 16 initial views", "Spearman(PSNR, support dist.) over the rows of a seed"],
        [[sc, f"{v['initial']:.3f}", f"{_f(v['psnr_vs_support_spearman'], 2)} (per seed "
          f"{', '.join(f'{x:+.2f}' for x in v['per_seed'])})"] for sc, v in res.get("support", {}).items()])
    lines += ["", "## Paired differences (scene-seed pairs)", ""]
    lines += markdown_table(
        ["pair", "ΔPSNR dB (± SEM)", "scene-seed wins", "scene-mean wins", "sign-flip p over scenes (floor)", "ΔLPIPS",
         "per scene ΔPSNR", "paper ΔPSNR"],
        [[k.replace("-", " − "), f"{_f(v['delta_psnr'], sign=True)} ± {_f(v['sem'])}", f"{v['wins']}/{v['n']}",
          f"{v['scene_wins']}/{v['n_scenes']}", f"{_f(v.get('scene_sign_flip_p'), 3)} ({_f(v.get('p_floor'), 3)})",
          _f(v["delta_lpips"], 4, sign=True), ", ".join(f"{sc} {x:+.3f}" for sc, x in v["per_scene"].items()),
          v["paper"] or "—"] for k, v in res["paired"].items()])
    if res["jaccard"]:
        lines += ["", "## Overlap of the selected views (Jaccard, mean over scene-seeds)", ""]
        lines += markdown_table(["pair", "ours", "paper"], [[k.replace("|", " / "), f"{v['mean']:.3f}", _f(v["paper"])]
                                                           for k, v in res["jaccard"].items()])
    lines += ["", "## Compute per scene-seed", "",
              "Phase-1 models first trained for that seed, every row's second round (shared rows cost nothing) and "
              "scoring; evaluation excluded. 1 thread per study, two scenes at once on the 2 cores. Job wall: the study "
              "processes' wall time summed over the sessions that ran the scene-seed (before 2026-11-25 only the last "
              "session's was kept, so a seed finished earlier may show the seconds of a session that only resumed it).", ""]
    lines += markdown_table(
        ["scene/seed", "rows", "phase 1 s", "round 2 s", "scoring s", "total min", "job wall min"],
        [[k, str(c["rows"]), f"{c['phase1_s']:.0f}", f"{c['round2_s']:.0f}", f"{c['scoring_s']:.0f}",
          f"{c['total_s'] / 60:.1f}", _f(c.get("wall_s") and c["wall_s"] / 60, 1)]
         for k, c in sorted(res["compute"].items()) if "total_s" in c])
    lines += ["", "Plots: `active_view/psnr.png` (final PSNR per policy ± SEM over seeds), `active_view/psnr_time.png` "
              "(final PSNR against compute), per scene `active_view/<scene>/{psnr,layout}.png`."]
    return "\n".join(lines) + "\n"


def plots(res: dict, d: Path) -> None:
    plt = pyplot()
    t = res["table"]
    names = [p for p in row_order(t) if t[p]["psnr"] is not None]
    d.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(1.2 + 0.85 * len(names), 3.4))
    m = [t[p]["psnr"] for p in names]
    e = [t[p].get("psnr_sem_seeds") or 0 for p in names]
    col = ["0.5" if t[p]["oracle"] else ("tab:blue" if t[p]["family"] == "standard" else "tab:orange") for p in names]
    ax.bar(range(len(names)), m, yerr=e, color=col, capsize=3)
    ax.set_xticks(range(len(names)), names, rotation=30, ha="right")
    ax.set_ylim(min(a - b for a, b in zip(m, e)) - 0.4, max(a + b for a, b in zip(m, e)) + 0.2)
    ax.set_ylabel("final test PSNR (dB), macro over scenes")
    ax.set_title(f"16 → 32 views, {', '.join(res['scenes'])}: ±1 SEM over seeds\nblue standard, orange NIW, grey oracle",
                 fontsize=9)
    fig.tight_layout()
    save_figure(fig, d / "psnr.png", dpi=120)
    fig, ax = plt.subplots(figsize=(5.2, 3.8))
    for p in names:
        x = t[p].get("cost_s") or 0
        ax.scatter([x], [t[p]["psnr"]], color=col[names.index(p)])
        ax.annotate(p, (x, t[p]["psnr"]), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set(xlabel="cost: phase-1 models + round 2 + scoring (s, 1 thread), macro mean", ylabel="final test PSNR (dB)")
    ax.set_title("error against run time, per policy", fontsize=9)
    fig.tight_layout()
    save_figure(fig, d / "psnr_time.png", dpi=120)


#: ``--smoke``: the embedded procedural scene at a tiny protocol (minutes on 2 cores): checks that every row,
#: batch row and diagnostic runs end to end; its numbers say nothing about the real scenes
SMOKE_SCENE = ["data=synthetic", "data.max_side=48", "+data.n_views=40"]
SMOKE = ["trainer.max_steps=300", "initial_views=8", "acquire=6", "strategy.refine_start=50", "strategy.refine_every=50",
         "strategy.refine_stop=250", "trainer.checkpoint_every_s=0",
         "+policy_settings.ppu.regime.ppu.steps=50", "+policy_settings.fisher.pixel_stride=4"]


#: what the archive keeps of a study dir: the per-scene protocol, meta and layout, each row's and each phase-1 model's
#: small JSON files (result.json, the selection, oracle.json), and the wall times; never checkpoints
ARCHIVED = ("walls.json", "*/protocol.json", "*/meta.json", "*/layout.json", "*/*_s*/*.json", "*/phase1/*/*.json")


def refuse_committed(archive: Path, extra: list[str]) -> None:
    """``--extra`` changes the study (policies, protocol), so its rows would rewrite the committed archive's
    meta.json/layout.json and tables: such runs go to their own ``--study-out`` and are paired with the committed
    campaign by bench/active_view_extra.py."""
    if extra and archive.resolve() == (RESULTS / "active_view_runs").resolve():
        raise SystemExit(f"bench/active_view.py: --extra {' '.join(extra)} would rewrite the committed archive "
                         f"{archive}; pass --study-out DIR (rows archived to DIR/archive) and pair them with "
                         "python -m bench.active_view_extra --new DIR")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=list(STUDY_SCENES), choices=scene_names(),
                    help="default: the seven scenes of conf/report.yaml; scenes with < 40 train views run 8 -> 16")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--jobs", type=int, default=2, help="scene-seeds run at once (one thread each)")
    ap.add_argument("--study-out", default=None, help="default outputs/study (--smoke: outputs/study_smoke)")
    ap.add_argument("--aggregate-only", action="store_true")
    ap.add_argument("--results-root", default=str(RESULTS),
                    help="where the tables and their plots go (default bench/results; bench.reproduce passes a temp dir)")
    ap.add_argument("--score-max-side", default="64",
                    help="acquisition.score_max_side of the committed study (64; 'null' = full size, use a new --study-out)")
    ap.add_argument("--batches", nargs="+", default=list(BATCHES),
                    help="acquisition.batch options: every score-based policy gets a row per option (topk: the rows "
                         "the study always had)")
    ap.add_argument("--smoke", action="store_true",
                    help="the embedded scene, seed 0, a tiny protocol; writes only under --study-out (not bench/results)")
    ap.add_argument("--extra", nargs="*", default=[], help="extra Hydra overrides for every study")
    ap.add_argument("--archive", default=None,
                    help="copy of the finished rows' small files for resuming across machines; default "
                         "bench/results/active_view_runs (committed) with the default --study-out, else <study-out>/archive")
    args = ap.parse_args()
    out = Path(args.study_out or ROOT / "outputs" / ("study_smoke" if args.smoke else "study"))
    if args.archive is None:  # smoke runs and other study dirs never write into the committed archive
        args.archive = str(out / "archive") if (args.study_out or args.smoke) else str(RESULTS / "active_view_runs")
    archive = Path(args.archive)
    refuse_committed(archive, args.extra)
    restore(archive, out, ARCHIVED)
    scenes, scene_args, extra = args.scenes, None, list(args.extra)
    extra.append(f"acquisition.batch=[{','.join(args.batches)}]")
    ladders: dict[str, str] = {}
    if args.smoke:
        scenes, scene_args, args.seeds = ["synthetic"], {"synthetic": SMOKE_SCENE}, [0]
        extra = SMOKE + extra
    else:
        ladders = scene_ladders(scenes)
        for sc, lad in ladders.items():
            print(f"{sc}: ladder {LADDERS[lad][0]} -> {sum(LADDERS[lad])}", flush=True)
    walls_path = out / "walls.json"
    walls = read_json(walls_path, {})
    if not args.aggregate_only:
        with PeriodicSync(out, archive, ARCHIVED), ThreadPoolExecutor(max_workers=max(1, args.jobs)) as ex:
            # one job per scene-seed (seed-major: every scene's seed 0 first); seeds of one scene share its phase-1
            # models, which the study trains under a file lock, so they may run at once
            futs = {(sc, sd): ex.submit(run_scene, sc, [sd], out,
                                        extra + ([f"initial_views={LADDERS[ladders[sc]][0]}",
                                                  f"acquire={LADDERS[ladders[sc]][1]}"] if sc in ladders else []),
                                        args.score_max_side, (scene_args or {}).get(sc))
                    for sd in args.seeds for sc in scenes}
            for (sc, _), f in futs.items():
                for sd, w in f.result().items():
                    walls[f"{sc}/s{sd}"] = walls.get(f"{sc}/s{sd}", 0.0) + w  # summed over the sessions it took
        write_json(walls_path, walls)
        sync_results(out, archive, ARCHIVED)
    if args.smoke:  # never over the committed results
        res = aggregate(scenes, out, walls, scene_args, results=out / "tables")
        write_results("active_view_smoke", res, markdown(res).rstrip("\n"), root=out)
        return
    results = {}
    # rows with --extra are another study: tables stay with it
    root = out / "tables" if args.extra else Path(args.results_root)
    for lad in LADDERS:  # one table per ladder: 16 -> 32 scenes are never pooled with 8 -> 16 ones in a table
        group = [sc for sc in scenes if ladders.get(sc) == lad]
        if group:
            results[lad] = aggregate(group, out, walls, results=root / NAME)
            results[lad]["ladder"] = lad
    pooled = pooled_pairs(list(results.values())) if len(results) > 1 else None
    for lad, res in results.items():
        text = markdown(res)
        if lad == "16to32":
            plots(res, root / NAME)
            if pooled:  # the paired answers over every scene sit with the main table
                res["paired_all_ladders"] = pooled
                text += pooled_markdown(pooled, {sc: lad2 for sc, lad2 in ladders.items() if sc in scenes})
        write_results(NAME if lad == "16to32" else f"{NAME}_{lad}", res, text, root=root)


if __name__ == "__main__":
    main()
