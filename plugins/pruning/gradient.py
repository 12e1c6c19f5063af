"""Gradient pruning: keep Gaussians whose position moves the training loss most."""
from __future__ import annotations

from dataclasses import dataclass

from b3dgs.compression import PruningScore, position_grad_norm


@dataclass
class GradientPruning(PruningScore):
    """Score Σ_v ‖∂MSE_v/∂μ_k‖ over the training views (paper appendix, compression 'gradient'; one round)."""

    rounds: int = 1

    def score(self, *, splats, optimizers, state, step, info):
        return position_grad_norm(info)
