"""Posterior-importance pruning: the paper's primary posterior-aware compression score."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from b3dgs.compression import DPPruningScore


@dataclass
class PosteriorImportancePruning(DPPruningScore):
    """Score E[π_k] · E[a_k] · E[o_k] · n̂_k (paper appendix, 'dp_posterior_importance'): DP weight, expected
    activity, opacity (σ of the point estimate: the base model has no opacity posterior) and the usage count
    normalised by its maximum, all from the DP fit of
    :class:`b3dgs.compression.DPPruningScore` (shared with ``dp_mass`` through the cache)."""

    def score(self, *, splats, optimizers, state, step, info):
        fit = self.fit(info)
        usage = fit["usage"]
        n_hat = usage / usage.max().clamp_min(1e-300)
        opacity = torch.sigmoid(splats["opacities"].detach().double().reshape(-1))
        return fit["e_pi"] * fit["e_a"] * opacity * n_hat
