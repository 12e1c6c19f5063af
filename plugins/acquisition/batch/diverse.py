"""diverse: policy-agnostic greedy with diminishing returns near the training and already picked cameras."""
from __future__ import annotations

import time
from dataclasses import dataclass

from b3dgs.acquisition import BatchSelector, Selection, camera_centres, check_radius, diverse_picks


@dataclass
class Diverse(BatchSelector):
    """Score every candidate once, then pick greedily by s_i · (1 − exp(−d_i² / (2 (radius·h)²))): d_i is the
    distance of its centre to the nearest training or picked camera centre, h the median nearest-neighbour
    spacing of the pool's centres (:func:`b3dgs.acquisition.diverse_picks`). One parameter, ``radius``
    (default 1: a candidate one typical spacing from a chosen camera keeps 39 % of its score, two spacings
    86 %). Cost: the policy's scoring plus an O(K²) distance table; no extra render."""

    radius: float = 1.0

    def validate(self, **kwargs):
        check_radius(self.radius, "diverse")

    def select(self, policy, ctx, candidates, budget):
        scores = [float(v) for v in policy.score(ctx, candidates).detach().double().cpu()]
        t0 = time.perf_counter()
        picks, h = diverse_picks(scores, camera_centres(candidates), camera_centres(ctx.train), budget, self.radius)
        return Selection(picks, scores, {"batch": "diverse", "radius": float(self.radius), "spacing": h,
                                         "batch_time_s": time.perf_counter() - t0})
