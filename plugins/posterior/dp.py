"""Truncated Dirichlet-process stick-breaking prior with CAVI and activity gates (paper Eq. 5)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Optional

import torch

from b3dgs.device import bernoulli
from b3dgs.plugin import PosteriorBlock
from b3dgs.posterior import dp as dpm


@dataclass
class DPBlock(PosteriorBlock):
    """q(v_k) = Beta(γ_k1, γ_k2) under a truncated stick-breaking prior v_k ~ Beta(1, α) (Eq. 5),
    updated by CAVI (Blei & Jordan 2006) every ``cavi_every`` steps after ``t_dp``.

    Usage counts: an EMA over steps of each Gaussian's total compositing weight Σ_p w_kp in the
    step's view, scaled by the number of training views (expected pixel responsibilities).
    Ordering for the stick-breaking: by decreasing expected usage (ties by index), re-sorted at
    every CAVI step, the usual choice that makes the truncated prior's size bias match the data.
    Gates: E[π_k] and an approximate activity posterior E[a_k] (see b3dgs.posterior.dp).
    Pruning: where E[π_k] < ``prune_pi`` / K (a fraction of the uniform share 1/K, so the rule
    scales with K) or E[a_k] < ``prune_activity``, every ``cavi_every`` steps after ``t_dp``.
    It augments, and does not replace, the strategy's densification.
    """

    alpha: float = 5.0
    cavi_every: int = 50
    t_dp: Optional[int] = None  # None: max_steps / 6
    ema: float = 0.99
    prune_pi: float = 0.05
    prune_activity: float = 0.05
    prior_active: float = 0.5
    gate_temperature: float = 1.0
    prune: bool = True
    needs_weights: ClassVar[bool] = True

    def check_sanity(self, max_steps: int = 0, **kw) -> None:
        if self.alpha <= 0:
            raise ValueError("posterior.dp.alpha must be > 0")
        if self.cavi_every < 1:
            raise ValueError("posterior.dp.cavi_every must be >= 1")
        if not 0 <= self.ema < 1:
            raise ValueError("posterior.dp.ema must be in [0, 1)")
        if not 0 < self.prior_active < 1:
            raise ValueError("posterior.dp.prior_active must be in (0, 1)")

    def initialize_state(self, *, splats, scene, info):
        n, dev = splats["means"].shape[0], splats["means"].device
        return {
            "usage": torch.zeros(n, dtype=torch.float64, device=dev),
            "g1": torch.ones(n, dtype=torch.float64, device=dev),
            "g2": torch.full((n,), float(self.alpha), dtype=torch.float64, device=dev),
            "e_pi": torch.full((n,), 1.0 / max(n, 1), dtype=torch.float64, device=dev),
            "e_a": torch.ones(n, dtype=torch.float64, device=dev),
            "n_views": torch.tensor(float(len(scene.train)) if scene is not None else 1.0, device=dev),
        }

    @torch.no_grad()
    def step_post_backward(self, *, splats, optimizers, state, step, info):
        ws = info["per_gaussian"].get("weight_sum")
        if ws is not None:
            state["usage"].mul_(self.ema).add_((1 - self.ema) * ws[0].double() * self.train_views(state, info))
        if step < self.stage_start(self.t_dp, info, 6) or step % self.cavi_every != 0:
            return
        self.cavi(state)
        if self.prune:
            k = state["usage"].numel()
            mask = (state["e_pi"] < dpm.prune_threshold(k, self.prune_pi)) | (state["e_a"] < self.prune_activity)
            state["last_pruned"] = mask.sum()
            info["ops"].prune(mask, reason="dp")

    @torch.no_grad()
    def cavi(self, state) -> None:
        counts = state["usage"]
        perm, inv = dpm.stick_order(counts)
        g1, g2 = dpm.cavi_stick_update(counts[perm], self.alpha)
        elog = dpm.expected_log_pi(g1, g2)
        e_pi = dpm.expected_pi(g1, g2)
        prior_logit = float(torch.logit(torch.tensor(self.prior_active)))
        tau = dpm.prune_threshold(counts.numel(), self.prune_pi)
        e_a = dpm.activity_posterior(elog, counts[perm], prior_logit, self.gate_temperature, threshold=tau)
        state["g1"], state["g2"] = g1[inv], g2[inv]
        state["e_pi"], state["e_a"] = e_pi[inv], e_a[inv]

    @torch.no_grad()
    def sample(self, *, splats, state, n, generator, params, info):
        """Activity draws a_k ~ Bernoulli(E[a_k]); inactive Gaussians render with zero opacity."""
        out = dict(params)
        a = bernoulli(state["e_a"].float().expand(n, -1), generator)
        base = out["opacities"] if out["opacities"].dim() == 2 else out["opacities"].unsqueeze(0).expand(n, -1)
        out["opacities"] = torch.where(a > 0, base, torch.full_like(base, -30.0))
        return out

    def export(self, *, splats=None, state):
        return {"dp_e_pi": state["e_pi"].float(), "dp_e_a": state["e_a"].float()}

    def summary(self, *, state):
        return {"alpha": self.alpha, "expected_active": float(state["e_a"].sum()),
                "usage_total": float(state["usage"].sum())}
