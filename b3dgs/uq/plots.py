"""Uncertainty plots: sparsification curves, reliability diagram, and a render/GT/error/uncertainty panel.

Figures are built with matplotlib's object API on an Agg canvas (no pyplot global state, no display
needed) and written atomically: PNG bytes go to a temporary file in the target directory, which is then
renamed onto the target with ``os.replace`` (:func:`b3dgs.io.save_figure`).

Curve inputs accept any of: the ``"curves"`` dict of :func:`b3dgs.uq.metrics.evaluate_view`, the
``"mean_curves"`` dict of :func:`b3dgs.uq.metrics.summarize`, or either full result dict.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from b3dgs.errors import B3dgsError
from b3dgs.io import save_figure

__all__ = ["plot_sparsification", "plot_reliability", "plot_uncertainty_panel", "figure_to_array"]


def _np(x: Any) -> np.ndarray:
    import torch

    if isinstance(x, torch.Tensor):
        return x.detach().cpu().double().numpy()
    return np.asarray(x, dtype=np.float64)


def _curves_of(d: Mapping) -> Mapping:
    """Find the curves dict inside an evaluate_view / summarize result (or return ``d`` itself)."""
    if "fractions" in d or "levels" in d or "calibration" in d:
        return d
    for key in ("curves", "mean_curves"):
        if isinstance(d.get(key), Mapping):
            return d[key]
    raise B3dgsError("no curves found", "pass an evaluate_view result (its 'curves') or a summarize result "
                     "(its 'mean_curves')")


def _new_figure(figsize: tuple[float, float], dpi: int) -> Figure:
    fig = Figure(figsize=figsize, dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def figure_to_array(fig: Figure) -> np.ndarray:
    """Render ``fig`` to an (H, W, 3) uint8 RGB array (e.g. for TensorBoard ``add_image(..., dataformats='HWC')``)."""
    canvas = fig.canvas if isinstance(fig.canvas, FigureCanvasAgg) else FigureCanvasAgg(fig)
    canvas.draw()
    return np.array(canvas.buffer_rgba())[..., :3].copy()


def plot_sparsification(curves_by_regime: Mapping[str, Mapping], path: str | os.PathLike,
                        title: str | None = None, dpi: int = 100) -> Path:
    """Sparsification (solid) and oracle (dashed) curves, one colour per regime; RMSE and MAE panels.

    The legend gives each regime's AUSE recomputed from the plotted curves (trapezoid over the fraction
    axis), so the figure is self-consistent whichever normalisation produced the curves.
    """
    if not curves_by_regime:
        raise B3dgsError("curves_by_regime is empty",
                         fix="pass {regime name: sparsification curve} with at least one regime (b3dgs-eval's "
                             "uq.json holds them)")
    fig = _new_figure((10.0, 4.0), dpi)
    axes = fig.subplots(1, 2)
    colors = [f"C{i % 10}" for i in range(len(curves_by_regime))]
    for ax, metric in zip(axes, ("rmse", "mae")):
        for color, (name, d) in zip(colors, curves_by_regime.items()):
            c = _curves_of(d)
            f = _np(c["fractions"])
            sp, orc = _np(c[metric]["sparsification"]), _np(c[metric]["oracle"])
            area = float(np.trapezoid(np.maximum(sp - orc, 0.0), f))
            ax.plot(f, sp, color=color, lw=1.6, label=f"{name} (AUSE {area:.4g})")
            ax.plot(f, orc, color=color, lw=1.2, ls="--", label=f"{name} oracle")
        ax.set_xlabel("fraction of pixels removed (most uncertain first)")
        ax.set_ylabel(metric.upper() + " of remaining pixels")
        ax.set_title(f"Sparsification ({metric.upper()})")
        ax.set_xlim(0.0, 1.0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_reliability(levels_by_regime: Mapping[str, Mapping], path: str | os.PathLike,
                     title: str | None = None, dpi: int = 100) -> Path:
    """Reliability diagram: observed vs. nominal central-interval coverage per regime, with the diagonal.

    Each value may be ``{"levels", "observed"}``, an evaluate_view ``curves`` dict (its
    ``"calibration"`` entry is used), or a full evaluate_view / summarize result.
    """
    if not levels_by_regime:
        raise B3dgsError("levels_by_regime is empty",
                         fix="pass {regime name: calibration result} with at least one regime (b3dgs-eval's uq.json "
                             "holds them)")
    fig = _new_figure((5.0, 5.0), dpi)
    ax = fig.subplots()
    ax.plot([0, 1], [0, 1], color="0.5", lw=1.0, ls=":", label="ideal")
    for i, (name, d) in enumerate(levels_by_regime.items()):
        c = _curves_of(d)
        c = c["calibration"] if "calibration" in c else c
        p, obs = _np(c["levels"]), _np(c["observed"])
        ece = float(np.mean(np.abs(obs - p)))
        ax.plot(p, obs, marker="o", ms=3, color=f"C{i % 10}", label=f"{name} (ECE {ece:.3g})")
    ax.set_xlabel("nominal coverage")
    ax.set_ylabel("observed coverage")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title(title or "Reliability diagram")
    fig.tight_layout()
    return save_figure(fig, path)


def _image(x: Any, name: str) -> np.ndarray:
    a = _np(x)
    if a.ndim == 3 and a.shape[0] == 3 and a.shape[-1] != 3:  # CHW -> HWC
        a = np.moveaxis(a, 0, -1)
    if a.ndim != 3 or a.shape[-1] != 3:
        raise B3dgsError(f"{name} must be an (H, W, 3) image, got shape {a.shape}",
                         fix=f"pass {name} as an RGB image of shape (H, W, 3) (or (3, H, W))")
    return np.clip(np.nan_to_num(a), 0.0, 1.0)


def _map(x: Any, name: str, hw: tuple[int, int]) -> np.ndarray:
    a = _np(x)
    if a.ndim == 3 and a.shape[-1] == 1:
        a = a[..., 0]
    if a.ndim == 3 and a.shape[-1] == 3:  # a per-channel map: average over RGB
        a = a.mean(axis=-1)
    if a.shape != hw:
        raise B3dgsError(f"{name} must have shape {hw}, got {a.shape}",
                         fix=f"pass {name} at the render's size {hw} (one value per pixel, or (H, W, 3) averaged "
                             "over RGB)")
    return a


def plot_uncertainty_panel(render: Any, gt: Any, error_map: Any, uncertainty_map: Any,
                           path: str | os.PathLike | None, title: str = "",
                           dpi: int = 100) -> np.ndarray:
    """Render | GT | error | uncertainty side by side (colour bars on the two maps).

    Images are clipped to [0, 1] for display. Writes a PNG to ``path`` (skipped if ``path`` is None) and
    returns the figure as an (H, W, 3) uint8 array for TensorBoard.
    """
    r, g = _image(render, "render"), _image(gt, "gt")
    if r.shape != g.shape:
        raise B3dgsError(f"render {r.shape} and gt {g.shape} differ in shape",
                         fix="pass the render and the ground truth of the same view at the same size (H, W, 3)")
    hw = r.shape[:2]
    e, u = _map(error_map, "error_map", hw), _map(uncertainty_map, "uncertainty_map", hw)
    aspect = hw[1] / max(hw[0], 1)
    fig = _new_figure((4 * 3.2 * aspect + 1.2, 3.4), dpi)
    axes = fig.subplots(1, 4)
    axes[0].imshow(r)
    axes[0].set_title("render")
    axes[1].imshow(g)
    axes[1].set_title("ground truth")
    for ax, m, name, cmap in ((axes[2], e, "error", "magma"), (axes[3], u, "uncertainty", "viridis")):
        finite = m[np.isfinite(m)]
        lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
        im = ax.imshow(m, cmap=cmap, vmin=lo, vmax=hi if hi > lo else lo + 1e-12)
        ax.set_title(name)
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    arr = figure_to_array(fig)
    if path is not None:
        save_figure(fig, path)
    return arr
