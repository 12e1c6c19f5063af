"""Approximate colour posterior: local linearised Gaussian (paper Table 1: "approximate refinement")."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Optional

import torch

from b3dgs.device import randn
from b3dgs.errors import B3dgsError, field_default
from b3dgs.numerics import on_device_path
from b3dgs.plugin import PosteriorBlock
from b3dgs_plugins.posterior import appearance as app
from b3dgs.render.projection import SH_C0


@dataclass
class ColorBlock(PosteriorBlock):
    """q(c_k) = N(ĉ_k, v_k I₃): a colour enters pixel p linearly with weight w_kp, so under the
    Gaussian pixel likelihood the local posterior precision is Σ_p w_kp² / σ² + τ₀ (prior precision).
    Σ_p w_kp² is an EMA over steps of the renderer's squared compositing weights, times the number
    of training views; σ² is E[σ²] of the NoiseBlock when present (``info["sigma2"]``), else the
    block's own plug-in residual MSE. Approximations: linearisation around the optimizer's colour,
    view-independent (DC) colour only, diagonal precision. Active after ``t_post``.
    """

    per_gaussian_state: ClassVar[tuple[str, ...]] = ("wsq",)

    prior_precision: float = 1.0
    ema: float = 0.99
    t_post: Optional[int] = None
    needs_weights: ClassVar[bool] = True
    needs_residuals: ClassVar[bool] = True  # reads info["sq_err_sum"]

    def validate(self, max_steps: int = 0, **kw) -> None:
        if self.prior_precision <= 0:
            raise B3dgsError("posterior.color.prior_precision must be > 0",
                             fix="pass posterior.color.prior_precision > 0, "
                                 f"e.g. the default {field_default(self, 'prior_precision')}")

    def initialize_state(self, *, splats, scene, info):
        n, dev = splats["means"].shape[0], splats["means"].device
        return {"wsq": torch.zeros(n, dtype=torch.float64, device=dev),
                "sigma2": torch.tensor(1e-2, dtype=torch.float64, device=dev),
                "n_views": torch.tensor(float(len(scene.train)) if scene is not None else 1.0, device=dev)}

    @torch.no_grad()
    def step_post_backward(self, *, splats, optimizers, state, step, info):
        s2 = info.get("sigma2")
        if s2 is None:
            ss = info["sq_err_sum"]
            # a 0-d tensor on the device path (no host read per step); the CPU path keeps its Python float
            s2 = (ss.double() if on_device_path(ss) else float(ss)) / max(int(info["num_values"]), 1)
        state["sigma2"] = self.ema * state["sigma2"] + (1 - self.ema) * s2
        if step < self.stage_start(self.t_post, info, 2):
            return
        wsq = info["per_gaussian"].get("weight_sq_sum")
        if wsq is not None:
            state["wsq"].mul_(self.ema).add_((1 - self.ema) * wsq[0].double() * self.train_views(state, info))

    def rgb_var(self, state):
        return app.color_posterior_var(state["wsq"], state["sigma2"], self.prior_precision)

    @torch.no_grad()
    def sample(self, *, splats, state, n, generator, params, info):
        """RGB draws c ~ N(ĉ, v I), applied to the DC SH coefficient (RGB = SH_C0 · sh0 + 0.5)."""
        out = dict(params)
        sh0 = out["sh0"] if out["sh0"].dim() == 4 else out["sh0"].unsqueeze(0).expand(n, -1, -1, -1)
        std = (self.rgb_var(state).sqrt() / SH_C0).to(sh0.dtype)
        eps = randn(sh0.shape, generator=generator, dtype=sh0.dtype, device=sh0.device)
        out["sh0"] = sh0 + std.view(1, -1, 1, 1) * eps
        return out

    def export(self, *, splats=None, state):
        return {"color_var": self.rgb_var(state).float()}

    def summary(self, *, state):
        v = self.rgb_var(state)
        return {"median_rgb_var": float(v.median()) if v.numel() else 0.0, "sigma2": float(state["sigma2"])}
