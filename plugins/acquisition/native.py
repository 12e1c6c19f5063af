"""Native: mean u_p (paper Eq. 4) from NIW posterior samples, epistemic part only."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from b3dgs.acquisition import AcquisitionPolicy
from b3dgs_plugins.uq.native import NativeUQ


@dataclass
class NativePolicy(AcquisitionPolicy):
    """Score = mean over pixels of the spread u_p of S posterior re-renders (batched ``chunk`` per call).
    The aleatoric σ̂² is left out: it is the same for every view, so it cannot change the ranking.

    ``count_scale`` = 0.1 by default: the posterior is drawn with N̂ ← 0.1·N̂. In ``bench/uq_count_scale.py``
    (seed 0, both shared scenes) that setting gave the epistemic part its best pixel-level ranking (Spearman ρ
    with the squared error 0.51 / 0.42 against 0.41 / 0.41 at the paper's c = 1) without moving the
    posterior-mean render; ``null`` scores with the model's own setting (the paper's)."""

    family: str = "niw"
    samples: int = 16
    chunk: int = 8
    count_scale: Optional[float] = 0.1

    @torch.no_grad()
    def score(self, ctx, candidates):
        regime = getattr(self, "_regime", None) or NativeUQ(samples=self.samples, chunk=self.chunk,
                                                             count_scale=self.count_scale)
        self._regime = regime
        return torch.stack([ctx.predict(regime, c, salt=i).epistemic.double().mean() for i, c in enumerate(candidates)]).cpu()
