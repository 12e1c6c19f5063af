"""Per-view uncertainty-quality metrics: AUSE, regression ECE, Gaussian NLL, Cov@95, Spearman rho.

Inputs (one held-out view)
--------------------------
``mean``  (H, W, 3)  predictive mean image (the rendered colour).
``var``   (H, W)     predictive variance per pixel. It is *isotropic over RGB*: the same variance is used
                     for each of the three channels (the paper's ``u_p + sigma^2``).
``gt``    (H, W, 3)  ground-truth image.
``mask``  (H, W)     optional bool; only pixels where it is True are scored.

Arrays may be numpy arrays or torch tensors; everything is converted to float64 numpy internally.

Per-pixel quantities (pixel ``p``, channels ``c`` in RGB, residual ``r_pc = gt_pc - mean_pc``)
---------------------------------------------------------------------------------------------
* absolute error (MAE sparsification, Spearman):  ``a_p = (1/3) sum_c |r_pc|``
* squared error  (RMSE sparsification):            ``s_p = (1/3) sum_c r_pc^2``
* uncertainty score used for ranking:              ``var_p`` (its square root gives the same order).

Metrics
-------
* **AUSE** (area under the sparsification error), for RMSE and for MAE. Pixels are sorted by uncertainty,
  most uncertain first; for each fraction ``f`` of a grid (default ``0, 0.01, ..., 0.99``: 100 points) the
  ``floor(f * N)`` most uncertain pixels are removed and the metric (RMSE = sqrt of the mean of ``s_p``,
  MAE = mean of ``a_p``) is computed over the rest -> sparsification curve. The oracle curve is built the
  same way but sorted by the true per-pixel error (``s_p`` for RMSE, ``a_p`` for MAE), which makes it the
  pointwise lower bound. AUSE = trapezoidal area of (sparsification - oracle) over the fraction grid
  (the fraction axis itself is the x axis, so with the default grid the integral spans [0, 0.99]).
  Sorting is stable: ties are broken by the row-major pixel index (the earlier pixel is removed first),
  so results are deterministic.

  Normalisation (reported in the result under ``"ause_normalization"``):
    - ``normalize=False`` (**default**, "raw"): curves are in the error's own units (colour intensity
      in whatever range the images use, e.g. [0, 1]).
    - ``normalize=True``: both curves are divided by the error of the full set, so ``curve[0] == 1``;
      AUSE is then scale-free. (Since both curves share that divisor, normalised AUSE = raw AUSE /
      full-set error; ``rmse`` and ``mae`` are returned so either variant can be recovered.)
  Raw is the default: it compares with the paper's AUSE (order 1e-2 for [0, 1] colours) and does not blow up for
  near-perfect views; always compare within one convention.

* **ECE for regression** (interval calibration). For each nominal central level ``p`` the interval is
  ``mean_pc +- z_{(1+p)/2} * sqrt(var_p)``; observed coverage is the fraction of (pixel, channel)
  residuals inside it (inclusive bounds); ECE = mean over levels of ``|observed - p|``. Default levels are
  ``0.05, 0.10, ..., 0.95`` (19 evenly spaced; a 0.99 tail level would be dominated by a few outliers; pass ``levels=``
  to change them). Coverage uses the unfloored variance: a zero variance is a zero-width interval.
* **Cov@95** = observed coverage of the nominal 95% interval (``z = 1.959964``), and
  ``cov95_err = |Cov@95 - 0.95|`` (the paper's headline calibration statistic).
* **Gaussian NLL** = mean over pixels and channels of ``0.5 log(2 pi v) + 0.5 r^2 / v`` with
  ``v = max(var_p, var_floor)`` (default ``var_floor = 1e-8``, i.e. a standard deviation of 1e-4 for
  [0, 1] colours). The number of pixels whose variance was raised to the floor is returned as
  ``nll_n_floored`` -- the flooring is never silent. NLL is only comparable within one uncertainty
  regime (e.g. native posterior vs. native posterior), not across regimes built differently.
* **Spearman rho** between ``var_p`` and ``a_p`` (average ranks for ties, Pearson correlation of the
  ranks). If more than ``max_spearman_pixels`` (default 200 000) pixels are scored, a subset of that size
  is drawn without replacement with ``numpy.random.default_rng(seed)`` (default seed 0), so the value is
  deterministic. rho is NaN if either variable is constant on the scored pixels.

Epistemic part alone (:func:`epistemic_view`, :func:`epistemic_summary`), for regimes whose variance is
``u_p`` plus a constant (native: ``u_p + σ̂²``): the AUSE of ``u_p`` (RMSE and MAE), the Spearman rho
(``scipy.stats.spearmanr``) of ``u_p`` with the per-pixel squared error ``s_p``, the view's mean ``u_p``
and its share of the mean predictive variance; over the views, rho between the per-view mean ``u_p``
and the per-view MSE, and the epistemic fraction (sum of the views' mean ``u_p`` over the sum of their
mean variance).

Scene summaries (:func:`summarize`): every scalar, AUSE and ECE included, is computed *per view* and then
averaged over views (a macro average); pixels are never pooled across views.
"""
from __future__ import annotations

