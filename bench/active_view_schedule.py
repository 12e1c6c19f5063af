"""The active-view study's cost and rows under two training schedules, run side by side (issue 30, item 4).

    python -m bench.active_view --scenes fox --seeds 0 --jobs 1 --batches topk \
        --extra "policies=[uniform,farthest,ensemble,native]" "family_baselines=[]" --study-out /work/av_const &
    python -m bench.active_view --scenes fox --seeds 0 --jobs 1 --batches topk \
        --extra "policies=[uniform,farthest,ensemble,native]" "family_baselines=[]" +schedule=dash --study-out /work/av_dash
    python -m bench.active_view_schedule            # reads bench/results/active_view_schedule/{constant,dash}/

Each folder holds the study's cross-scene table (``active_view.json``, from ``<study-out>/tables``) and its archived
rows (``runs/``). Writes ``bench/results/active_view_schedule/compare.{json,md}``: per policy the final PSNR and LPIPS
under each schedule, each policy's rank, and the scene-seed's compute (phase 1, round 2, scoring) with their ratios.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from bench.common import RESULTS


def compare(a: dict, b: dict, name_a: str, name_b: str) -> dict:
    """Policies both tables have: PSNR/LPIPS and ranks under each; compute per scene-seed and the b/a ratios."""
    pols = [p for p in a["table"] if p in b["table"]]

    def rank(t: dict) -> dict:
        order = sorted(pols, key=lambda p: -t[p]["psnr"])
        return {p: order.index(p) + 1 for p in pols}

    ra, rb = rank(a["table"]), rank(b["table"])
    rows = [{"policy": p, f"psnr_{name_a}": a["table"][p]["psnr"], f"psnr_{name_b}": b["table"][p]["psnr"],
             f"lpips_{name_a}": a["table"][p]["lpips"], f"lpips_{name_b}": b["table"][p]["lpips"],
             f"rank_{name_a}": ra[p], f"rank_{name_b}": rb[p]} for p in pols]
    compute = {}
    for ss in sorted(a["compute"].keys() & b["compute"].keys()):
        ca, cb = a["compute"][ss], b["compute"][ss]
        compute[ss] = {k: {name_a: ca[k], name_b: cb[k], "ratio": cb[k] / ca[k] if ca[k] else None}
                       for k in ("phase1_s", "round2_s", "scoring_s", "total_s")}
    return {"a": name_a, "b": name_b, "scenes": a.get("scenes"), "rows": rows, "compute": compute}


def markdown(res: dict) -> str:
    a, b = res["a"], res["b"]
    lines = [f"# Active view under schedule={b} against schedule={a}", "",
             f"Scenes {res['scenes']}, the two studies run side by side on one machine (one thread each).", "",
             f"| policy | PSNR {a} | PSNR {b} | Δ | LPIPS {a} | LPIPS {b} | rank {a} | rank {b} |",
             "|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        lines.append(f"| {r['policy']} | {r['psnr_' + a]:.3f} | {r['psnr_' + b]:.3f} | {r['psnr_' + b] - r['psnr_' + a]:+.3f} "
                     f"| {r['lpips_' + a]:.4f} | {r['lpips_' + b]:.4f} | {r['rank_' + a]} | {r['rank_' + b]} |")
    lines += ["", f"| scene/seed | part | {a} s | {b} s | {b} / {a} |", "|---|---|---|---|---|"]
    for ss, parts in res["compute"].items():
        for k, v in parts.items():
            ratio = "—" if v["ratio"] is None else f"{v['ratio']:.2f}"
            lines.append(f"| {ss} | {k[:-2]} | {v[a]:.0f} | {v[b]:.0f} | {ratio} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dir", default=str(RESULTS / "active_view_schedule"))
    ap.add_argument("--a", default="constant")
    ap.add_argument("--b", default="dash")
    ap.add_argument("--results-root", default=None, help="where compare.{json,md} go (default: --dir)")
    args = ap.parse_args()
    d = Path(args.dir)
    tables = {}
    for n in (args.a, args.b):
        f = d / n / "active_view.json"
        if not f.is_file():
            raise SystemExit(f"bench/active_view_schedule.py: no {f} (fix: copy the study's tables/active_view.json there)")
        tables[n] = json.loads(f.read_text())
    from b3dgs.io import atomic_path, write_json

    res = compare(tables[args.a], tables[args.b], args.a, args.b)
    root = Path(args.results_root) if args.results_root else d
    root.mkdir(parents=True, exist_ok=True)
    write_json(root / "compare.json", res)
    with atomic_path(root / "compare.md") as tmp:
        tmp.write_text(markdown(res))
    print(markdown(res))


if __name__ == "__main__":
    main()
