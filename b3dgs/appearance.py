"""Approximate opacity / colour posterior refinements (Table 1 "approximate" rows, Alg. 1 stage C).

Opacity: a Gaussian (Laplace / empirical-Fisher) posterior on the opacity logit is pushed through
the sigmoid and moment-matched to a Beta. Colour: local linearised Gaussian posterior for a
colour entering pixel p linearly with compositing weight w_kp under I_p ~ N(C_p, sigma^2 I_3).
All float64 internally; outputs follow the input dtype.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Tuple, Union

import numpy as np
import torch

from b3dgs.errors import B3dgsError
from b3dgs.numerics import float_dtype as _dtype, guard, guard_fill, scalar_or_vector as _scalar_or_vec, zero_invalid
from b3dgs.numerics import vector as _vec

__all__ = ["SH_C0", "OPACITY_MAX_LOGIT", "BETA_MAX_CONCENTRATION", "BETA_MIN_CONCENTRATION", "opacity_to_logit",
           "logit_normal_moments", "opacity_beta_moment_match", "opacity_fisher_var", "color_posterior_var",
           "color_posterior_mean", "rgb_var_to_dc_var", "dc_var_to_rgb_var"]

Num = Union[float, torch.Tensor]
_F64 = torch.float64

#: 0th-order real SH constant; 3DGS maps a DC coefficient f to colour c = SH_C0 * f + 0.5.
SH_C0 = 0.28209479177387814
#: Logits are clamped to [-30, 30] (opacity within ~1e-13 of 0/1); guard ``opacity.logit_clamp``.
OPACITY_MAX_LOGIT = 30.0
#: Beta concentration a + b is capped (zero logit variance = point mass); guard ``opacity_beta.concentration_cap``.
BETA_MAX_CONCENTRATION = 1e12
#: Lower cap on a + b (only reachable by rounding when var ~ mean(1-mean)); guard ``opacity_beta.concentration_floor``.
BETA_MIN_CONCENTRATION = 1e-6
_GH_NODES = 48
_SIGMA2_FLOOR = 1e-12


@lru_cache(maxsize=4)
def _gauss_hermite(n: int) -> Tuple[np.ndarray, np.ndarray]:
    t, w = np.polynomial.hermite.hermgauss(n)
    return t, w / math.sqrt(math.pi)


# ----------------------------------------------------------------------------- opacity
def opacity_to_logit(opacity: torch.Tensor) -> torch.Tensor:
    """Logit of opacities in [0, 1], clamped to +-OPACITY_MAX_LOGIT (guard ``opacity.logit_clamp``)."""
    o = _vec("opacity", opacity)
    if not bool(((o >= 0) & (o <= 1)).all()):
        raise B3dgsError("opacity must lie in [0, 1]",
                         fix="pass opacities as probabilities in [0, 1] (torch.sigmoid of the stored logits)")
    lg = torch.logit(o)
    return _clamp_logit(lg).to(_dtype(opacity))


def _clamp_logit(lg: torch.Tensor) -> torch.Tensor:
    if bool(torch.isnan(lg).any()):
        raise B3dgsError("logit contains NaN",
                         fix="the Gaussians' opacity logits hold NaN (training diverged): lower the learning rates "
                             "(e.g. model.lr_opacities)")
    out = ~(lg.abs() <= OPACITY_MAX_LOGIT)
    if guard("opacity.logit_clamp", out):
        lg = lg.clamp(-OPACITY_MAX_LOGIT, OPACITY_MAX_LOGIT)
    return lg


def logit_normal_moments(logit: torch.Tensor, logit_var: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Mean and variance of sigmoid(x), x ~ N(logit, logit_var), by Gauss-Hermite quadrature.

    Computed on the side m <= 0 (sigmoid(x) = 1 - sigmoid(-x)) so values near 1 keep relative
    precision; the variance is formed from centred terms. Returns float64 (K,), (K,).
    """
    return _ln_moments(_clamp_logit(_vec("logit", logit)), logit_var)


