"""Post-hoc calibration of a predictive variance on held-out calibration views (never test views).

Three pieces, each a pure function of arrays (the regimes in ``plugins/uq`` feed them renders):

* :func:`training_mse` -- the plug-in aleatoric level σ̂² of *any* model: the mean squared residual
  of its renders of the training views, per colour value (the ``uq=constant`` regime).
* :func:`fit_scale_and_level` -- the Gaussian maximum-likelihood fit of at most two scalars,
  ``var_p = s·u_p + a`` (``s`` scales the epistemic part u_p, ``a`` is the aleatoric level), to
  calibration residuals (``uq=native_calibrated``). s > 0, so the pixel ranking of ``var`` is that of
  ``u_p`` whatever is fitted.
* :func:`conformal_scale` -- the split-conformal multiplier of a fixed normalised score
  (``uq=native_conformal``).
"""
from __future__ import annotations

import math
from typing import Any, Iterable, Optional, Sequence

import numpy as np

from b3dgs.errors import B3dgsError

__all__ = ["calibration_views", "conformal_scale", "fit_scale_and_level", "gaussian_nll_scalars", "training_mse"]


def calibration_views(scene: Any, regime: str) -> list:
    """The scene's calibration cameras (``scene.calib``, made by ``data.calib_every``); refuses, in one
    line naming the fix, a scene that has none."""
    calib = list(getattr(scene, "calib", None) or [])
    if not calib:
        raise B3dgsError(f"uq={regime} fits on calibration views and this run has none (it was trained on all its "
                         "training views)", "train the run with data.calib_every=16 (every 16th training view is "
                         "held out for calibration, never a test view), then evaluate that run")
    return calib


def training_mse(module: Any, cameras: Sequence[Any]) -> float:
    """Mean over the ``cameras``' pixels and RGB values of (render - image)², rendered with the model's
    evaluation render (``render_eval``, clamped to [0, 1]); accumulated in float64."""
    import torch

    if not cameras:
        raise B3dgsError("training_mse needs at least one camera with an image",
                         fix="pass the scene's training cameras with their images (scene.train), at least one")
    total, count = 0.0, 0
    with torch.no_grad():
        for cam in cameras:
            if cam.image is None:
                raise B3dgsError(f"camera {cam.name!r} has no image",
                                 fix="pass cameras loaded with their images (the scene's train or calib views), not "
                                     "image-less poses")
            img = module.render_eval(cam).detach().double().cpu()
            total += float((img - cam.image.double()).square().sum())
            count += img.numel()
    return total / count


def gaussian_nll_scalars(u: np.ndarray, r2: np.ndarray, a: float, s: float, channels: int = 3) -> float:
    """Mean NLL per value of residuals with per-pixel variance ``s·u + a`` (``r2``: per-pixel sum of
    the squared residuals over ``channels`` values)."""
    v = s * np.asarray(u, np.float64) + a
    return float(np.mean(0.5 * channels * np.log(2 * math.pi * v) + 0.5 * np.asarray(r2, np.float64) / v) / channels)


