"""New active-view rows against the committed campaign's, paired by scene-seed.

    python -m bench.active_view_extra --new /work/av_out --policies sh native_sh --name active_view_sh

A study run later with a few new policies only (``bench.active_view --extra "policies=[sh,native_sh]"
family_baselines=false --study-out DIR --archive DIR/archive``) trains its own phase-1 models; the default build
trains them bit for bit like the campaign's, which this script checks on the phase-1 oracle errors (every candidate's
error must match the committed ``oracle.json``; a scene-seed whose phase 1 differs is reported and left out). Then, per
budget ladder (16 -> 32 and 8 -> 16 are never pooled), each new policy's final PSNR minus each committed policy's
(paired over scenes, each scene's seed mean one unit: bootstrap CI, exact sign-flip p) and each row's Spearman ρ
of its candidate scores with the phase-1 model's error on the candidate (how informative the score is) and with the
candidate's support deficit (distance to the nearest initial training camera: does the score know where the cameras
were?), both ρ paired over every scene of both ladders. Writes bench/results/<name>.{json,md}.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from bench.common import RESULTS, read_json as _read, write_results

# oracle: analysis only (its ρₛ is the error's own ρ with the support deficit); the diverse rows pair a new policy's
# diverse batch with the committed scores' diverse batches
AGAINST = ["native", "ensemble", "farthest", "uniform", "fisher", "proxy", "ppu", "oracle", "native+diverse",
           "ensemble+diverse"]


def _deficits(scene: str, meta: dict) -> dict:
    """{candidate: distance to the nearest initial training camera centre} (bench.active_view.support_deficit)."""
    from bench.active_view import camera_geometry, support_deficit

    centres, _ = camera_geometry(scene)
    return support_deficit(list(meta.get("initial_views") or []), list(meta.get("candidates") or []), centres)


def collect(new: Path, archive: Path, policies: list[str], against: list[str], support: bool = True,
            within: tuple[str, ...] = ()) -> dict:
    from b3dgs.study.active_tables import oracle_rho

    rows, problems = [], []
    for scene_dir in sorted(p for p in new.iterdir() if (p / "meta.json").is_file()):
        scene = scene_dir.name
        meta = json.loads((scene_dir / "meta.json").read_text())
        deficit = _deficits(scene, meta) if support else {}
        ladder = f"{len(meta.get('initial_views', []))}->{len(meta.get('initial_views', [])) + int(meta.get('acquire', 0))}"
        for res in sorted(scene_dir.glob("*_s*/result.json")):
            label, seed = res.parent.name.rsplit("_s", 1)
            if label not in policies:
                continue
            r = json.loads(res.read_text())
            fam = r["family"]
            o_new = _read(scene_dir / "phase1" / f"{fam}_s{seed}" / "oracle.json")
            o_old = _read(archive / scene / "phase1" / f"{fam}_s{seed}" / "oracle.json")
            if o_new is None or o_old is None:
                problems.append(f"{scene} s{seed}: no phase-1 ({fam}) oracle.json in "
                                f"{'the new rows' if o_new is None else 'the committed campaign'}: left out")
                continue
            if set(o_new) != set(o_old) or any(abs(o_new[k] - o_old[k]) > 1e-9 * max(1.0, abs(o_old[k])) for k in o_old):
                problems.append(f"{scene} s{seed}: phase 1 ({fam}) differs from the committed campaign's: left out")
                continue
            row = {"scene": scene, "seed": int(seed), "ladder": ladder, "policy": label, "psnr": r["psnr"],
                   "lpips": r.get("lpips"),
                   "rho": oracle_rho(r.get("scores"), o_new), "rho_support": oracle_rho(r.get("scores"), deficit),
                   "scoring_time_s": r.get("scoring_time_s"), "round2_time_s": r.get("round2_time_s")}
            # new rows paired with each other (same phase-1 models, same new study), then with the committed ones
            for b, d in [(b, scene_dir) for b in within if b != label] + [(b, archive / scene) for b in against]:
                other = _read(d / f"{b}_s{seed}" / "result.json")
                if other is not None:
                    o_b = _read(d / "phase1" / f"{other['family']}_s{seed}" / "oracle.json")
                    row[f"psnr_{b}"], row[f"rho_{b}"] = other["psnr"], oracle_rho(other.get("scores"), o_b)
                    row[f"rho_support_{b}"] = oracle_rho(other.get("scores"), deficit)
                    if d != scene_dir:
                        row[f"scoring_time_s_{b}"] = other.get("scoring_time_s")
                    row[f"lpips_{b}"] = other.get("lpips")
            rows.append(row)
    return {"rows": rows, "problems": problems}


def scene_deltas(mine: list[dict], key: str, b: str) -> dict[str, float]:
    """Per scene, the mean over its seeds of ``row[key] - row[key_b]`` (rows where both are known)."""
    per = {}
    for sc in sorted({r["scene"] for r in mine}):
        d = [r[key] - r[f"{key}_{b}"] for r in mine
             if r["scene"] == sc and r.get(key) is not None and r.get(f"{key}_{b}") is not None]
        if d:
            per[sc] = float(np.mean(d))
    return per


def applies(policy: str, against: str) -> bool:
    """A committed batch row (``ensemble+diverse``) is paired only with a new row of a batch option."""
    return "+" in policy or "+" not in against


def pair(rows: list[dict], policies: list[str], against: list[str], key: str = "psnr") -> list[dict]:
    """Each new policy's final ``key`` (psnr; lpips, lower is better) minus each other policy's, per budget ladder,
    paired over scenes (each scene's seed mean one unit)."""
    from b3dgs.report.stats import paired_stats

    out = []
    for ladder in sorted({r["ladder"] for r in rows}):
        for p in policies:
            mine = [r for r in rows if r["policy"] == p and r["ladder"] == ladder]
            for b in against:
                per = scene_deltas(mine, key, b) if applies(p, b) else {}
                if not per:
                    continue
                st = paired_stats(list(per.values()), higher_is_better=key != "lpips") if len(per) >= 2 else {}
                out.append({"ladder": ladder, "a": p, "b": b, "per_scene": per, **st})
    return out


def pair_rho(rows: list[dict], policies: list[str], against: list[str]) -> list[dict]:
    """Each ρ (``rho``: with the oracle error; ``rho_support``: with the support deficit) of a new policy minus a
    committed one's, paired over every scene of both ladders (a scene's seed mean one unit; ρ has no budget unit)."""
    from b3dgs.report.stats import paired_stats

    out = []
    for key in ("rho", "rho_support"):
        for p in policies:
            mine = [r for r in rows if r["policy"] == p]
            for b in against:
                # a batch option changes which views are picked, not the scores: ρ against a batch row repeats
                # ρ against its policy's top-k row
                per = scene_deltas(mine, key, b) if "+" not in b else {}
                if len(per) >= 2:
                    out.append({"rho": key, "a": p, "b": b, "per_scene": per,
                                **paired_stats(list(per.values()), higher_is_better=True)})
    return out


def cost(rows: list[dict], policies: list[str], against: list[str]) -> list[dict]:
    """Per policy, the seconds its scoring took (the study's ``scoring_time_s``: scoring the candidates of one round,
    conditioning included; an ensemble's members were trained in phase 1 and are not in it) over every scene-seed,
    beside the new rows' round-2 training seconds. The committed policies' come from their own rows."""
    r2 = [float(r["round2_time_s"]) for r in rows if r.get("round2_time_s") is not None]
    out = []
    for p in [*policies, *(b for b in against if b not in policies)]:
        new = p in policies
        sel = [r for r in rows if r["policy"] == p] if new else \
            list({(r["scene"], r["seed"]): r for r in rows}.values())  # one committed row per scene-seed
        t = [float(r["scoring_time_s" if new else f"scoring_time_s_{p}"]) for r in sel
             if r.get("scoring_time_s" if new else f"scoring_time_s_{p}") is not None]
        if t:
            out.append({"policy": p, "new": new, "n": len(t), "median_s": float(np.median(t)), "min_s": float(min(t)),
                        "max_s": float(max(t)), "round2_median_s": float(np.median(r2)) if r2 else None})
    return out


def write(res: dict, name: str, policies: list[str], against: list[str], root: Path = RESULTS) -> None:
    lines = [f"# Active view: {', '.join(policies)} against the committed campaign", "",
             "New rows trained later from the same phase-1 models (checked: identical oracle errors), quick protocol, "
             "topk batches; paired over scenes (each scene's seed mean one unit). ρ: Spearman of the candidate scores "
             "with the phase-1 model's error on each candidate.", "",
             "## Rows", "", "ρ / ρₛ: Spearman of the candidate scores with the phase-1 model's error on each candidate / "
             "with each candidate's distance to the nearest initial training camera (its support deficit).", "",
             "| scene | ladder | seed | policy | PSNR | ρ / ρₛ | " + " | ".join(f"{b} PSNR / ρ / ρₛ" for b in against)
             + " |", "|---" * (5 + 1 + len(against)) + "|"]
    f = lambda v, nd=3: "—" if v is None else f"{v:.{nd}f}"  # noqa: E731
    for r in res["rows"]:
        cells = [f"{f(r.get(f'psnr_{b}'))} / {f(r.get(f'rho_{b}'), 2)} / {f(r.get(f'rho_support_{b}'), 2)}"
                 for b in against]
        lines.append(f"| {r['scene']} | {r['ladder']} | {r['seed']} | {r['policy']} | {f(r['psnr'])} | "
                     f"{f(r['rho'], 2)} / {f(r.get('rho_support'), 2)} | " + " | ".join(cells) + " |")
    for title, entries, nd in (("Paired final PSNR (a − b, dB)", res["paired"], 2),
                               ("Paired final LPIPS (a − b, lower is better: 'a better' counts a − b < 0)",
                                res.get("paired_lpips", []), 4)):
        if not entries:
            continue
        lines += ["", f"## {title}", "", "| ladder | a | b | mean Δ | 95 % CI | p | a better / worse | per scene |",
                  "|---|---|---|---|---|---|---|---|"]
        for p in entries:
            ci = p.get("ci") or {}
            cis = "—" if ci.get("low") is None else f"[{ci['low']:+.{nd + 1}f}, {ci['high']:+.{nd + 1}f}]"
            pv = "—" if p.get("p_two_sided") is None else f"{p['p_two_sided']:.3g}"
            mean = float(np.mean(list(p["per_scene"].values())))
            signs = " ".join(f"{s[:10]}{v:+.{nd}f}" for s, v in p["per_scene"].items())
            lines.append(f"| {p['ladder']} | {p['a']} | {p['b']} | {mean:+.{nd + 1}f} | {cis} | {pv} | "
                         f"{p.get('wins', '—')} / {p.get('losses', '—')} | {signs} |")
    lines += ["", "## Paired ρ (a − b), every scene of both ladders", "",
              "farthest's score is the support deficit itself (its ρₛ is 1): its rows give the ceiling.", "",
              "| ρ with | a | b | mean Δρ | 95 % CI | p | a higher / lower | per scene |", "|---|---|---|---|---|---|---|---|"]
    for p in res.get("paired_rho", []):
        ci = p.get("ci") or {}
        cis = "—" if ci.get("low") is None else f"[{ci['low']:+.2f}, {ci['high']:+.2f}]"
        pv = "—" if p.get("p_two_sided") is None else f"{p['p_two_sided']:.3g}"
        what = "oracle error" if p["rho"] == "rho" else "support deficit"
        signs = " ".join(f"{s[:10]}{v:+.2f}" for s, v in p["per_scene"].items())
        lines.append(f"| {what} | {p['a']} | {p['b']} | {p['mean']:+.3f} | {cis} | {pv} | {p['wins']} / {p['losses']} | "
                     f"{signs} |")
    if res.get("cost"):
        lines += ["", "## Scoring time (s per round, every scene-seed)", "",
                  "Beside the median round-2 training time of the new rows (the same protocol for every row).", "",
                  "| policy | row | scene-seeds | median s | range s | median / round-2 training |", "|---|---|---|---|---|---|"]
        for c in res["cost"]:
            share = "—" if not c["round2_median_s"] else f"{100 * c['median_s'] / c['round2_median_s']:.1f} %"
            lines.append(f"| {c['policy']} | {'new' if c['new'] else 'committed'} | {c['n']} | {c['median_s']:.1f} | "
                         f"{c['min_s']:.1f}–{c['max_s']:.1f} | {share} |")
    if res["problems"]:
        lines += ["", "## Left out", ""] + [f"- {x}" for x in res["problems"]]
    write_results(name, res, "\n".join(lines), root)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--new", required=True, help="the study dir (or its archive) with the new rows")
    ap.add_argument("--archive", default=str(RESULTS / "active_view_runs"), help="the committed campaign's rows")
    ap.add_argument("--policies", nargs="+", required=True)
    ap.add_argument("--against", nargs="+", default=AGAINST)
    ap.add_argument("--within", nargs="*", default=[], help="new policies every new policy is also paired with")
    ap.add_argument("--name", default="active_view_extra", help="bench/results/<name>.{json,md}")
    ap.add_argument("--results-root", default=str(RESULTS), help="where <name>.{json,md} go (default bench/results)")
    args = ap.parse_args()
    new, archive = Path(args.new), Path(args.archive)
    for p, what in ((new, "--new"), (archive, "--archive")):
        if not p.is_dir():
            raise SystemExit(f"bench.active_view_extra: {what} {p} is not a folder (fix: pass the study dir)")
    res = collect(new, archive, args.policies, args.against, within=tuple(args.within))
    against = args.against + [w for w in args.within if w not in args.against]
    res["paired"] = pair(res["rows"], args.policies, against)
    res["paired_lpips"] = pair(res["rows"], args.policies, against, key="lpips")
    res["paired_rho"] = pair_rho(res["rows"], args.policies, against)
    res["cost"] = cost(res["rows"], args.policies, against)
    write(res, args.name, args.policies, against, Path(args.results_root))


if __name__ == "__main__":
    main()
