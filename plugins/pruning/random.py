"""Random retention: the floor any ranking must beat."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from b3dgs.compression import PruningScore


@dataclass
class RandomPruning(PruningScore):
    """Uniform random scores from the study's seeded generator (``info["generator"]``)."""

    rounds: int = 1

    def score(self, *, splats, optimizers, state, step, info):
        n = splats["means"].shape[0]
        return torch.rand(n, generator=info["generator"], dtype=torch.float64).to(splats["means"].device)
