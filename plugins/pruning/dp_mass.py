"""DP-mass pruning: keep Gaussians with large expected stick-breaking weight E[π_k]."""
from __future__ import annotations

from dataclasses import dataclass

from b3dgs.compression import PruningScore, cached, usage_counts


@dataclass
class DPMassPruning(PruningScore):
    """Score E[π_k] of the DP posterior (paper Eq. 5) fitted by CAVI to the model's usage counts on the fixed
    structure (:func:`b3dgs.compression.usage_counts`). The DP settings mirror ``conf/posterior/dp.yaml``."""

    rounds: int = 2
    alpha: float = 5.0
    prior_active: float = 0.5
    prune_pi: float = 0.05
    gate_temperature: float = 1.0

    def validate(self, **kwargs) -> None:
        super().validate(**kwargs)
        self.dp_block().validate()

    def dp_block(self):
        from b3dgs_plugins.posterior.dp import DPBlock

        return DPBlock(alpha=self.alpha, prior_active=self.prior_active, prune_pi=self.prune_pi,
                       gate_temperature=self.gate_temperature, prune=False)

    def fit(self, info) -> dict:
        """{usage, g1, g2, e_pi, e_a} of the DP posterior at the current model state (cached per state)."""
        def fit():
            state = {"usage": usage_counts(info).clone()}
            self.dp_block().cavi(state)
            return state

        return cached(info, f"dp_fit_{self.alpha}_{self.prior_active}_{self.prune_pi}_{self.gate_temperature}", fit)

    def score(self, *, splats, optimizers, state, step, info):
        return self.fit(info)["e_pi"]
