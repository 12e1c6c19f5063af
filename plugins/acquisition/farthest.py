"""Farthest: greedy farthest-camera-centre sampling from the current training set (NeRF Director)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from b3dgs.acquisition import AcquisitionPolicy, Selection, camera_centres, greedy_spread


@dataclass
class FarthestPolicy(AcquisitionPolicy):
    """Pick the candidate whose centre is farthest from every training (and already picked) centre, then
    repeat. Scores: each candidate's distance to the nearest training centre before any pick."""

    selects_batch: ClassVar[bool] = True  # its select builds the batch (only batch=topk applies)

    def select(self, ctx, candidates, budget):
        picks, d = greedy_spread(camera_centres(candidates), camera_centres(ctx.train), budget, lambda d: d)
        return Selection(picks, d.tolist())
