"""Farthest: greedy farthest-camera-centre sampling from the current training set (NeRF Director)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from b3dgs.acquisition import AcquisitionPolicy, Selection, camera_centres


@dataclass
class FarthestPolicy(AcquisitionPolicy):
    """Pick the candidate whose centre is farthest from every training (and already picked) centre, then
    repeat. Scores: each candidate's distance to the nearest training centre before any pick."""

    selects_batch: ClassVar[bool] = True  # its select builds the batch (only batch=topk applies)

    def select(self, ctx, candidates, budget):
        cand = camera_centres(candidates)
        train = camera_centres(ctx.train)
        d = np.linalg.norm(cand[:, None] - train[None], axis=-1).min(axis=1) if len(train) else np.full(len(cand), np.inf)
        scores = d.tolist()
        picks: list[int] = []
        for _ in range(min(int(budget), len(cand))):
            masked = np.where(np.isin(np.arange(len(cand)), picks), -np.inf, d)
            i = int(np.argmax(masked))  # first of equal distances: deterministic
            picks.append(i)
            d = np.minimum(d, np.linalg.norm(cand - cand[i], axis=-1))
        return Selection(picks, scores)
