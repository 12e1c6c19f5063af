"""The active-view study's outputs per scene: ``study.json``, ``study.md`` (laid out like the paper's Table 2)
and ``plots/`` (final PSNR per policy ±1 SEM, top view of the camera layout with each policy's picks, a
contact sheet of the picked views)."""
from __future__ import annotations

import json
import math
from itertools import combinations
from pathlib import Path
from typing import Any, Optional

import numpy as np

from b3dgs.io import atomic_path, save_figure, write_json
from b3dgs.report.document import markdown_table
from b3dgs.report.stats import mean_sem

#: every policy is paired with each of these (rows present only); the study's ``pairs=`` adds others
BASELINES = ("farthest", "uniform", "ensemble")


def pairs_for(policies: list[str], extra=()) -> list[tuple[str, str]]:
    """The paired rows (a − b by scene-seed): ``extra`` (the study's ``pairs=``), then every policy against each of
    :data:`BASELINES` by rule; each pair of policies once, in its first orientation."""
    out = []
    for a, b in [tuple(x) for x in extra] + [(p, b) for p in policies for b in BASELINES if p != b]:
        if (a, b) not in out and (b, a) not in out:
            out.append((a, b))
    return out


def jaccard(a, b) -> float:
    a, b = set(a), set(b)
    return len(a & b) / len(a | b) if a | b else 1.0


def oracle_for(out: Path, family: str, seed: int) -> Optional[dict]:
    p = out / "phase1" / f"{family}_s{seed}" / "oracle.json"
    return json.loads(p.read_text()) if p.exists() else None


def oracle_rho(scores: Optional[dict], oracle: Optional[dict]) -> Optional[float]:
    """Spearman ρ of a row's candidate scores with the phase-1 model's error on each candidate (the oracle's
    scores), over the candidates both name; None with fewer than 3."""
    from b3dgs.uq.metrics import spearman_rho

    if not scores or not oracle:
        return None
    names = sorted(set(scores) & set(oracle))
    if len(names) < 3:
        return None
    return spearman_rho([scores[n] for n in names], [oracle[n] for n in names], max_pixels=None)[0]


def summarize(out: Path, pairs=None) -> dict:
    """The scene folder's tables; ``pairs``: the paired rows (default :func:`pairs_for` of meta.json's lists)."""
    rows = [json.loads(p.read_text()) for p in sorted(out.glob("*_s*/result.json"))]
    meta = json.loads((out / "meta.json").read_text()) if (out / "meta.json").exists() else {}
    # meta's order first (the last invocation's policies), then rows of earlier invocations with other policies:
    # a study extended by a subset of its policies (or by new ones) keeps every finished row in its tables
    policies = list(meta.get("policies", []))
    policies += sorted({r["policy"] for r in rows} - set(policies))
    by = {(r["policy"], int(r["seed"])): r for r in rows}
    seeds = sorted({int(r["seed"]) for r in rows})
    table = {}
    for pol in policies:
        rs = [by[(pol, s)] for s in seeds if (pol, s) in by]
        if not rs:
            continue
        ent: dict[str, Any] = {"family": rs[0]["family"], "n_seeds": len(rs), "oracle": bool(rs[0].get("uses_ground_truth"))}
        for k in ("psnr", "ssim", "lpips", "train_time_s", "scoring_time_s"):
            ent[k], ent[k + "_sem"] = mean_sem([r.get(k) for r in rs])
        twins = sorted({r["training_shared_with"] for r in rs if r.get("training_shared_with")})
        ent["training_shared_with"] = twins or None
        hh = [r.get("hole_hits") for r in rs if r.get("hole_hits") is not None]
        ent["hole_hits"] = float(np.mean(hh)) if hh else None
        rhos = [rho for r in rs if (rho := oracle_rho(r.get("scores"), oracle_for(out, r["family"], int(r["seed"]))))
                is not None]
        ent["spearman_vs_oracle"], ent["spearman_vs_oracle_sem"] = mean_sem(rhos)
        table[pol] = ent
    jac = {}
    for a, b in combinations([p for p in policies if p in table], 2):
        vals = [jaccard(by[(a, s)]["selected"], by[(b, s)]["selected"]) for s in seeds if (a, s) in by and (b, s) in by]
        if vals:
            jac[f"{a}|{b}"] = float(np.mean(vals))
    paired = {}
    for a, b in pairs_for(policies, meta.get("pairs", ())) if pairs is None else pairs:
        d = [by[(a, s)]["psnr"] - by[(b, s)]["psnr"] for s in seeds if (a, s) in by and (b, s) in by
             and by[(a, s)]["psnr"] is not None and by[(b, s)]["psnr"] is not None]
        if d:
            m, sem = mean_sem(d)
            paired[f"{a}-{b}"] = {"delta_psnr": m, "sem": sem, "wins": int(sum(x > 0 for x in d)), "n": len(d),
                                  "per_seed": d}
    return {"scene": meta.get("scene", out.name), "meta": meta, "seeds": seeds, "table": table, "jaccard": jac,
            "paired": paired, "runs": rows}


