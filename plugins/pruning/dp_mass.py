"""DP-mass pruning: keep Gaussians with large expected stick-breaking weight E[π_k]."""
from __future__ import annotations

from dataclasses import dataclass

from b3dgs.compression import DPPruningScore


@dataclass
class DPMassPruning(DPPruningScore):
    """Score E[π_k] of the DP posterior (paper Eq. 5) fitted by CAVI to the model's usage counts on the fixed
    structure (:class:`b3dgs.compression.DPPruningScore`)."""

    def score(self, *, splats, optimizers, state, step, info):
        return self.fit(info)["e_pi"]
