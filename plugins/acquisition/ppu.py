"""PPU: the residual head of ``plugins/uq/ppu.py``, fit on the frozen phase-1 model's training views."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar

import torch

from b3dgs.acquisition import RegimePolicy


@dataclass
class PPUPolicy(RegimePolicy):
    """Score = mean predicted variance of the ``regime``, the residual head of conf/uq/ppu.yaml
    (:class:`b3dgs_plugins.uq.ppu.PPUHead`), fit at the scoring resolution on the training views with the
    scoring context's seed."""

    no_conditioning: ClassVar[str] = ("the head is fit to training residuals, which a view acquired without its "
                                      "image does not provide")

    @torch.no_grad()
    def score(self, ctx, candidates):
        head = self.uq()
        if head.seed != ctx.seed:  # the study's scene-seed, known only when scoring
            head = self.regime = replace(head, seed=ctx.seed)
        with torch.enable_grad():
            ctx.fit_regime(head)
        return torch.stack([ctx.predict(head, c).var.double().mean() for c in candidates]).cpu()

    def score_at(self, ctx, candidates, positions):
        return self.score(ctx, [candidates[i] for i in positions])