import math
from statistics import NormalDist
from typing import Any, Iterable, Sequence

import numpy as np

from b3dgs.errors import B3dgsError, B3dgsTypeError
from b3dgs.io import to_jsonable  # noqa: F401 - re-exported: the one JSON converter lives in b3dgs.io

__all__ = ["DEFAULT_FRACTIONS", "DEFAULT_LEVELS", "DEFAULT_VAR_FLOOR", "DEFAULT_MAX_SPEARMAN_PIXELS", "Z95",
           "AUSE_NORMALIZATION_RAW", "AUSE_NORMALIZATION_NORMALIZED", "NLL_NOTE", "per_pixel_errors", "sparsification",
           "ause", "coverage", "calibration", "gaussian_nll", "spearman_rho", "evaluate_view", "epistemic_view",
           "epistemic_summary", "summarize", "to_jsonable"]

DEFAULT_FRACTIONS: np.ndarray = np.arange(100) / 100.0  # 0.00, 0.01, ..., 0.99
DEFAULT_LEVELS: np.ndarray = np.arange(1, 20) * 0.05  # 0.05, 0.10, ..., 0.95
DEFAULT_VAR_FLOOR = 1e-8
DEFAULT_MAX_SPEARMAN_PIXELS = 200_000
Z95 = 1.959964  # z_{0.975}
AUSE_NORMALIZATION_RAW = "raw: curves in the error's own units (not normalised)"
AUSE_NORMALIZATION_NORMALIZED = "curves normalised by the error of the full set (curve[0]=1)"
NLL_NOTE = ("NLL is comparable only within one uncertainty regime (same variance construction); "
            "do not rank proxy, native and ensemble variances against each other by NLL.")
AGGREGATION_NOTE = ("All scalars (AUSE and ECE included) are computed per view and then averaged over "
                    "views; pixels are not pooled across views.")


# ------------------------------------------------------------------------------------ validation
def _to_numpy(x: Any, name: str) -> np.ndarray:
    if x is None:
        raise B3dgsError(f"{name} is None", fix=f"pass {name} as a numpy array or torch tensor")
    import torch

    if isinstance(x, torch.Tensor):
        x = x.detach().cpu()
        x = x.numpy() if x.dtype == torch.bool else x.double().numpy()
    return np.asarray(x)


