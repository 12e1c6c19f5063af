"""Opacity pruning: keep the most opaque Gaussians (the paper's compression baseline)."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from b3dgs.compression import PruningScore


@dataclass
class OpacityPruning(PruningScore):
    """Score σ(o_k) of the current model (paper appendix, compression 'opacity'; two prune-refine rounds)."""

    rounds: int = 2

    def score(self, *, splats, optimizers, state, step, info):
        return torch.sigmoid(splats["opacities"].detach().double().reshape(-1))
