"""The compression study's outputs: ``compression.json``, ``compression.md`` (laid out like the paper's keep-ratio
table, plus quality, size, speed and time per row, and paired differences) and ``plots/`` (PSNR against kept
Gaussians per scene; PSNR against compression time)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Optional

import numpy as np

from b3dgs.io import atomic_path, write_json
from b3dgs.report.document import markdown_table
from b3dgs.report.stats import mean_sem, paired_stats

# (a, b): report a − b where both are present. The paper's primary contrast, then the dedicated comparator
# against the posterior-aware score.
PAIRS = (("posterior_importance", "opacity"), ("pup", "posterior_importance"), ("pup", "opacity"))
METRICS = ("psnr", "ssim", "lpips", "kept_fraction", "num_gaussians", "render_fps", "time_s", "score_s", "finetune_s")


def load(out: Path) -> tuple[list[dict], list[dict], dict]:
    rows = [json.loads(p.read_text()) for p in sorted(out.glob("*/s*/*_k*/result.json"))]
    bases = [json.loads(p.read_text()) for p in sorted(out.glob("*/s*/base.json"))]
    meta = json.loads((out / "meta.json").read_text()) if (out / "meta.json").exists() else {}
    return rows, bases, meta


def _macro(per_scene: dict[str, list[float]]) -> Optional[float]:
    means = [float(np.mean(v)) for v in per_scene.values() if v]
    return float(np.mean(means)) if means else None


def summarize(out: Path) -> dict:
    rows, bases, meta = load(out)
    strategies = meta.get("strategies") or sorted({r["strategy"] for r in rows})
    keeps = sorted({float(r["keep"]) for r in rows}, reverse=True)
    scenes = sorted({r["scene"] for r in rows})
    cells: dict[str, dict[str, Any]] = {}
    for s in strategies:
        for k in keeps:
            rs = [r for r in rows if r["strategy"] == s and float(r["keep"]) == k]
            if not rs:
                continue
            ent: dict[str, Any] = {"strategy": s, "keep": k, "n_runs": len(rs), "scenes": {}}
            for sc in scenes:
                srs = [r for r in rs if r["scene"] == sc]
                if srs:
                    ent["scenes"][sc] = {m: mean_sem([r.get(m) for r in srs]) for m in METRICS}
                    ent["scenes"][sc]["n_seeds"] = len(srs)
            for m in METRICS:
                ent[m] = _macro({sc: [r[m] for r in rs if r["scene"] == sc and r.get(m) is not None] for sc in scenes})
            cells[f"{s}@{k}"] = ent
    base = {}
    for sc in scenes:
        bs = [b for b in bases if b["scene"] == sc]
        base[sc] = {m: mean_sem([b.get(m) for b in bs])[0] for m in ("psnr", "ssim", "lpips", "num_gaussians",
                                                                     "render_fps", "train_time_s")}
    base_macro = {m: (float(np.mean([base[sc][m] for sc in scenes if base[sc].get(m) is not None]))
                      if any(base[sc].get(m) is not None for sc in scenes) else None)
                  for m in ("psnr", "ssim", "lpips", "num_gaussians", "render_fps", "train_time_s")}
    pairs = []
    for a, b in PAIRS:
        if a not in strategies or b not in strategies:
            continue
        for k in keeps:
            by = {(r["strategy"], r["scene"], int(r["seed"])): r for r in rows if float(r["keep"]) == k}
            units = sorted({(sc, sd) for (st, sc, sd) in by if st == a} & {(sc, sd) for (st, sc, sd) in by if st == b})
            if not units:
                continue
            d_unit = [by[(a, sc, sd)]["psnr"] - by[(b, sc, sd)]["psnr"] for sc, sd in units]
            per_scene = {sc: float(np.mean([d for (u, d) in zip(units, d_unit) if u[0] == sc])) for sc in scenes
                         if any(u[0] == sc for u in units)}
            st = paired_stats(list(per_scene.values()), higher_is_better=True)
            pairs.append({"a": a, "b": b, "keep": k, "per_scene": per_scene, "scene_seed_wins": int(sum(d > 0 for d in d_unit)),
                          "scene_seed_n": len(d_unit), **st})
    return {"strategies": strategies, "keeps": keeps, "scenes": scenes, "cells": cells, "base": base,
            "base_macro": base_macro, "pairs": pairs, "meta": meta, "n_rows": len(rows)}


def _f(v, nd=3, signed=False) -> str:
    if v is None:
        return "—"
    return f"{v:+.{nd}f}" if signed else f"{v:.{nd}f}"


def markdown(s: dict) -> str:
    st, keeps, cells = s["strategies"], s["keeps"], s["cells"]
    meta = s.get("meta", {})
    L = ["# Compression ladder on matched checkpoints", ""]
    L.append(f"{s['n_rows']} rows over scenes {s['scenes']}; every score and keep ratio starts from the same finished "
             f"standard run per scene and seed (base runs: {len(meta.get('base_runs', []))}). Fine-tune "
             f"{meta.get('finetune_steps')} steps per prune round, training views scored at "
             f"{meta.get('score_max_side') or 'full size'} px. Macro means over scenes of per-scene seed means.")
    L += ["", "## PSNR by keep ratio (the paper's layout)", ""]
    cols = [x for x in st if any(f"{x}@{k}" in cells for k in keeps)]
    extra = [(a, b) for a, b in PAIRS if a in cols and b in cols]
    rows = []
    for k in keeps:
        vals = {c: cells.get(f"{c}@{k}", {}).get("psnr") for c in cols}
        best = max((v for v in vals.values() if v is not None), default=None)
        cell = [("**" + _f(vals[c]) + "**") if vals[c] is not None and vals[c] == best else _f(vals[c]) for c in cols]
        diffs = [_f(None if vals[a] is None or vals[b] is None else vals[a] - vals[b], signed=True) for a, b in extra]
        rows.append([str(int(round(k * 100))), *cell, *diffs])
    L += markdown_table(["Keep %", *cols, *(f"{a} − {b}" for a, b in extra)], rows)
    bm = s["base_macro"]
    L += ["", f"Base (no pruning): PSNR {_f(bm.get('psnr'))}, LPIPS {_f(bm.get('lpips'), 4)}, "
          f"{_f(bm.get('num_gaussians'), 0)} Gaussians, {_f(bm.get('render_fps'), 1)} FPS, trained in "
          f"{_f(bm.get('train_time_s'), 0)} s.", ""]
    L += ["## Quality, size, speed and time per row", ""]
    rows = [[c, str(int(round(k * 100))), _f(e["psnr"]), _f(e["ssim"], 4), _f(e["lpips"], 4),
             _f(100 * e["kept_fraction"] if e["kept_fraction"] is not None else None, 1), _f(e["num_gaussians"], 0),
             _f(e["render_fps"], 1), _f(e["score_s"], 1), _f(e["finetune_s"], 1), _f(e["time_s"], 1), str(e["n_runs"])]
            for c in cols for k in keeps for e in [cells.get(f"{c}@{k}")] if e]
    L += markdown_table(["Score", "Keep %", "PSNR ↑", "SSIM ↑", "LPIPS ↓", "kept % of base", "#Gaussians", "FPS ↑",
                         "score s", "fine-tune s", "compression s", "runs"], rows)
    L += ["", "compression s = scoring (every round; the first round's scores are computed once per base and shared "
          "by the keep ratios, each row still counts them) + fine-tuning; the base's own training time is above.", ""]
    L += ["## Per-scene PSNR (seed mean ± SEM)", ""]
    rows = []
    for c in cols:
        for k in keeps:
            e = cells.get(f"{c}@{k}")
            if not e:
                continue
            parts = []
            for sc in s["scenes"]:
                v = e["scenes"].get(sc)
                parts.append("—" if not v else f"{_f(v['psnr'][0])} ± {_f(v['psnr'][1])} (n={v['n_seeds']})")
            rows.append([c, str(int(round(k * 100))), *parts])
    rows.append(["base", "100", *(_f(s["base"][sc].get("psnr")) for sc in s["scenes"])])
    L += markdown_table(["Score", "Keep %", *s["scenes"]], rows)
    if s["pairs"]:
        L += ["", "## Paired PSNR differences", ""]
        L += markdown_table(["a − b", "Keep %", "mean Δ (scenes)", "CI", "CI method", "scene wins / losses", "p (2-sided)",
                             "p floor", "scene-seed wins"],
                            [[f"{p['a']} − {p['b']}", str(int(round(p["keep"] * 100))), _f(p["mean"], 3, True),
                              f"[{_f(p['ci'].get('low'), 3, True)}, {_f(p['ci'].get('high'), 3, True)}]",
                              p["ci"].get("method", "—"), f"{p['wins']} / {p['losses']}", _f(p["p_two_sided"], 3),
                              _f(p["p_floor"], 3), f"{p['scene_seed_wins']}/{p['scene_seed_n']}"] for p in s["pairs"]])
        L += ["", "Units are scenes (per-scene means over seeds): cluster bootstrap CI and exact sign-flip p "
              "(b3dgs.report.stats); with n scenes no two-sided p can fall below 2/2ⁿ."]
    if s.get("plots"):  # relative to the markdown file
        L += ["", "![PSNR against kept Gaussians](plots/ladder.png)", "",
              "![PSNR against compression time](plots/time.png)"]
    return "\n".join(L) + "\n"


def plot(s: dict, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = out / "plots"
    d.mkdir(parents=True, exist_ok=True)
    written = []
    scenes = s["scenes"]
    fig, axes = plt.subplots(1, max(1, len(scenes)), figsize=(5.2 * max(1, len(scenes)), 4.0), squeeze=False)
    for ax, sc in zip(axes[0], scenes):
        for c in s["strategies"]:
            pts = []
            for k in s["keeps"]:
                e = s["cells"].get(f"{c}@{k}", {}).get("scenes", {}).get(sc)
                if e:
                    pts.append((e["num_gaussians"][0], e["psnr"][0], e["psnr"][1] or 0.0))
            if pts:
                x, y, err = zip(*sorted(pts))
                ax.errorbar(x, y, yerr=err, marker="o", ms=4, capsize=2, label=c)
        b = s["base"].get(sc, {})
        if b.get("psnr") is not None:
            ax.plot([b["num_gaussians"]], [b["psnr"]], marker="*", ms=12, color="k", ls="none", label="base")
        ax.set_xscale("log")
        ax.set_xlabel("Gaussians kept")
        ax.set_ylabel("test PSNR (dB)")
        ax.set_title(sc)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(d / "ladder.png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    written.append("plots/ladder.png")

    fig, ax = plt.subplots(figsize=(6.0, 4.2))
    for c in s["strategies"]:
        pts = [(e["time_s"], e["psnr"], int(round(e["keep"] * 100))) for k in s["keeps"]
               if (e := s["cells"].get(f"{c}@{k}")) and e.get("time_s") is not None]
        if pts:
            x, y, lab = zip(*pts)
            ax.plot(x, y, marker="o", ls="-", label=c)
            for xi, yi, li in pts:
                ax.annotate(f"{li}%", (xi, yi), fontsize=6, xytext=(2, 2), textcoords="offset points")
    ax.set_xlabel("compression time per row (s): scoring + fine-tuning")
    ax.set_ylabel("test PSNR (dB), macro over scenes")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(d / "time.png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    written.append("plots/time.png")
    return written


def write_report(out: Path, plots: bool = True) -> dict:
    out = Path(out)
    s = summarize(out)
    if plots and s["n_rows"]:
        s["plots"] = plot(s, out)
    write_json(out / "compression.json", s)
    with atomic_path(out / "compression.md") as tmp:
        Path(tmp).write_text(markdown(s))
    return s