def _validate(mean: Any, var: Any, gt: Any, mask: Any = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Check shapes/values and return the scored pixels as ``mean (N,3)``, ``var (N,)``, ``gt (N,3)``."""
    mean = _to_numpy(mean, "mean")
    gt = _to_numpy(gt, "gt")
    var = _to_numpy(var, "var")
    for name, a in (("mean", mean), ("gt", gt), ("var", var)):
        if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            raise B3dgsTypeError(f"{name} must be a real numeric array, got dtype {a.dtype}", f"pass {name} as floats")
    if mean.ndim != 3 or mean.shape[-1] != 3:
        raise B3dgsError(f"mean must have shape (H, W, 3), got {tuple(mean.shape)}",
                         fix="pass the rendered colour image as mean, a float array of shape (H, W, 3)")
    if gt.shape != mean.shape:
        raise B3dgsError(f"gt shape {tuple(gt.shape)} does not match mean shape {tuple(mean.shape)}",
                         fix="pass the ground-truth image of the same view at the rendered size, shape (H, W, 3) "
                             "like mean")
    if var.ndim == 3 and var.shape[-1] == 1:
        var = var[..., 0]
    if var.shape != mean.shape[:2]:
        raise B3dgsError(f"var must have shape (H, W) = {tuple(mean.shape[:2])} "
                         f"(one variance per pixel, shared by RGB), got {tuple(var.shape)}",
                         fix="pass one variance per pixel, shape (H, W) or (H, W, 1); reduce a per-channel (H, W, 3) "
                             "variance with .mean(-1)")
    if mean.shape[0] * mean.shape[1] == 0:
        raise B3dgsError("empty image", fix="pass a view with at least one pixel (H, W >= 1)")
    mean, gt, var = (a.astype(np.float64, copy=False) for a in (mean, gt, var))
    for name, a, fix in (
            ("mean", mean, "the render is not finite: check the model (retrain, or lower the optimiser's learning "
                           "rates) before scoring it"),
            ("gt", gt, "load the ground-truth image as finite floats in [0, 1] (b3dgs.data.images.load_image does)"),
            ("var", var, "the UQ regime's predict returned a non-finite variance: check that regime (uq=...) and its "
                         "posterior block")):
        if not np.all(np.isfinite(a)):
            raise B3dgsError(f"{name} contains NaN or Inf", fix=fix)
    if np.any(var < 0):
        raise B3dgsError(f"var must be >= 0 (min is {float(var.min())})",
                         fix="pass variances >= 0 (a standard deviation squared); clip tiny negative rounding errors "
                             "with numpy.clip(var, 0, None)")
    hw = tuple(int(d) for d in mean.shape[:2])
    mean, gt, var = mean.reshape(-1, 3), gt.reshape(-1, 3), var.reshape(-1)
    if mask is not None:
        mask = _to_numpy(mask, "mask")
        if mask.dtype != np.bool_:
            raise B3dgsTypeError(f"mask must be a bool array, got dtype {mask.dtype}", "pass mask.astype(bool)")
        if mask.ndim == 3 and mask.shape[-1] == 1:
            mask = mask[..., 0]
        if mask.shape != hw:
            raise B3dgsError(f"mask must have shape (H, W) = {hw}, got {tuple(mask.shape)}",
                             fix="pass a bool mask of the image's shape (H, W), or mask=None to score every pixel")
        mask = mask.reshape(-1)
        mean, gt, var = mean[mask], gt[mask], var[mask]
        if var.size == 0:
            raise B3dgsError("mask selects no pixels", fix="pass a mask with at least one True pixel, or mask=None")
    return mean, var, gt


def _check_fractions(fractions: Iterable[float] | None) -> np.ndarray:
    f = DEFAULT_FRACTIONS.copy() if fractions is None else np.asarray(list(fractions), dtype=np.float64)
    if f.ndim != 1 or f.size < 2:
        raise B3dgsError("fractions must be a 1-D grid with at least two points",
                         fix="pass fractions as a 1-D list of at least two values, e.g. [0, 0.01, ..., 0.99] (the "
                             "default when None)")
    if not np.all(np.isfinite(f)) or f.min() < 0 or f.max() >= 1:
        raise B3dgsError("fractions must lie in [0, 1)",
                         fix="pass fractions in [0, 1), e.g. numpy.arange(100) / 100 (the default when None)")
    if np.any(np.diff(f) <= 0):
        raise B3dgsError("fractions must be strictly increasing",
                         fix="sort the fractions in ascending order and drop duplicates (numpy.unique does both)")
    return f


def _check_levels(levels: Iterable[float] | None) -> np.ndarray:
    p = DEFAULT_LEVELS.copy() if levels is None else np.asarray(list(levels), dtype=np.float64)
    if p.ndim != 1 or p.size < 1:
        raise B3dgsError("levels must be a non-empty 1-D grid",
                         fix="pass levels as a 1-D list of at least one value, e.g. [0.05, 0.10, ..., 0.95] (the "
                             "default when None)")
    if not np.all(np.isfinite(p)) or p.min() <= 0 or p.max() >= 1:
        raise B3dgsError("levels must lie in (0, 1)", fix="pass levels strictly between 0 and 1, e.g. [0.5, 0.9, 0.95]")
    return p


# ----------------------------------------------------------------------------------- per pixel
def per_pixel_errors(mean: Any, gt: Any) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(abs_err, sq_err)``: mean over the last (RGB) axis of ``|mean-gt|`` and ``(mean-gt)^2``."""
    r = _to_numpy(gt, "gt").astype(np.float64) - _to_numpy(mean, "mean").astype(np.float64)
    return np.abs(r).mean(axis=-1), (r * r).mean(axis=-1)


# ------------------------------------------------------------------------------- sparsification
def _removed_counts(n: int, fractions: np.ndarray) -> np.ndarray:
    # floor(f * n), guarded against f * n landing a hair below an integer (0.29 * 100 = 28.999...).
    k = np.floor(np.round(fractions * n, 6)).astype(np.int64)
    return np.clip(k, 0, n - 1)  # always keep at least one pixel


def _curve(values_sorted: np.ndarray, removed: np.ndarray, metric: str) -> np.ndarray:
    """Metric over ``values_sorted[k:]`` for each ``k`` in ``removed``; values are s_p or a_p."""
    n = values_sorted.size
    suffix = np.concatenate([np.cumsum(values_sorted[::-1])[::-1], [0.0]])  # suffix[k] = sum(v[k:])
    m = suffix[removed] / (n - removed)
    m = np.maximum(m, 0.0)  # cumulative-sum round-off can go a hair below 0 for an all-zero tail
    return np.sqrt(m) if metric == "rmse" else m


def sparsification(uncertainty: Any, error: Any, metric: str = "rmse",
                   fractions: Iterable[float] | None = None, normalize: bool = False) -> dict:
    """Sparsification and oracle curves for one set of pixels.

    ``uncertainty`` and ``error`` are 1-D per-pixel arrays of equal length (already masked); ``error``
    is the per-pixel squared error ``s_p`` when ``metric == "rmse"`` and the absolute error ``a_p``
    when ``metric == "mae"``. See the module docstring for the definition and normalisation.
    Returns ``{"fractions", "sparsification", "oracle", "ause", "full_error", "normalize",
    "ause_normalization", "metric"}``.
    """
    if metric not in ("rmse", "mae"):
        raise B3dgsError(f"metric must be 'rmse' or 'mae', got {metric!r}", fix="pass metric='rmse' or metric='mae'")
    u = np.asarray(_to_numpy(uncertainty, "uncertainty"), dtype=np.float64).reshape(-1)
    e = np.asarray(_to_numpy(error, "error"), dtype=np.float64).reshape(-1)
    if u.shape != e.shape or u.size == 0:
        raise B3dgsError(f"uncertainty and error must be non-empty and equally long ({u.size} vs {e.size})",
                         fix="pass one uncertainty per error value, both flattened from the same pixels and "
                             "non-empty")
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(e))):
        raise B3dgsError("uncertainty/error contain NaN or Inf",
                         fix="pass finite uncertainties and errors (drop NaN pixels with a mask first)")
    if np.any(e < 0):
        raise B3dgsError("per-pixel error must be >= 0",
                         fix="pass a non-negative per-pixel error, e.g. the absolute or squared residual "
                             "(per_pixel_errors gives both)")
    f = _check_fractions(fractions)
    removed = _removed_counts(u.size, f)
    # descending, stable: negate and use a stable ascending sort (ties keep the row-major order)
    order_u = np.argsort(-u, kind="stable")
    order_e = np.argsort(-e, kind="stable")
    spars = _curve(e[order_u], removed, metric)
    oracle = _curve(e[order_e], removed, metric)
    full = float(_curve(e, np.array([0]), metric)[0])
    if normalize and full > 0:
        spars, oracle = spars / full, oracle / full
    # the oracle is the pointwise lower bound; clip round-off so the area is never negative
    gap = np.maximum(spars - oracle, 0.0)
    return {"metric": metric, "fractions": f, "sparsification": spars, "oracle": oracle,
            "ause": float(np.trapezoid(gap, f)), "full_error": full, "normalize": bool(normalize),
            "ause_normalization": AUSE_NORMALIZATION_NORMALIZED if normalize else AUSE_NORMALIZATION_RAW}


