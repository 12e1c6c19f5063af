"""Proxy: mean position-jitter uncertainty (``plugins/uq/proxy.py``) of the phase-1 model."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from b3dgs.acquisition import AcquisitionPolicy
from b3dgs_plugins.uq.proxy import ProxyUQ


@dataclass
class ProxyPolicy(AcquisitionPolicy):
    """Score = mean over pixels of the proxy u_p (S centre-jittered re-renders)."""

    family: str = "niw"
    samples: int = 16
    chunk: int = 8
    jitter: float = 0.002

    @torch.no_grad()
    def score(self, ctx, candidates):
        regime = getattr(self, "_regime", None) or ProxyUQ(samples=self.samples, chunk=self.chunk, jitter=self.jitter)
        self._regime = regime
        return torch.stack([ctx.predict(regime, c, salt=i).epistemic.double().mean() for i, c in enumerate(candidates)]).cpu()
