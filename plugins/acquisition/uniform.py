"""Uniform: deterministic even spacing over the remaining candidates (sorted by name)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from b3dgs.acquisition import AcquisitionPolicy, Selection
from b3dgs.data.scene import select_evenly


@dataclass
class UniformPolicy(AcquisitionPolicy):
    """``budget`` candidates evenly spaced over the name-sorted pool (no scores, no model needed)."""

    selects_batch: ClassVar[bool] = True  # its select builds the batch (only batch=topk applies)

    def select(self, ctx, candidates, budget):
        order = sorted(range(len(candidates)), key=lambda i: candidates[i].name)
        return Selection([order[i] for i in select_evenly(len(order), int(budget))], None)