def ause(mean: Any, var: Any, gt: Any, mask: Any = None, metric: str = "rmse",
         fractions: Iterable[float] | None = None, normalize: bool = False) -> dict:
    """AUSE of one view for ``metric`` in {"rmse", "mae"}; see :func:`sparsification`."""
    m, v, g = _validate(mean, var, gt, mask)
    a, s = per_pixel_errors(m, g)
    return sparsification(v, s if metric == "rmse" else a, metric=metric, fractions=fractions,
                          normalize=normalize)


# --------------------------------------------------------------------------------- calibration
def _standardized_abs_residuals(m: np.ndarray, v: np.ndarray, g: np.ndarray) -> np.ndarray:
    """|r| / sqrt(var) per (pixel, channel), with 0/0 -> 0 (inside any interval) and x/0 -> inf."""
    r = np.abs(g - m)
    sd = np.broadcast_to(np.sqrt(v)[:, None], r.shape)
    t = np.full(r.shape, np.inf)
    pos = sd > 0
    t[pos] = r[pos] / sd[pos]
    t[(~pos) & (r == 0)] = 0.0
    return t.reshape(-1)


def _z(levels: np.ndarray) -> np.ndarray:
    nd = NormalDist()
    return np.array([nd.inv_cdf(0.5 * (1.0 + p)) for p in levels], dtype=np.float64)