def _ln_moments(m: torch.Tensor, logit_var: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    v = _vec("logit_var", logit_var)
    if v.shape != m.shape:
        raise B3dgsError(f"logit_var shape {tuple(v.shape)} != logit shape {tuple(m.shape)}",
                         fix="pass logit_var with one entry per Gaussian, the same shape (K,) as the logits")
    v = zero_invalid("logit_normal_moments.invalid_logit_var", v)
    t, w = _gauss_hermite(_GH_NODES)
    t = torch.as_tensor(t, dtype=_F64, device=m.device)
    w = torch.as_tensor(w, dtype=_F64, device=m.device)
    mneg = -m.abs()
    x = mneg[:, None] + torch.sqrt(2.0 * v)[:, None] * t[None, :]
    s = torch.sigmoid(x)
    mean_lo = (s * w).sum(-1)
    var = (((s - mean_lo[:, None]) ** 2) * w).sum(-1)
    mean = torch.where(m > 0, 1.0 - mean_lo, mean_lo)
    return mean, var


def opacity_beta_moment_match(logit: torch.Tensor, logit_var: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Beta(a, b) matching mean/variance of sigmoid(x), x ~ N(logit, logit_var) (approximate, Table 1).

    Moments by Gauss-Hermite quadrature (``logit_normal_moments``; more accurate than the delta
    method or the probit approximation for large variances); a + b = mean(1-mean)/var - 1 capped
    to [BETA_MIN_CONCENTRATION, BETA_MAX_CONCENTRATION] (guarded). Logits +-inf (opacity 0/1) are
    clamped to +-OPACITY_MAX_LOGIT (guarded). Returns (a, b) (K,) in the logit's dtype.
    """
    dtype = _dtype(logit)
    m = _clamp_logit(_vec("logit", logit))
    mean, var = _ln_moments(m, logit_var)
    # mirror to the small side: Beta(a, b) for sigmoid(x) <-> Beta(b, a) for sigmoid(-x)
    mu = torch.where(m > 0, 1.0 - mean, mean)
    mu = guard_fill("opacity_beta.mean_floor", ~(mu > 0), mu, 1e-300)
    pq = mu * (1.0 - mu)
    conc = torch.where(var > 0, pq / var.clamp_min(1e-300) - 1.0, torch.full_like(var, float("inf")))
    conc = guard_fill("opacity_beta.concentration_cap", ~(conc <= BETA_MAX_CONCENTRATION), conc, BETA_MAX_CONCENTRATION)
    conc = guard_fill("opacity_beta.concentration_floor", conc < BETA_MIN_CONCENTRATION, conc, BETA_MIN_CONCENTRATION)
    a_small, b_big = mu * conc, (1.0 - mu) * conc
    a = torch.where(m > 0, b_big, a_small)
    b = torch.where(m > 0, a_small, b_big)
    return a.to(dtype), b.to(dtype)


def opacity_fisher_var(grad_sq_ema: torch.Tensor, prior_precision: Num, data_scale: Num = 1.0) -> torch.Tensor:
    """Laplace variance of the opacity logit: 1 / (data_scale * E[g^2] + prior_precision).

    ``grad_sq_ema`` (K,) is the EMA of squared per-step loss gradients w.r.t. the logit (empirical
    Fisher); ``data_scale`` converts it to the Fisher of the full likelihood (e.g. number of
    pixel observations per step / sigma^2 normalisation). At opacity 0/1 the gradient vanishes
    and the variance reverts to the prior 1/prior_precision.
    """
    g = _vec("grad_sq_ema", grad_sq_ema)
    K = g.numel()
    pp = _scalar_or_vec("prior_precision", prior_precision, K, g.device)
    ds = _scalar_or_vec("data_scale", data_scale, K, g.device)
    if not bool((torch.isfinite(pp) & (pp > 0)).all()):
        raise B3dgsError("prior_precision must be finite and > 0",
                         fix="pass prior_precision > 0 and finite (posterior.opacity.prior_precision)")
    if not bool((torch.isfinite(ds) & (ds >= 0)).all()):
        raise B3dgsError("data_scale must be finite and >= 0",
                         fix="pass data_scale >= 0 and finite (1.0 uses the Fisher as summed)")
    g = zero_invalid("opacity_fisher_var.invalid_grad_sq_ema", g)
    prec = ds * g + pp
    return (1.0 / prec).to(_dtype(grad_sq_ema))


# ----------------------------------------------------------------------------- colour
def _sigma2(sigma2: Num, K: int, device, where: str) -> torch.Tensor:
    s2 = _scalar_or_vec("sigma2", sigma2, K, device)
    if bool(torch.isnan(s2).any()):
        raise B3dgsError("sigma2 contains NaN",
                         fix="pass a finite sigma2 (the NoiseBlock's E[sigma^2]); NaN means the noise posterior "
                             "diverged: check posterior.noise")
    s2 = guard_fill(f"{where}.sigma2_floor", ~(s2 >= _SIGMA2_FLOOR), s2, _SIGMA2_FLOOR)
    return s2


def _color_prior_precision(prior_precision: Num, K: int, device) -> torch.Tensor:
    """(K,) float64 colour prior precision, refused unless finite and > 0."""
    pp = _scalar_or_vec("prior_precision", prior_precision, K, device)
    if not bool((torch.isfinite(pp) & (pp > 0)).all()):
        raise B3dgsError("prior_precision must be finite and > 0",
                         fix="pass prior_precision > 0 and finite (posterior.color.prior_precision)")
    return pp


def color_posterior_var(
    weight_sq_sum: torch.Tensor, sigma2: Num, prior_precision: Num, space: str = "rgb"
) -> torch.Tensor:
    """Per-channel posterior variance of a Gaussian's colour (approximate, Table 1).

    Precision (RGB) = sum_p w_kp^2 / sigma^2 + prior_precision, for a colour entering pixel p
    linearly with compositing weight w_kp (exact for fixed geometry/opacity; "linearised" since
    the weights depend on the other parameters). The three channels share it (sigma^2 I_3).
    ``space="dc"``: variance of the SH DC coefficient f (c = SH_C0 f + 0.5): the likelihood
    precision becomes SH_C0^2 sum w^2 / sigma^2, and ``prior_precision`` is read in DC units.
    sigma2 is floored at 1e-12 (guarded).
    """
    ws = _vec("weight_sq_sum", weight_sq_sum)
    K = ws.numel()
    ws = zero_invalid("color_posterior_var.invalid_weight_sq_sum", ws)
    s2 = _sigma2(sigma2, K, ws.device, "color_posterior_var")
    pp = _color_prior_precision(prior_precision, K, ws.device)
    if space not in ("rgb", "dc"):
        raise B3dgsError(f"space must be 'rgb' or 'dc', got {space!r}", fix="pass space='rgb' or space='dc'")
    lik = ws / s2
    if space == "dc":
        lik = (SH_C0 * SH_C0) * lik
    return (1.0 / (lik + pp)).to(_dtype(weight_sq_sum))


def color_posterior_mean(color: torch.Tensor, weighted_residual_sum: torch.Tensor, weight_sq_sum: torch.Tensor,
                         sigma2: Num, prior_mean: Num, prior_precision: Num) -> torch.Tensor:
    """Local linearised posterior mean of RGB colour (one Newton step = exact for linear C_p).

    color, weighted_residual_sum = sum_p w_kp (I_p - C_p): (K,3); weight_sq_sum: (K,).
    mean = c + (sum_p w r / sigma^2 - tau0 (c - eta0)) / (sum_p w^2 / sigma^2 + tau0).
    """
    if not isinstance(color, torch.Tensor) or color.ndim != 2:
        raise B3dgsError(f"color: expected (K, C), got {getattr(color, 'shape', type(color).__name__)}",
                         fix="pass color as a float tensor of shape (K, C): one colour per Gaussian")
    K = color.shape[0]
    c = color.to(_F64)
    r = weighted_residual_sum
    if not isinstance(r, torch.Tensor) or r.shape != color.shape:
        raise B3dgsError(f"weighted_residual_sum: expected shape {tuple(color.shape)}, got {getattr(r, 'shape', None)}",
                         fix="pass weighted_residual_sum of the same shape (K, C) as color")
    r = r.to(_F64)
    ws = _vec("weight_sq_sum", weight_sq_sum)
    if ws.numel() != K:
        raise B3dgsError(f"weight_sq_sum: expected ({K},), got {tuple(ws.shape)}",
                         fix=f"pass weight_sq_sum with one entry per Gaussian, shape ({K},)")
    ws = zero_invalid("color_posterior_mean.invalid_weight_sq_sum", ws)
    s2 = _sigma2(sigma2, K, c.device, "color_posterior_mean")
    pp = _color_prior_precision(prior_precision, K, c.device)
    eta = torch.as_tensor(prior_mean, dtype=_F64, device=c.device)
    prec = ws / s2 + pp
    grad = r / s2[:, None] - pp[:, None] * (c - eta)
    return (c + grad / prec[:, None]).to(_dtype(color))


def rgb_var_to_dc_var(var_rgb: torch.Tensor) -> torch.Tensor:
    """Var[f_dc] = Var[c] / SH_C0^2 (c = SH_C0 f_dc + 0.5)."""
    return var_rgb / (SH_C0 * SH_C0)


def dc_var_to_rgb_var(var_dc: torch.Tensor) -> torch.Tensor:
    """Var[c] = SH_C0^2 Var[f_dc]."""
    return var_dc * (SH_C0 * SH_C0)
