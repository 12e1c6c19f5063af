"""Truncated Dirichlet-process stick-breaking prior with CAVI and activity gates (paper Eq. 5): the block
:class:`DPBlock`; its math (stick-breaking, CAVI, activity gate) lives in :mod:`b3dgs.dp`."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Optional

import torch

from b3dgs.device import bernoulli
from b3dgs.dp import check_dp_prior, dp_cavi, prune_threshold
from b3dgs.errors import B3dgsError, check_field
from b3dgs.plugin import PosteriorBlock


@dataclass
class DPBlock(PosteriorBlock):
    """q(v_k) = Beta(γ_k1, γ_k2) under a truncated stick-breaking prior v_k ~ Beta(1, α) (Eq. 5),
    updated by CAVI (Blei & Jordan 2006) every ``cavi_every`` steps after ``t_dp``.

    Usage counts: an EMA over steps of each Gaussian's total compositing weight Σ_p w_kp in the
    step's view, scaled by the number of training views (expected pixel responsibilities). The EMA is a
    recurrence over every step's view: usage at a CAVI step depends on each earlier step's Σ_p w (weight
    (1 - ema)·ema^age), so the paper's block reads the renderer's pair sums on every step (the default,
    ``pair_sums_every`` = 1), although CAVI itself runs only every ``cavi_every`` steps. ``pair_sums_every`` = k > 1
    updates the EMA on every k-th step only, with decay ema^k (the same memory in steps, from 1/k of the views):
    the renderer computes the sums on 1/k of the steps (the cost DPMM adds on gsplat), and results change
    (``bench/dp_cadence.py`` measures by how much).
    Ordering for the stick-breaking: by decreasing expected usage (ties by index), re-sorted at
    every CAVI step, the usual choice that makes the truncated prior's size bias match the data.
    Gates: E[π_k] and an approximate activity posterior E[a_k] (the math: :mod:`b3dgs.dp`).
    Pruning: where E[π_k] < ``prune_pi`` / K (a fraction of the uniform share 1/K, so the rule
    scales with K) or E[a_k] < ``prune_activity``, every ``cavi_every`` steps after ``t_dp``.
    It augments, and does not replace, the strategy's densification.
    """

    per_gaussian_state: ClassVar[tuple[str, ...]] = ("usage", "g1", "g2", "e_pi", "e_a")

    alpha: float = 5.0
    cavi_every: int = 50
    t_dp: Optional[int] = None  # None: max_steps / 6
    ema: float = 0.99  # usage EMA; its window (~1/(1-ema) steps) should cover an epoch of views
    prune_pi: float = 0.05  # prune where E[pi_k] < prune_pi / K
    prune_activity: float = 0.05  # prune where E[a_k] < prune_activity
    prior_active: float = 0.5
    gate_temperature: float = 1.0
    prune: bool = True
    #: read the pair sums (Σ_p w) on every k-th step only (step % k == 0), the usage EMA then decaying by ema^k per
    #: read; 1: every step (the paper, and the runs archived; a run's protocol leaves 1 out: upgrade.RUN_DEFAULTS),
    #: e.g. ``posterior.dp.pair_sums_every=4`` (see ``bench/dp_cadence.py``)
    pair_sums_every: int = 1
    needs_weights: ClassVar[bool] = True

    def validate(self, max_steps: int = 0, **kw) -> None:
        check_dp_prior(self)
        check_field(self, "posterior.dp.cavi_every", not self.cavi_every < 1, ">= 1", "as an integer >= 1")
        if not isinstance(self.pair_sums_every, int) or self.pair_sums_every < 1:
            raise B3dgsError(f"posterior.dp.pair_sums_every={self.pair_sums_every} must be an integer >= 1",
                             fix="pass posterior.dp.pair_sums_every as an integer >= 1 (1, the default: every step)")
        check_field(self, "posterior.dp.ema", 0 <= self.ema < 1, "in [0, 1)")

    def initialize_state(self, *, splats, scene, info):
        n, dev = splats["means"].shape[0], splats["means"].device
        return {"usage": torch.zeros(n, dtype=torch.float64, device=dev),
                "g1": torch.ones(n, dtype=torch.float64, device=dev),
                "g2": torch.full((n,), float(self.alpha), dtype=torch.float64, device=dev),
                "e_pi": torch.full((n,), 1.0 / max(n, 1), dtype=torch.float64, device=dev),
                "e_a": torch.ones(n, dtype=torch.float64, device=dev),
                "n_views": torch.tensor(float(len(scene.train)) if scene is not None else 1.0, device=dev)}

    @torch.no_grad()
    def step_post_backward(self, *, splats, optimizers, state, step, info):
        ws = info["per_gaussian"].get("weight_sum")
        if ws is not None and self.reads_pair_sums(step, info):
            w = ws[0].double()
            rs = info.get("resolution_scale", 1.0)
            if rs != 1.0:  # a downsampled step (schedule=dash): the weights in full-resolution pixels
                w = w / (rs * rs)
            d = self.strided_decay(self.ema, self.pair_sums_every)
            state["usage"].mul_(d).add_((1 - d) * w * self.train_views(state, info))
        if "cavi" not in self.periodic(step, info):
            return
        self.cavi(state)
        if self.prune:
            k = state["usage"].numel()
            mask = (state["e_pi"] < prune_threshold(k, self.prune_pi)) | (state["e_a"] < self.prune_activity)
            state["last_pruned"] = mask.sum()
            info["ops"].prune(mask, reason="dp")

    def reads_pair_sums(self, step: int, info: dict) -> bool:
        """Every step by default (the usage EMA is a per-step recurrence); every ``pair_sums_every``-th if set."""
        return step % self.pair_sums_every == 0

    def periodic(self, step: int, info: dict) -> tuple[str, ...]:
        """``cavi`` (and activity pruning) every ``cavi_every`` steps from ``t_dp``."""
        if step >= self.stage_start(self.t_dp, info, 6) and step % self.cavi_every == 0:
            return ("cavi",)
        return ()

    @torch.no_grad()
    def cavi(self, state) -> None:
        dp_cavi(state, self.alpha, self.prior_active, self.prune_pi, self.gate_temperature)

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
