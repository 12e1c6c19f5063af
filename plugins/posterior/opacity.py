"""Approximate opacity posterior around the optimizer (paper Table 1: "approximate refinement")."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Optional

import torch

from b3dgs import appearance as app
from b3dgs.device import randn
from b3dgs.errors import check_field
from b3dgs.numerics import on_device_path
from b3dgs.plugin import PosteriorBlock


@dataclass
class OpacityBlock(PosteriorBlock):
    """q(o_k) ≈ Beta(a_k, b_k), moment-matched to sigmoid(ℓ) with ℓ ~ N(ℓ̂_k, v_k): ℓ̂ is the optimizer's
    logit and v_k a Laplace variance from the empirical Fisher (EMA over steps of the squared
    per-view NLL gradient w.r.t. the logit, times the number of training views) plus a prior precision.

    Approximations: a diagonal Laplace/Fisher curvature, the EMA over minibatches, and the moment
    match. The block does not move the point estimate; it supplies the variance that the DPMM
    predictive path samples. Active after ``t_post`` (default max_steps / 2).
    """

    per_gaussian_state: ClassVar[tuple[str, ...]] = ("fisher",)

    needs_residuals: ClassVar[bool] = True  # reads info["sq_err_sum"]

    prior_precision: float = 1.0
    ema: float = 0.99
    t_post: Optional[int] = None

    def validate(self, max_steps: int = 0, **kw) -> None:
        check_field(self, "posterior.opacity.prior_precision", not self.prior_precision <= 0, "> 0")
        check_field(self, "posterior.opacity.ema", 0 <= self.ema < 1, "in [0, 1)")

    def initialize_state(self, *, splats, scene, info):
        n, dev = splats["means"].shape[0], splats["means"].device
        return {"fisher": torch.zeros(n, dtype=torch.float64, device=dev),
                "n_views": torch.tensor(float(len(scene.train)) if scene is not None else 1.0, device=dev)}

    @torch.no_grad()
    def step_post_backward(self, *, splats, optimizers, state, step, info):
        if step < self.stage_start(self.t_post, info, 2):
            return
        g = splats["opacities"].grad
        if g is None:
            return
        # The training loss is a pixel mean (L1 + D-SSIM); rescale its gradient to the per-view Gaussian
        # NLL, Σ_p ||r_p||² / (2σ²), whose gradient is M / (2σ²) times that of the pixel-mean L2 loss
        # (M values per view). This is an approximation: the L1/SSIM gradient stands in for the L2 one.
        s2 = info.get("sigma2")
        if on_device_path(g):  # the same scale as a 0-d tensor: no host read per step
            if s2 is None:
                s2 = info["sq_err_sum"].double() / max(int(info["num_values"]), 1)
            scale = float(info["num_values"]) / (2.0 * torch.as_tensor(s2, dtype=torch.float64, device=g.device)
                                                 .clamp_min(1e-8))
        else:
            if s2 is None:
                s2 = float(info["sq_err_sum"]) / max(int(info["num_values"]), 1)
            scale = float(info["num_values"]) / (2.0 * max(float(s2), 1e-8))
        state["fisher"].mul_(self.ema).add_((1 - self.ema) * (g.double() * scale).square() * self.train_views(state, info))

    def logit_var(self, state):
        return app.opacity_fisher_var(state["fisher"], self.prior_precision)

    @torch.no_grad()
    def sample(self, *, splats, state, n, generator, params, info):
        """Logit draws ℓ ~ N(ℓ̂, v) (the Gaussian the Beta is matched to); inactive (-30) stay off."""
        out = dict(params)
        base = out["opacities"] if out["opacities"].dim() == 2 else out["opacities"].unsqueeze(0).expand(n, -1)
        std = self.logit_var(state).sqrt().to(base.dtype)
        eps = randn(base.shape, generator=generator, dtype=base.dtype, device=base.device)
        out["opacities"] = torch.where(base > -29.0, base + std * eps, base)
        return out

    @torch.no_grad()
    def export(self, *, splats, state):
        """Variance of the opacity under the moment-matched Beta(a, b)."""
        a, b = app.opacity_beta_moment_match(splats["opacities"].detach().double(), self.logit_var(state))
        return {"opacity_var": (a * b / ((a + b) ** 2 * (a + b + 1))).float()}

    def summary(self, *, state):
        v = self.logit_var(state)
        return {"median_logit_var": float(v.median()) if v.numel() else 0.0}