def _fmt(m, s=None, nd=3):
    if m is None:
        return "—"
    return f"{m:.{nd}f}" if s is None else f"{m:.{nd}f} ± {s:.{nd}f}"


def _points(pf) -> str:
    if not isinstance(pf, dict):
        return "all (not filtered)"
    return f"{pf.get('kept')} of {pf.get('total')} kept (seen by >= 2 of the {pf.get('train_views')} initial views, {pf.get('method')})"


def markdown(summary: dict) -> str:
    meta = summary["meta"]
    side = meta.get("score_max_side")
    side = f"{side} px (longest side)" if side else "the training resolution"
    lines = [f"# Active view selection: {summary['scene']}", "",
             f"{len(meta.get('initial_views', []))} initial views → +{meta.get('acquire')} views; phase 1 "
             f"{meta.get('phase1_steps')} of {meta.get('total_steps')} steps; variant {meta.get('variant')}; seeds "
             f"{summary['seeds']}; scoring at {side}; initial points: "
             f"{_points(meta.get('point_filter'))}.", ""]
    rows = []
    for pol, e in sorted(summary["table"].items(), key=lambda kv: (kv[1]["family"] != "standard", kv[1]["family"])):
        name = f"{pol} (ORACLE, analysis only)" if e["oracle"] else pol
        if e.get("training_shared_with"):
            name += f" (same run as {', '.join(e['training_shared_with'])})"
        rows.append([e["family"], name, _fmt(e["psnr"], e["psnr_sem"]), _fmt(e["ssim"], e["ssim_sem"], 4),
                     _fmt(e["lpips"], e["lpips_sem"], 4), _fmt(e["spearman_vs_oracle"], e["spearman_vs_oracle_sem"], 2),
                     _fmt(e["train_time_s"], nd=1), _fmt(e["scoring_time_s"], nd=1), _fmt(e["hole_hits"], nd=1)])
    lines += markdown_table(["family", "policy", "PSNR ↑", "SSIM ↑", "LPIPS ↓", "ρ vs oracle error", "train s",
                             "scoring s", "hole hits"], rows)
    lines += ["", "Mean ± SEM over seeds. ρ: Spearman correlation of the policy's candidate scores with the phase-1 "
              "model's current render error on each candidate (the oracle's score; how informative the score is). "
              "'Same run as X': the row acquired X's views in X's order and its model trains bit for bit like X's "
              "(its posterior blocks only observe training), so X's second round is its result.", ""]
    if summary["paired"]:
        lines += markdown_table(["paired", "ΔPSNR (dB)", "scene-seed wins"],
                                [[k.replace("-", " − "), _fmt(v["delta_psnr"], v["sem"]), f"{v['wins']}/{v['n']}"]
                                 for k, v in summary["paired"].items()])
        lines.append("")
    if summary["jaccard"]:
        lines += ["Jaccard overlap of the selected sets (mean over seeds):", ""]
        lines += markdown_table(["pair", "Jaccard"], [[k.replace("|", " / "), f"{v:.2f}"] for k, v in summary["jaccard"].items()])
    return "\n".join(lines) + "\n"


