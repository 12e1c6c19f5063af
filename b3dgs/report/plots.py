"""The report's figures (matplotlib, Agg), drawn from the analysis dicts and written atomically as PNG."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from b3dgs.io import save_figure  # noqa: E402
from b3dgs.report.analysis import PARETO_AXES  # noqa: E402
from b3dgs.report.collect import METHOD_ORDER, method_order  # noqa: E402

__all__ = ["plot_curves", "plot_pareto", "plot_paired", "plot_ood", "plot_levels"]

ZERO = 1e-9  # a paired difference this small is float noise of identical runs


def _color(method: str) -> str:
    i = METHOD_ORDER.index(method) if method in METHOD_ORDER else len(METHOD_ORDER) + sum(map(ord, method)) % 5
    return f"C{i % 10}"


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    return save_figure(fig, path)


def _grid(n: int, ncols: int = 3, size=(4.2, 3.2)):
    ncols = max(1, min(ncols, n))
    nrows = math.ceil(n / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(size[0] * ncols, size[1] * nrows), dpi=100, squeeze=False)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    return fig, list(axes.flat)


def plot_curves(curves: dict, path: Path, ylabel: str = "test PSNR (dB)") -> Path:
    """One panel per scene: the seed mean of each method against training seconds, ±1 SEM band."""
    fig, axes = _grid(len(curves))
    for ax, (scene, by_m) in zip(axes, curves.items()):
        for m in method_order(by_m):
            c = by_m[m]
            ax.plot(c["t"], c["y"], "o-", ms=3, color=_color(m), label=f"{m} (n={c['n_seeds']})")
            if all(s is not None for s in c["sem"]):
                lo = [y - s for y, s in zip(c["y"], c["sem"])]
                hi = [y + s for y, s in zip(c["y"], c["sem"])]
                ax.fill_between(c["t"], lo, hi, color=_color(m), alpha=0.2, lw=0)
        ax.set_title(scene, fontsize=10)
        ax.set(xlabel="training time (s)", ylabel=ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    return _save(fig, path)


def plot_pareto(panels: dict, path: Path) -> Path:
    """Rows: scenes (and the macro mean); columns: PSNR against train time, #Gaussians, render FPS.
    Frontier methods are ringed and joined by a dashed line."""
    fig, axes = plt.subplots(len(panels), len(PARETO_AXES), figsize=(4.2 * len(PARETO_AXES), 3.1 * len(panels)),
                             dpi=100, squeeze=False)
    for row, (label, panel) in zip(axes, panels.items()):
        pts = panel["points"]
        for ax, (axis, xlabel, _) in zip(row, PARETO_AXES):
            for m, p in pts.items():
                if p[axis] is None or p["psnr"] is None:
                    continue
                ax.scatter(p[axis], p["psnr"], color=_color(m), s=40, zorder=3, label=m)
            front = panel["front"][axis]
            if front:
                ax.plot([pts[m][axis] for m in front], [pts[m]["psnr"] for m in front], "k--", lw=1, zorder=2)
                ax.scatter([pts[m][axis] for m in front], [pts[m]["psnr"] for m in front], s=140,
                           facecolors="none", edgecolors="k", zorder=4, label="frontier")
            ax.set(xlabel=xlabel, ylabel="PSNR (dB)")
            ax.set_title(f"{label}", fontsize=9)
            ax.grid(alpha=0.3)
        row[0].legend(fontsize=7)
    return _save(fig, path)


def plot_paired(results: Sequence[dict], path: Path) -> Path:
    """One panel per metric: per-scene Δ (points), the mean Δ (line) and its bootstrap CI (band); a metric whose
    Δ is zero in every scene gets a panel saying so."""
    fig, axes = _grid(len(results), ncols=len(results))
    for ax, r in zip(axes, results):
        scenes = list(r["per_scene"])
        if scenes and all(abs(v) <= ZERO for v in r["per_scene"].values()):  # identical runs: say so, not a 1e-17 axis
            ax.text(0.5, 0.5, f"Δ = 0 in all {len(scenes)} scenes\n({r['a']} and {r['b']} are identical)",
                    ha="center", va="center", transform=ax.transAxes, fontsize=9)
            ax.set(xticks=[], yticks=[])
            ax.set_title(f"Δ{r['metric']} ({r['a']} − {r['b']})", fontsize=9)
            continue
        ax.axhline(0, color="grey", lw=1)
        ax.bar(range(len(scenes)), [r["per_scene"][s] for s in scenes], color="C0", alpha=0.7)
        if r["mean"] is not None:
            ax.axhline(r["mean"], color="k", lw=1.5, label=f"mean {r['mean']:+.4g}")
        ci = r["ci"]
        if ci.get("low") is not None:
            ax.axhspan(ci["low"], ci["high"], color="k", alpha=0.12, label=f"{round(100 * r['confidence'])}% CI ({ci['method']})")
        ax.set_xticks(range(len(scenes)))
        ax.set_xticklabels(scenes, rotation=30, ha="right", fontsize=8)
        ax.set_title(f"Δ{r['metric']} ({r['a']} − {r['b']}), p={_p(r)}", fontsize=9)
        ax.legend(fontsize=7)
    return _save(fig, path)


def _p(r: dict) -> str:
    return "n/a" if r["p_two_sided"] is None else f"{r['p_two_sided']:.3g} (floor {r['p_floor']:.3g})"


def plot_ood(views: Sequence[dict], path: Path) -> Path:
    """One panel per detector row: per-view uncertainty against support score, ID / OOD / middle band."""
    rows = list(dict.fromkeys(v["row"] for v in views))
    fig, axes = _grid(len(rows))
    names = {0: ("ID (best supported)", "C2"), 1: ("OOD (worst supported)", "C3"), -1: ("middle (ignored)", "0.6")}
    for ax, row in zip(axes, rows):
        sel = [v for v in views if v["row"] == row]
        for lab, (name, color) in names.items():
            vs = [v for v in sel if v["label"] == lab]
            ax.scatter([v["support"] for v in vs], [v["uncertainty"] for v in vs], s=14, color=color, label=name)
        ax.set(yscale="log", xlabel="support score (nearest train camera / extent)", ylabel="mean per-view uncertainty")
        ax.set_title(row, fontsize=9)
        ax.legend(fontsize=7)
    return _save(fig, path)


def plot_levels(table: dict, path: Path, xlabel: str, keys=(("psnr", "PSNR (dB)"), ("train_time_s", "train time (s)"))) -> Path:
    """A study's macro means against its level (train-view budget, init cap), one line per method."""
    fig, axes = _grid(len(keys), ncols=len(keys))
    levels = list(table)
    for ax, (key, label) in zip(axes, keys):
        methods = method_order({m for lv in table.values() for m in lv})
        for m in methods:
            xs = [i for i, lv in enumerate(levels) if table[lv].get(m, {}).get(key) is not None]
            ax.plot(xs, [table[levels[i]][m][key] for i in xs], "o-", color=_color(m), label=m)
        ax.set(xticks=range(len(levels)), xticklabels=[str(lv) for lv in levels], xlabel=xlabel, ylabel=label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    return _save(fig, path)
