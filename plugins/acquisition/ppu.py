"""PPU: the residual head of ``plugins/uq/ppu.py``, fit on the frozen phase-1 model's training views."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch

from b3dgs.acquisition import AcquisitionPolicy
from b3dgs_plugins.uq.ppu import PPUHead


@dataclass
class PPUPolicy(AcquisitionPolicy):
    """Score = mean predicted variance of the head (fit at the scoring resolution on the training views)."""

    no_conditioning: ClassVar[str] = ("the head is fit to training residuals, which a view acquired without its "
                                      "image does not provide")
    steps: int = 300
    lr: float = 5.0e-3
    width: int = 16

    @torch.no_grad()
    def score(self, ctx, candidates):
        regime = getattr(self, "_regime", None) or PPUHead(steps=self.steps, lr=self.lr, width=self.width, seed=ctx.seed)
        self._regime = regime
        with torch.enable_grad():
            ctx.fit_regime(regime)
        return torch.stack([ctx.predict(regime, c).var.double().mean() for c in candidates]).cpu()