def _coverage_from_t(t_sorted: np.ndarray, z: np.ndarray) -> np.ndarray:
    return np.searchsorted(t_sorted, z, side="right") / t_sorted.size  # inclusive: |r| <= z * sd


def coverage(mean: Any, var: Any, gt: Any, mask: Any = None, level: float = 0.95) -> float:
    """Fraction of (pixel, channel) residuals inside the central ``level`` Gaussian interval."""
    m, v, g = _validate(mean, var, gt, mask)
    z = np.array([Z95]) if level == 0.95 else _z(_check_levels([level]))
    return float(_coverage_from_t(np.sort(_standardized_abs_residuals(m, v, g)), z)[0])


def calibration(mean: Any, var: Any, gt: Any, mask: Any = None,
                levels: Iterable[float] | None = None) -> dict:
    """Reliability data and regression ECE: ``{"levels", "observed", "ece"}`` (see module docstring)."""
    m, v, g = _validate(mean, var, gt, mask)
    p = _check_levels(levels)
    obs = _coverage_from_t(np.sort(_standardized_abs_residuals(m, v, g)), _z(p))
    return {"levels": p, "observed": obs, "ece": float(np.mean(np.abs(obs - p)))}


def gaussian_nll(mean: Any, var: Any, gt: Any, mask: Any = None,
                 var_floor: float = DEFAULT_VAR_FLOOR) -> dict:
    """Mean Gaussian NLL over pixels and channels, with the variance floored at ``var_floor``.

    Returns ``{"nll", "nll_var_floor", "nll_n_floored"}``; ``nll_n_floored`` counts *pixels* whose
    variance was below the floor (each such pixel affects its three channels).
    """
    m, v, g = _validate(mean, var, gt, mask)
    return _nll(m, v, g, var_floor)


