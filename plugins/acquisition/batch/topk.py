"""topk (default): the policy's own selection, the paper's protocol (top-k of the scores; uniform, farthest and
fisher keep their own batch rule)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from b3dgs.acquisition import BatchSelector


@dataclass
class TopK(BatchSelector):
    """``policy.select``: for a score-based policy the ``budget`` highest scores (ties by position), bit for
    bit what the study did before batch options existed. No parameter, no cost beyond scoring."""

    own_batch_ok: ClassVar[bool] = True

    def select(self, policy, ctx, candidates, budget):
        return policy.select(ctx, candidates, budget)
