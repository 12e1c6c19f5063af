"""Approximate colour posterior: local linearised Gaussian (paper Table 1: "approximate refinement")."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Optional

import torch

from b3dgs import appearance as app
from b3dgs.device import randn
from b3dgs.errors import B3dgsError, check_field
from b3dgs.numerics import on_device_path
from b3dgs.plugin import PosteriorBlock
from b3dgs.render.projection import SH_C0


@dataclass
class ColorBlock(PosteriorBlock):
    """q(c_k) = N(ĉ_k, v_k I₃): a colour enters pixel p linearly with weight w_kp, so under the
    Gaussian pixel likelihood the local posterior precision is Σ_p w_kp² / σ² + τ₀ (prior precision).
    Σ_p w_kp² is an EMA over steps of the renderer's squared compositing weights, times the number
    of training views; σ² is E[σ²] of the NoiseBlock when present (``info["sigma2"]``), else the
    block's own plug-in residual MSE. Approximations: linearisation around the optimizer's colour,
    view-independent (DC) colour only, diagonal precision. Active after ``t_post``.

    The Σ w² EMA starts at ``t_post`` (before it the block reads only the residual for σ²), so the block asks
    for the renderer's pair sums from ``t_post`` on: the same values, and no sums in the first half of a run
    where no other block reads them. From ``t_post`` the EMA is a per-step recurrence like the DP usage, read
    on every step unless ``pair_sums_every`` = k > 1 (every k-th step, decay ema^k; results change).
    """

    per_gaussian_state: ClassVar[tuple[str, ...]] = ("wsq",)

    prior_precision: float = 1.0
    ema: float = 0.99
    t_post: Optional[int] = None
    #: from ``t_post``, read Σ_p w² on every k-th step only (step % k == 0), the EMA then decaying by ema^k per read;
    #: 1: every step (the runs archived; left out of a run's protocol at 1), e.g. ``posterior.color.pair_sums_every=4``
    pair_sums_every: int = 1
    needs_weights: ClassVar[bool] = True
    needs_residuals: ClassVar[bool] = True  # reads info["sq_err_sum"]

    def validate(self, max_steps: int = 0, **kw) -> None:
        check_field(self, "posterior.color.prior_precision", not self.prior_precision <= 0, "> 0")
        if not isinstance(self.pair_sums_every, int) or self.pair_sums_every < 1:
            raise B3dgsError(f"posterior.color.pair_sums_every={self.pair_sums_every} must be an integer >= 1",
                             fix="pass posterior.color.pair_sums_every as an integer >= 1 (1, the default: every step)")

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
        if wsq is not None and self.reads_pair_sums(step, info):
            d = self.strided_decay(self.ema, self.pair_sums_every)
            state["wsq"].mul_(d).add_((1 - d) * wsq[0].double() * self.train_views(state, info))

    def reads_pair_sums(self, step: int, info: dict) -> bool:
        """From ``t_post`` (the Σ w² EMA's start), on every ``pair_sums_every``-th step (default: every step)."""
        return step >= self.stage_start(self.t_post, info, 2) and step % self.pair_sums_every == 0

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