def _nll(m: np.ndarray, v: np.ndarray, g: np.ndarray, var_floor: float) -> dict:
    if not (var_floor > 0 and math.isfinite(var_floor)):
        raise B3dgsError("var_floor must be a positive finite number", fix="pass var_floor > 0, e.g. the default 1e-8")
    n_floored = int(np.count_nonzero(v < var_floor))
    vf = np.maximum(v, var_floor)[:, None]
    r2 = (g - m) ** 2
    nll = 0.5 * np.log(2.0 * math.pi * vf) + 0.5 * r2 / vf
    return {"nll": float(nll.mean()), "nll_var_floor": float(var_floor), "nll_n_floored": n_floored}


# ------------------------------------------------------------------------------------ Spearman
def spearman_rho(x: Any, y: Any, max_pixels: int | None = DEFAULT_MAX_SPEARMAN_PIXELS,
                 seed: int = 0) -> tuple[float, int]:
    """Spearman rank correlation of two 1-D samples (``scipy.stats.spearmanr``); returns ``(rho, n_used)``.

    Ties get average ranks. When ``max_pixels`` is set and the sample is larger, a subset of
    ``max_pixels`` indices is drawn without replacement with ``numpy.random.default_rng(seed)``
    (sorted, so the subset and the value are deterministic). rho is NaN for a constant input.
    """
    a = np.asarray(_to_numpy(x, "x"), dtype=np.float64).reshape(-1)
    b = np.asarray(_to_numpy(y, "y"), dtype=np.float64).reshape(-1)
    if a.shape != b.shape:
        raise B3dgsError(f"x and y must have the same length ({a.size} vs {b.size})",
                         fix="pass x and y flattened from the same pixels, so they have equal length")
    if a.size < 2:
        raise B3dgsError("need at least two samples",
                         fix="pass at least two pixels (e.g. a mask with two or more True pixels)")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise B3dgsError("x/y contain NaN or Inf", fix="pass finite values (drop NaN pixels with a mask first)")
    if max_pixels is not None and max_pixels < 2:
        raise B3dgsError("max_pixels must be >= 2", fix="pass max_pixels >= 2, or None to use every pixel")
    return _spearmanr(a, b, max_pixels, seed)


# -------------------------------------------------------------------------------------- driver
def evaluate_view(mean: Any, var: Any, gt: Any, mask: Any = None, *, fractions: Iterable[float] | None = None,
                  normalize: bool = False, levels: Iterable[float] | None = None, var_floor: float = DEFAULT_VAR_FLOOR,
                  max_spearman_pixels: int | None = DEFAULT_MAX_SPEARMAN_PIXELS, seed: int = 0) -> dict:
    """All uncertainty metrics of one view (the module docstring's), and their ``"curves"``; ``rmse``/``mae`` are the
    full-set errors (the raw curves' first points), ``normalize`` the AUSE convention (default raw)."""
    m, v, g = _validate(mean, var, gt, mask)
    a, s = per_pixel_errors(m, g)
    sp_r = sparsification(v, s, "rmse", fractions, normalize)
    sp_a = sparsification(v, a, "mae", fractions, normalize)
    t = np.sort(_standardized_abs_residuals(m, v, g))
    p = _check_levels(levels)
    obs = _coverage_from_t(t, _z(p))
    cov95 = float(_coverage_from_t(t, np.array([Z95]))[0])
    nll = _nll(m, v, g, var_floor)
    rho, n_rho = spearman_rho(v, a, max_pixels=max_spearman_pixels, seed=seed)
    return {
        "n_pixels": int(v.size),
        "mae": sp_a["full_error"],
        "rmse": sp_r["full_error"],
        "mean_var": float(v.mean()),
        "ause_rmse": sp_r["ause"],
        "ause_mae": sp_a["ause"],
        "ause_normalization": sp_r["ause_normalization"],
        "ece": float(np.mean(np.abs(obs - p))),
        "cov95": cov95,
        "cov95_err": abs(cov95 - 0.95),
        **nll,  # nll, nll_var_floor, nll_n_floored
        "spearman_rho": rho,
        "spearman_n": n_rho,
        "curves": {
            "fractions": sp_r["fractions"],
            "rmse": {"sparsification": sp_r["sparsification"], "oracle": sp_r["oracle"]},
            "mae": {"sparsification": sp_a["sparsification"], "oracle": sp_a["oracle"]},
            "calibration": {"levels": p, "observed": obs},
        },
    }


