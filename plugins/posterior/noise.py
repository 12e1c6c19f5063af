"""Inverse-gamma posterior on the pixel noise variance σ² (paper Table 1, "closed-form IG step"; Algorithm 1
"noise update"): the block (:class:`NoiseBlock`) and its pure batched math (tested in tests/test_posterior_math.py).

Observation model I_p ~ N(C_p, sigma^2 I_3) with the render C_p treated as known: for n scalar
residual entries with sum of squares SS the conjugate update of IG(a, b) is
a_n = a + n/2, b_n = b + SS/2. Everything is float64; inputs may be floats or tensors of any
(broadcastable) shape.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Optional, Tuple, Union

import torch

from b3dgs.errors import B3dgsError, check_field, field_default
from b3dgs.numerics import guard_fill, guard_where, on_device_path
from b3dgs.plugin import PosteriorBlock


Num = Union[float, int, torch.Tensor]
_F64 = torch.float64

#: Floor on a - 1 (resp. a - 2) in the IG mean (resp. variance); a <= 1 means an infinite mean.
IG_MEAN_DENOM_EPS = 1e-6
#: Floor on the Gamma(a, 1) draw used by ig_sample (sigma^2 = b / g).
IG_GAMMA_FLOOR = 1e-300


def _t(x: Num) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(_F64)
    return torch.as_tensor(x, dtype=_F64)  # python floats straight to float64 (1e300 stays finite)


def _check_ab(a: torch.Tensor, b: torch.Tensor) -> None:
    if on_device_path(a):  # the training step's own state (no host read per step); the CPU path checks
        return
    if not bool((torch.isfinite(a) & (a > 0)).all()) or not bool((torch.isfinite(b) & (b > 0)).all()):
        raise B3dgsError("inverse-gamma parameters a, b must be finite and > 0",
                         fix="pass inverse-gamma parameters a > 0 and b > 0, finite (posterior.noise.a0 and b0, "
                             f"defaults {field_default(NoiseBlock, 'a0')} and {field_default(NoiseBlock, 'b0')})")
    try:
        torch.broadcast_shapes(a.shape, b.shape)
    except RuntimeError as e:
        raise B3dgsError(f"a {tuple(a.shape)} and b {tuple(b.shape)} do not broadcast",
                         fix="pass a and b of broadcastable shapes, e.g. both scalars or both (K,)") from e


def _check_evidence(ss: torch.Tensor, n: torch.Tensor, where: str) -> torch.Tensor:
    if on_device_path(ss):  # the step's residual, finite whenever the loss is (checked by the core)
        return guard_where(f"{where}.negative_ss", ss < 0, torch.zeros_like(ss), ss)
    if not bool((torch.isfinite(n) & (n >= 0)).all()):
        raise B3dgsError(f"{where}: n_obs must be finite and >= 0",
                         fix=f"pass n_obs finite and >= 0 to {where} (a count of observed pixels)")
    if not bool(torch.isfinite(ss).all()):
        raise B3dgsError(f"{where}: sum_sq_residual must be finite",
                         fix=f"pass a finite sum_sq_residual to {where}; a NaN residual means the render diverged: "
                             "lower the learning rates (e.g. model.lr_means)")
    return guard_fill(f"{where}.negative_ss", ss < 0, ss, 0.0)  # tiny negative values from cancellation upstream


def ig_update(a0: Num, b0: Num, sum_sq_residual: Num, n_obs: Num) -> Tuple[torch.Tensor, torch.Tensor]:
    """Conjugate IG update with known mean: a_n = a0 + n/2, b_n = b0 + SS/2 (closed-form, Table 1)."""
    a, b = _t(a0), _t(b0)
    _check_ab(a, b)
    n = _t(n_obs)
    ss = _check_evidence(_t(sum_sq_residual), n, "ig_update")
    return a + 0.5 * n, b + 0.5 * ss


def ig_update_ema(a: Num, b: Num, sum_sq_residual: Num, n_obs: Num, decay: float, a0: Optional[Num] = None,
                  b0: Optional[Num] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    """Online IG update with exponential forgetting (power-prior discounting of old evidence).

    With a prior (a0, b0): a' = a0 + decay*(a - a0) + n/2, b' = b0 + decay*(b - b0) + SS/2, i.e.
    the accumulated evidence is discounted by ``decay`` each call while the prior is kept, so
    the effective memory is ~1/(1-decay) calls and the posterior tracks the (shrinking) training
    residual. At a stationary residual the fixed point is a0 + n/(2(1-decay)),
    b0 + SS/(2(1-decay)), whose mean -> SS/n. Without a prior, the whole state is discounted
    (a' = decay*a + n/2); then a can drift towards 0 if no evidence arrives.
    decay=1 is the plain conjugate update.
    """
    if not (0.0 <= float(decay) <= 1.0):
        raise B3dgsError(f"decay must be in [0, 1], got {decay}",
                         fix=f"pass decay in [0, 1] (posterior.noise.decay, default {field_default(NoiseBlock, 'decay')}; "
                             "1 is the plain conjugate update)")
    a_, b_ = _t(a), _t(b)
    _check_ab(a_, b_)
    n = _t(n_obs)
    ss = _check_evidence(_t(sum_sq_residual), n, "ig_update_ema")
    if (a0 is None) != (b0 is None):
        raise B3dgsError("pass both a0 and b0 (or neither)",
                         fix="pass both a0 and b0 (the prior the EMA decays towards), or neither for a plain decayed "
                             "update")
    if a0 is None:
        return decay * a_ + 0.5 * n, decay * b_ + 0.5 * ss
    pa, pb = _t(a0), _t(b0)
    _check_ab(pa, pb)
    return pa + decay * (a_ - pa) + 0.5 * n, pb + decay * (b_ - pb) + 0.5 * ss


def ig_mean(a: Num, b: Num, eps: float = IG_MEAN_DENOM_EPS) -> torch.Tensor:
    """E[sigma^2] = b / (a - 1); a - 1 floored at ``eps`` (guard ``ig_mean.a_le_1``)."""
    a_, b_ = _t(a), _t(b)
    _check_ab(a_, b_)
    den = a_ - 1.0
    den = guard_where("ig_mean.a_le_1", den < eps, torch.full_like(den, eps), den)
    return b_ / den


def ig_mode(a: Num, b: Num) -> torch.Tensor:
    """Mode of IG(a, b): b / (a + 1)."""
    a_, b_ = _t(a), _t(b)
    _check_ab(a_, b_)
    return b_ / (a_ + 1.0)


def ig_var(a: Num, b: Num, eps: float = IG_MEAN_DENOM_EPS) -> torch.Tensor:
    """Var[sigma^2] = b^2 / ((a-1)^2 (a-2)); a - 2 floored at ``eps`` (guard ``ig_var.a_le_2``)."""
    a_, b_ = _t(a), _t(b)
    _check_ab(a_, b_)
    d1 = (a_ - 1.0).clamp_min(eps)
    d2 = a_ - 2.0
    d2 = guard_fill("ig_var.a_le_2", d2 < eps, d2, eps)
    return b_ * b_ / (d1 * d1 * d2)


def ig_sample(a: Num, b: Num, n_samples: int, generator: Optional[torch.Generator] = None) -> torch.Tensor:
    """Draw sigma^2 ~ IG(a, b) as b / Gamma(a, 1); returns (n_samples, *broadcast(a, b).shape)."""
    if not isinstance(n_samples, int) or n_samples < 1:
        raise B3dgsError(f"n_samples must be a positive int, got {n_samples!r}",
                         fix="pass n_samples as an int >= 1 (e.g. uq.native.samples)")
    a_, b_ = _t(a), _t(b)
    _check_ab(a_, b_)
    shape = torch.broadcast_shapes(a_.shape, b_.shape)
    conc = a_.expand(shape).unsqueeze(0).expand(n_samples, *shape).contiguous()
    g = torch._standard_gamma(conc, generator=generator)
    g = guard_fill("ig_sample.gamma_floor", ~(g >= IG_GAMMA_FLOOR), g, IG_GAMMA_FLOOR)
    out = b_.expand(shape) / g
    out = guard_fill("ig_sample.overflow", ~torch.isfinite(out), out, torch.finfo(_F64).max)
    return out


@dataclass
class NoiseBlock(PosteriorBlock):
    """q(σ²) = IG(a_n, b_n), updated in closed form from each step's residual statistics
    (sum of squared residuals over the minibatch's pixels and channels, with known mean = render).

    Old evidence is discounted by ``decay`` per step so the posterior tracks the residual as
    training sharpens the model (a forgetting conjugate update; the effective sample size is
    bounded by ``n / (1 - decay)``). E[σ²] is the aleatoric term of native uncertainty.
    Updates start at ``t_dp`` (default: max_steps / 6, with the DP block).
    """

    per_gaussian_state: ClassVar[tuple[str, ...]] = ()

    needs_residuals: ClassVar[bool] = True  # reads info["sq_err_sum"]

    a0: float = 2.0
    b0: float = 1e-3
    decay: float = 0.99
    t_noise: Optional[int] = None

    def validate(self, max_steps: int = 0, **kw) -> None:
        if self.a0 <= 0 or self.b0 <= 0:
            raise B3dgsError("posterior.noise.a0 and b0 must be > 0",
                             fix="pass posterior.noise.a0 > 0 and posterior.noise.b0 > 0, e.g. the defaults "
                                 f"{field_default(self, 'a0')} and {field_default(self, 'b0')}")
        check_field(self, "posterior.noise.decay", 0 <= self.decay < 1, "in [0, 1)")

    def initialize_state(self, *, splats, scene, info):
        dev = splats["means"].device
        return {"a": torch.tensor(self.a0, dtype=torch.float64, device=dev),
                "b": torch.tensor(self.b0, dtype=torch.float64, device=dev)}

    @torch.no_grad()
    def step_post_backward(self, *, splats, optimizers, state, step, info):
        if step < self.stage_start(self.t_noise, info, 6):
            return
        a, b = ig_update_ema(state["a"], state["b"], info["sq_err_sum"].double(), float(info["num_values"]),
                                self.decay, a0=self.a0, b0=self.b0)
        state["a"], state["b"] = a, b
        s2 = ig_mean(a, b)
        info["sigma2"] = s2 if on_device_path(s2) else float(s2)  # a 0-d tensor on the device: no host read

    def aleatoric_variance(self, *, state):
        return float(ig_mean(state["a"], state["b"]))

    def summary(self, *, state):
        return {"sigma2_mean": self.aleatoric_variance(state=state), "a": float(state["a"]), "b": float(state["b"])}
