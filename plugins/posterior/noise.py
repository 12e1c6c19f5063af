"""Inverse-gamma posterior on the pixel noise variance σ² (paper Table 1, "closed-form IG step")."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Optional

import torch

from b3dgs.plugin import PosteriorBlock
from b3dgs.posterior import noise as ig


@dataclass
class NoiseBlock(PosteriorBlock):
    """q(σ²) = IG(a_n, b_n), updated in closed form from each step's residual statistics
    (sum of squared residuals over the minibatch's pixels and channels, with known mean = render).

    Old evidence is discounted by ``decay`` per step so the posterior tracks the residual as
    training sharpens the model (a forgetting conjugate update; the effective sample size is
    bounded by ``n / (1 - decay)``). E[σ²] is the aleatoric term of native uncertainty.
    Updates start at ``t_dp`` (default: max_steps / 6, with the DP block).
    """

    needs_residuals: ClassVar[bool] = True  # reads info["sq_err_sum"]

    a0: float = 2.0
    b0: float = 1e-3
    decay: float = 0.99
    t_noise: Optional[int] = None

    def check_sanity(self, max_steps: int = 0, **kw) -> None:
        if self.a0 <= 0 or self.b0 <= 0:
            raise ValueError("posterior.noise.a0 and b0 must be > 0")
        if not 0 <= self.decay < 1:
            raise ValueError("posterior.noise.decay must be in [0, 1)")

    def initialize_state(self, *, splats, scene, info):
        dev = splats["means"].device
        return {"a": torch.tensor(self.a0, dtype=torch.float64, device=dev),
                "b": torch.tensor(self.b0, dtype=torch.float64, device=dev)}

    @torch.no_grad()
    def step_post_backward(self, *, splats, optimizers, state, step, info):
        if step < self.stage_start(self.t_noise, info, 6):
            return
        a, b = ig.ig_update_ema(state["a"], state["b"], info["sq_err_sum"].double(), float(info["num_values"]),
                                self.decay, a0=self.a0, b0=self.b0)
        state["a"], state["b"] = a, b
        info["sigma2"] = float(ig.ig_mean(a, b))

    def aleatoric_variance(self, *, state):
        return float(ig.ig_mean(state["a"], state["b"]))

    def summary(self, *, state):
        return {"sigma2_mean": self.aleatoric_variance(state=state), "a": float(state["a"]), "b": float(state["b"])}