def _spearmanr(x: np.ndarray, y: np.ndarray, max_pixels: int | None, seed: int) -> tuple[float, int]:
    """scipy's Spearman rho (average ranks for ties), on a deterministic subset of at most ``max_pixels``;
    NaN when either side is constant."""
    import warnings

    from scipy.stats import spearmanr

    if max_pixels is not None and x.size > max_pixels:
        idx = np.sort(np.random.default_rng(seed).choice(x.size, size=int(max_pixels), replace=False))
        x, y = x[idx], y[idx]
    if x.size < 2 or np.all(x == x[0]) or np.all(y == y[0]):
        return float("nan"), int(x.size)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rho = spearmanr(x, y).statistic
    return float(np.clip(rho, -1.0, 1.0)), int(x.size)


def epistemic_view(epistemic: Any, mean: Any, gt: Any, var: Any = None, mask: Any = None, *,
                   fractions: Iterable[float] | None = None,
                   max_spearman_pixels: int | None = DEFAULT_MAX_SPEARMAN_PIXELS, seed: int = 0) -> dict:
    """The epistemic part ``u_p`` (H, W) of one view scored alone: ``epi_ause_rmse`` / ``epi_ause_mae``
    (AUSE of the order of ``u_p``, raw convention), ``epi_spearman_sq`` (scipy Spearman rho of ``u_p``
    with the squared error ``s_p``), ``mean_epistemic``, ``mse`` (mean ``s_p``) and, with ``var``,
    ``epi_fraction`` = mean ``u_p`` / mean ``var``."""
    m, u, g = _validate(mean, epistemic, gt, mask)
    a, s = per_pixel_errors(m, g)
    out = {"epi_ause_rmse": sparsification(u, s, "rmse", fractions)["ause"],
           "epi_ause_mae": sparsification(u, a, "mae", fractions)["ause"], "mean_epistemic": float(u.mean()),
           "mse": float(s.mean())}
    out["epi_spearman_sq"], out["epi_spearman_n"] = _spearmanr(u, s, max_spearman_pixels, seed)
    if var is not None:
        _, v, _ = _validate(mean, var, gt, mask)
        mv = float(v.mean())
        out["epi_fraction"] = float(u.mean()) / mv if mv > 0 else float("nan")
    return out


def epistemic_summary(per_view: Sequence[dict]) -> dict:
    """Over the views of :func:`epistemic_view` rows (each also holding ``mean_var``):
    ``epi_view_spearman`` -- scipy Spearman rho between the per-view mean ``u_p`` and the per-view MSE
    (NaN with fewer than 3 views or a constant side), ``epi_view_n`` and ``epistemic_fraction`` = the
    sum of the views' mean ``u_p`` over the sum of their mean predictive variance."""
    u = np.array([float(d["mean_epistemic"]) for d in per_view])
    e = np.array([float(d["mse"]) for d in per_view])
    v = np.array([float(d.get("mean_var", np.nan)) for d in per_view])
    rho = _spearmanr(u, e, None, 0)[0] if len(per_view) >= 3 else float("nan")
    frac = float(u.sum() / v.sum()) if np.all(np.isfinite(v)) and v.sum() > 0 else float("nan")
    return {"epi_view_spearman": rho, "epi_view_n": len(per_view), "epistemic_fraction": frac}


