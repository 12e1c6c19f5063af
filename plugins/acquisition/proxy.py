"""Proxy: mean position-jitter uncertainty (``plugins/uq/proxy.py``) of the phase-1 model."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch

from b3dgs.acquisition import AcquisitionPolicy, epistemic_scores
from b3dgs_plugins.uq.proxy import ProxyUQ


@dataclass
class ProxyPolicy(AcquisitionPolicy):
    """Score = mean over pixels of the proxy u_p (S centre-jittered re-renders)."""

    no_conditioning: ClassVar[str] = ("the jitter has one fixed scale for every Gaussian and no posterior: a view "
                                      "acquired without its image changes nothing the score depends on")

    family: str = "niw"
    samples: int = 16
    chunk: int = 8
    jitter: float = 0.002

    @torch.no_grad()
    def score(self, ctx, candidates):
        return self.score_at(ctx, candidates, range(len(candidates)))

    @torch.no_grad()
    def score_at(self, ctx, candidates, positions):
        regime = getattr(self, "_regime", None) or ProxyUQ(samples=self.samples, chunk=self.chunk, jitter=self.jitter)
        self._regime = regime
        return epistemic_scores(ctx, regime, candidates, positions)
