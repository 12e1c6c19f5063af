"""Does scoring candidates at reduced resolution change an acquisition policy's ranking?

For one scene and seed of a finished (or running) ``b3dgs-study active`` out_dir, every scoring policy
scores the candidate pool from the same phase-1 models at each ``--sides`` value (``full`` = the training
resolution) and the rankings are compared with the first side's:

* Spearman ρ of the candidate scores (``scipy.stats.spearmanr``);
* the overlap of the selected ``acquire`` views (Jaccard) and how many picks differ;
* the scoring time at each side (median of one run: the machine is noisy; the ratio is measured side by side).

    python -m bench.active_resolution --scene ethiopian_head --seed 0                 # 64 vs full (256 px)
    python -m bench.active_resolution --scene fox --sides full 64 32 --policies proxy native

Resumable: every (policy, side) entry is written to ``bench/results/active_resolution.json`` when done and
reused. The phase-1 models come from ``<study_out>/<scene>/phase1`` (trained by the study if missing).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from bench.common import RESULTS, machine, scene_names, scene_overrides, table, write_results

ROOT = Path(__file__).resolve().parents[1]
NAME = "active_resolution"


def study_for(scene: str, study_out: str, threads: int):
    from b3dgs.study.active import ActiveStudy, compose_config

    overrides = scene_overrides(scene) + [
        "renderer=cpu", f"out_dir={study_out}", f"threads={threads}", "trainer.enable_progress_bar=false"]
    return ActiveStudy(compose_config("study", overrides))


def score(study, label: str, seed: int, side):
    from b3dgs.study.active import load_policy

    _, policy = load_policy(label, study.cfg.get("policy_settings"))
    models = study.scoring_models(policy.family, seed, int(policy.members))
    ctx = study.context(models, policy, seed, score_max_side=None if side == "full" else int(side))
    t0 = time.perf_counter()
    sel = policy.select(ctx, study.scene.candidates, int(study.cfg.acquire))
    dt = time.perf_counter() - t0
    return {"scores": sel.scores, "picks": [study.scene.candidates[i].name for i in sel.indices], "time_s": dt}


def main() -> None:
    import json

    import torch

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="ethiopian_head", choices=scene_names())
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sides", nargs="+", default=["full", "64"], help="first = the reference; 'full' = training size")
    ap.add_argument("--policies", nargs="+", default=["ensemble", "ppu", "fisher", "proxy", "native", "oracle"])
    ap.add_argument("--study-out", default=str(ROOT / "outputs" / "study"))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--outcome", nargs=2, metavar=("STUDY_SIDE", "STUDY_FULL"), default=None,
                    help="only compare the final PSNR of rows trained after scoring at the reduced side and at full "
                         "size (two b3dgs-study out_dirs, same seeds; e.g. outputs/study outputs/study_full)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    path = RESULTS / f"{NAME}.json"
    payload = json.loads(path.read_text()) if path.exists() else {"entries": {}}
    payload["machine"] = machine()
    if args.outcome:
        payload["outcome"] = outcome(Path(args.outcome[0]), Path(args.outcome[1]))
        write_results(NAME, payload, render(payload))
        return
    entries = payload["entries"]
    study = study_for(args.scene, args.study_out, args.threads)
    for label in args.policies:
        for side in args.sides:
            key = f"{args.scene}/s{args.seed}/{label}/{side}"
            if key in entries:
                continue
            print(f"scoring {key} ...", flush=True)
            entries[key] = score(study, label, args.seed, side)
            write_results(NAME, payload, render(payload))  # after every entry: an interruption loses one
    write_results(NAME, payload, render(payload))


def outcome(side_dir: Path, full_dir: Path) -> list[dict]:
    """Rows present in both study dirs: picks that differ and final PSNR / LPIPS after the second round."""
    import json

    rows = []
    for res_full in sorted(full_dir.glob("*/*_s*/result.json")):
        rel = res_full.relative_to(full_dir)
        res_side = side_dir / rel
        if not res_side.exists():
            continue
        a, b = json.loads(res_side.read_text()), json.loads(res_full.read_text())
        rows.append({"scene": rel.parts[0], "policy": a["policy"], "seed": int(a["seed"]),
                     "picks_differ": len(set(a["selected"]) - set(b["selected"])), "psnr_side": a["psnr"],
                     "psnr_full": b["psnr"], "delta_psnr": b["psnr"] - a["psnr"],
                     "delta_lpips": (b["lpips"] - a["lpips"]) if a.get("lpips") is not None and b.get("lpips") is not None
                     else None})
    return rows


def render(payload: dict) -> str:
    from scipy.stats import spearmanr

    rows = []
    ent = payload["entries"]
    groups: dict[tuple, dict] = {}
    for key, v in ent.items():
        scene, seed, label, side = key.split("/")
        groups.setdefault((scene, seed, label), {})[side] = v
    for (scene, seed, label), sides in groups.items():
        names = list(sides)
        ref_side = "full" if "full" in sides else names[0]
        ref = sides[ref_side]
        for side in names:
            if side == ref_side:
                continue
            v = sides[side]
            rho = None
            if ref["scores"] is not None and v["scores"] is not None:
                rho = float(spearmanr(ref["scores"], v["scores"]).statistic)
            a, b = set(ref["picks"]), set(v["picks"])
            rows.append({"scene": scene, "seed": seed, "policy": label, "reference": ref_side, "side": side,
                         "spearman": rho, "jaccard": len(a & b) / max(1, len(a | b)),
                         "picks_differ": len(a - b), "t_ref_s": ref["time_s"], "t_side_s": v["time_s"],
                         "speedup": ref["time_s"] / max(v["time_s"], 1e-9)})
    cols = ["scene", "seed", "policy", "reference", "side", "spearman", "jaccard", "picks_differ", "t_ref_s", "t_side_s",
            "speedup"]
    payload["summary"] = rows
    head = ("# Acquisition scores at reduced resolution against the reference resolution\n\n"
            "Same phase-1 models, same candidates; Spearman ρ of the candidate scores, Jaccard overlap of the "
            "selected views and picks that differ (of `acquire`), scoring time (one run each, side by side).\n\n")
    text = head + (table(rows, cols) if rows else "(no pairs yet)")
    if payload.get("outcome"):
        oc = payload["outcome"]
        text += ("\n\n## Effect on the study's outcome\n\nThe same rows trained after scoring at the reduced side "
                 "(the committed study) and at full size (same phase-1 models): picks that differ and the final test "
                 "PSNR (full − reduced).\n\n" + table(oc, ["scene", "policy", "seed", "picks_differ", "psnr_side",
                                                          "psnr_full", "delta_psnr", "delta_lpips"]))
    return text


if __name__ == "__main__":
    main()