def _is_scalar(x: Any) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)


def _mean_curves(curves: Sequence[dict]) -> dict | None:
    """Element-wise mean of per-view curves, or None if the grids differ between views."""
    c0 = curves[0]
    f0, l0 = np.asarray(c0["fractions"]), np.asarray(c0["calibration"]["levels"])
    for c in curves[1:]:
        if (np.shape(c["fractions"]) != f0.shape or not np.allclose(c["fractions"], f0)
                or np.shape(c["calibration"]["levels"]) != l0.shape
                or not np.allclose(c["calibration"]["levels"], l0)):
            return None

    def avg(get):
        return np.mean([np.asarray(get(c), dtype=np.float64) for c in curves], axis=0)

    out = {"fractions": f0.astype(np.float64)}
    for k in ("rmse", "mae"):
        out[k] = {"sparsification": avg(lambda c: c[k]["sparsification"]),
                  "oracle": avg(lambda c: c[k]["oracle"])}
    out["calibration"] = {"levels": l0.astype(np.float64), "observed": avg(lambda c: c["calibration"]["observed"])}
    return out


def summarize(per_view: Sequence[dict], keep_curves: bool = False) -> dict:
    """Scene summary of :func:`evaluate_view` results: the mean over views of every numeric per-view scalar (a macro
    average; non-finite values skipped, ``n_finite`` counting the views of each mean that has fewer than all), the
    element-wise mean of the per-view curves (``mean_curves``; None when grids differ) and ``per_view`` (their
    ``"curves"`` only with ``keep_curves``)."""
    per_view = list(per_view)
    if not per_view:
        raise B3dgsError("summarize needs at least one per-view result",
                         fix="pass the list of per-view results (b3dgs.uq.metrics.evaluate_view's dicts), with at "
                             "least one view")
    norms = {d.get("ause_normalization") for d in per_view}
    if len(norms) > 1:
        raise B3dgsError(f"per-view results mix AUSE normalisations: {sorted(map(str, norms))}",
                         fix="compute every view with the same normalize= setting before summarising them")
    keys = [k for k, x in per_view[0].items() if _is_scalar(x) and all(_is_scalar(d.get(k)) for d in per_view)]
    out: dict[str, Any] = {"n_views": len(per_view)}
    n_finite: dict[str, int] = {}
    for k in keys:
        vals = np.array([float(d[k]) for d in per_view])
        fin = np.isfinite(vals)
        out[k] = float(vals[fin].mean()) if fin.any() else float("nan")
        if not fin.all():
            n_finite[k] = int(fin.sum())
    if "nll_n_floored" in out:
        out["nll_n_floored"] = int(sum(int(d["nll_n_floored"]) for d in per_view))  # a total, not a mean
    if "n_pixels" in out:
        out["n_pixels"] = int(sum(int(d["n_pixels"]) for d in per_view))
    if n_finite:
        out["n_finite"] = n_finite
    out["ause_normalization"] = norms.pop()
    out["nll_note"] = NLL_NOTE
    out["aggregation_note"] = AGGREGATION_NOTE
    curves = [d["curves"] for d in per_view if isinstance(d.get("curves"), dict)]
    out["mean_curves"] = _mean_curves(curves) if len(curves) == len(per_view) else None
    out["per_view"] = [{**{k: x for k, x in d.items() if k != "curves"},
                        **({"curves": d["curves"]} if keep_curves and "curves" in d else {})} for d in per_view]
    return out