def fit_scale_and_level(u: Iterable[float], r2: Iterable[float], channels: int = 3, fit_scale: bool = True,
                        bounds: tuple[float, float] = (1e-8, 1e8)) -> dict:
    """Maximum-likelihood (a, s) of ``var_p = s·u_p + a`` for Gaussian residuals.

    ``u`` (N,): the epistemic part per pixel (>= 0); ``r2`` (N,): the sum over the pixel's ``channels``
    colour values of the squared residual. Minimises

        NLL(a, s) = Σ_p [ channels/2 · log(2π v_p) + r2_p / (2 v_p) ],   v_p = s·u_p + a,

    over (log a, log s) with L-BFGS-B (analytic gradient, several starting points for s), in units where
    the calibration MSE and the mean u are 1; both scalars stay inside ``bounds`` (relative to those
    units; a bound that binds is reported). With ``fit_scale=False`` or u ≡ 0 only a is fitted, in closed
    form: a = mean(r2) / channels (the held-out residual variance).

    Returns ``{"a", "s", "nll", "nll_uncalibrated" (s = 1, a = calibration MSE), "mse", "mean_u",
    "n_pixels", "s_identifiable", "at_bound", "converged"}``.
    """
    from scipy.optimize import minimize

    u = np.asarray(list(u) if not isinstance(u, np.ndarray) else u, np.float64).reshape(-1)
    r2 = np.asarray(list(r2) if not isinstance(r2, np.ndarray) else r2, np.float64).reshape(-1)
    if u.shape != r2.shape or u.size == 0:
        raise B3dgsError(f"u and r2 must be non-empty and equally long ({u.size} vs {r2.size})",
                         fix="pass one variance u per squared residual r2, from the same calibration pixels, "
                             "non-empty")
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(r2))) or np.any(u < 0) or np.any(r2 < 0):
        raise B3dgsError("u and r2 must be finite and >= 0",
                         fix="pass finite, non-negative variances u and squared residuals r2 (drop NaN pixels first)")
    mse = float(r2.mean() / channels)
    if not mse > 0:
        raise B3dgsError("the calibration residuals are all zero: no aleatoric level can be fitted",
                         fix="calibrate on held-out views the model does not reproduce exactly: train with "
                             "data.calib_every=16 and check the calibration images are not copies of training views")
    mean_u = float(u.mean())
    out = {"mse": mse, "mean_u": mean_u, "n_pixels": int(u.size), "channels": int(channels)}
    if not fit_scale or not mean_u > 0:
        out.update(a=mse, s=1.0, s_identifiable=bool(mean_u > 0), at_bound=False, converged=True)
        out["nll"] = gaussian_nll_scalars(u, r2, mse, 1.0, channels)
        out["nll_uncalibrated"] = out["nll"]
        return out
    un = u / mean_u  # units: v / mse, u / mean_u  ->  v_n = exp(x0) + exp(x1) * un
    rn = r2 / mse
    lo, hi = math.log(bounds[0]), math.log(bounds[1])

    def f(x):
        ea, es = math.exp(x[0]), math.exp(x[1])
        v = ea + es * un
        nll = float(np.mean(0.5 * channels * np.log(v) + 0.5 * rn / v))
        dv = 0.5 * channels / v - 0.5 * rn / v ** 2  # d nll / d v, per pixel
        return nll, np.array([float(np.mean(dv)) * ea, float(np.mean(dv * un)) * es])

    best = None
    for x1 in (-6.0, -2.0, 0.0, 2.0):  # the likelihood need not be convex in (a, s): several starts
        res = minimize(f, np.array([math.log(0.9), x1]), jac=True, method="L-BFGS-B", bounds=[(lo, hi), (lo, hi)])
        if best is None or res.fun < best.fun:
            best = res
    a = math.exp(best.x[0]) * mse
    s = math.exp(best.x[1]) * mse / mean_u
    out.update(a=a, s=s, s_identifiable=True, converged=bool(best.success),
               at_bound=bool(np.any(np.isclose(best.x, lo)) or np.any(np.isclose(best.x, hi))),
               nll=gaussian_nll_scalars(u, r2, a, s, channels),
               nll_uncalibrated=gaussian_nll_scalars(u, r2, mse, 1.0, channels))
    return out


def conformal_scale(scores: Iterable[float], level: float = 0.95, z: Optional[float] = None) -> dict:
    """Split-conformal quantile of normalised scores t_i = |r_i| / σ_i on calibration data.

    q is the ⌈(n + 1)·level⌉-th smallest of the n scores (q = inf when that rank exceeds n). If the n
    calibration scores and a test score are exchangeable, P(t_test ≤ q) ≥ level (and < level + 1/(n + 1)
    when there are no ties). Returns ``{"q", "rank", "n", "level", "multiplier"}`` where ``multiplier``
    = (q / z)² rescales σ² so that the Gaussian interval ±z·σ at ``level`` becomes the conformal ±q·σ
    (z defaults to the Gaussian quantile of ``level``).
    """
    from statistics import NormalDist

    t = np.sort(np.asarray(list(scores) if not isinstance(scores, np.ndarray) else scores, np.float64).reshape(-1))
    if t.size == 0 or not np.all(t >= 0) or np.any(np.isnan(t)):
        raise B3dgsError("conformal scores must be a non-empty array of values >= 0",
                         fix="pass non-negative normalised scores |r| / sigma from at least one calibration pixel, "
                             "without NaN")
    if not 0 < level < 1:
        raise B3dgsError(f"level must be in (0, 1), got {level}",
                         fix="pass level strictly between 0 and 1, e.g. the default 0.95")
    n = int(t.size)
    rank = int(math.ceil((n + 1) * level))
    q = float(t[rank - 1]) if rank <= n else float("inf")
    z = NormalDist().inv_cdf(0.5 * (1 + level)) if z is None else float(z)
    return {"q": q, "rank": rank, "n": n, "level": float(level), "z": z, "multiplier": (q / z) ** 2}
