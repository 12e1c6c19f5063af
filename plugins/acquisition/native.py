"""Native: mean u_p (paper Eq. 4) from NIW posterior samples, epistemic part only."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from b3dgs.acquisition import AcquisitionPolicy
from plugins.uq.native import NativeUQ


@dataclass
class NativePolicy(AcquisitionPolicy):
    """Score = mean over pixels of the spread u_p of S posterior re-renders (batched ``chunk`` per call).
    The aleatoric σ̂² is left out: it is the same for every view, so it cannot change the ranking."""

    family: str = "niw"
    samples: int = 16
    chunk: int = 8

    @torch.no_grad()
    def score(self, ctx, candidates):
        regime = getattr(self, "_regime", None) or NativeUQ(samples=self.samples, chunk=self.chunk)
        self._regime = regime
        return torch.stack([ctx.predict(regime, c, salt=i).epistemic.double().mean() for i, c in enumerate(candidates)]).cpu()
