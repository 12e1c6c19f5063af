"""Deep ensemble of independently seeded runs (Lakshminarayanan et al. 2017)."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from b3dgs.errors import B3dgsError
from b3dgs.uq.regime import Predictive, UQRegime


@dataclass
class EnsembleUQ(UQRegime):
    """Prediction: the pixelwise mean of the M member renders. Uncertainty: the pixelwise standard
    deviation across members (population form, 1/M), averaged over RGB, as in the paper's appendix
    table; var is its square. No aleatoric term."""

    min_members: int = 2

    def fit(self, models, scene):
        super().fit(models, scene)
        if len(self.models) < self.min_members:
            raise B3dgsError(f"uq=ensemble needs >= {self.min_members} run dirs (got {len(self.models)})",
                             fix="pass run=[dir1,dir2,dir3]: runs of one scene trained with different seeds")

    @torch.no_grad()
    def predict(self, camera, generator=None):
        imgs = torch.stack([m.render_eval(camera).double() for m in self.models])  # (M, H, W, 3)
        mean = imgs.mean(0)
        std = imgs.std(0, unbiased=False).mean(-1)
        u = std.square()
        return Predictive(mean=mean.float(), var=u.float(), epistemic=u.float(), aleatoric=0.0)