def write_report(out: Path, plots: bool = True, store=None, pairs=None) -> dict:
    out = Path(out)
    summary = summarize(out, pairs)
    write_json(out / "study.json", summary)
    with atomic_path(out / "study.md") as tmp:  # concurrent seed jobs each rewrite it when they finish
        tmp.write_text(markdown(summary))
    if plots and summary["runs"]:
        try:
            make_plots(out, summary, store)
        except Exception as e:  # noqa: BLE001 - plots must never lose the numbers
            import logging

            logging.getLogger(__name__).warning("study plots failed: %s", e)
    return summary


def make_plots(out: Path, summary: dict, store=None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pdir = out / "plots"
    pdir.mkdir(exist_ok=True)
    table = summary["table"]
    names = list(table)
    fig, ax = plt.subplots(figsize=(1.0 + 0.9 * len(names), 3.2))
    m = [table[n]["psnr"] or 0 for n in names]
    e = [table[n]["psnr_sem"] or 0 for n in names]
    colors = ["tab:blue" if table[n]["family"] == "standard" else "tab:orange" for n in names]
    ax.bar(range(len(names)), m, yerr=e, color=colors, capsize=3)
    ax.set_xticks(range(len(names)), names, rotation=30, ha="right")
    lo = min(v - s for v, s in zip(m, e)) if m else 0
    ax.set(ylim=(lo - 0.5, max(v + s for v, s in zip(m, e)) + 0.3), ylabel="final test PSNR (dB)",
           title=f"{summary['scene']}: ±1 SEM over {len(summary['seeds'])} seeds (blue standard, orange NIW)")
    fig.tight_layout()
    save_figure(fig, pdir / "psnr.png", dpi=120)
    layout = out / "layout.json"
    if layout.exists():
        lay = json.loads(layout.read_text())
        seed = summary["seeds"][0]
        runs = {r["policy"]: r for r in summary["runs"] if int(r["seed"]) == seed}
        k = len(runs)
        cols = min(4, max(k, 1))
        rows_n = int(math.ceil(k / cols)) or 1
        xy = lay["xy"]
        pts = np.asarray(list(xy.values()), dtype=float).reshape(-1, 2)
        span = np.ptp(pts, axis=0) if len(pts) else np.ones(2)
        aspect = float(np.clip(span[1] / max(span[0], 1e-9), 0.2, 1.5))  # panel height follows the layout's shape
        fig, axes = plt.subplots(rows_n, cols, figsize=(3 * cols, (3 * aspect + 0.45) * rows_n + 0.5), squeeze=False)
        for ax, (pol, r) in zip(axes.flat, sorted(runs.items())):
            for n, (x, y) in xy.items():
                kind = "init" if n in lay["initial"] else "cand"
                ax.scatter([x], [y], s=10, c="k" if kind == "init" else "0.75", marker="s" if kind == "init" else "o")
            px = [xy[n] for n in r["selected"] if n in xy]
            if px:
                ax.scatter(*zip(*px), s=22, facecolors="none", edgecolors="r")
            ax.set_title(pol, fontsize=9)
            ax.set(aspect="equal", xticks=[], yticks=[])
        for ax in list(axes.flat)[k:]:
            ax.axis("off")
        fig.suptitle(f"top view (PCA plane), seed {seed}: black initial, grey candidates, red picks")
        fig.tight_layout()
        save_figure(fig, pdir / "layout.png", dpi=110)
    if store is not None:
        seed = summary["seeds"][0]
        runs = sorted((r for r in summary["runs"] if int(r["seed"]) == seed), key=lambda r: r["policy"])
        if runs:
            ncol = max(len(r["selected"]) for r in runs)
            fig, axes = plt.subplots(len(runs), ncol, figsize=(0.9 * ncol, 0.9 * len(runs) + 0.4), squeeze=False)
            for i, r in enumerate(runs):
                for j in range(ncol):
                    ax = axes[i, j]
                    ax.axis("off")
                    if j < len(r["selected"]) and r["selected"][j] in store:
                        ax.imshow(store.image(r["selected"][j]).clamp(0, 1).cpu().numpy())
                axes[i, 0].set_title(r["policy"], fontsize=7, loc="left")
            fig.tight_layout()
            save_figure(fig, pdir / "contact_sheet.png", dpi=100)
