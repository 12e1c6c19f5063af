"""Ensemble: mean cross-member RGB variance of M independently seeded phase-1 models."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch

from b3dgs.acquisition import AcquisitionPolicy
from b3dgs.errors import B3dgsError, field_default


@dataclass
class EnsemblePolicy(AcquisitionPolicy):
    """Score = mean over pixels and RGB of the variance across the M members' renders (population form).
    The members are the family's phase-1 models of seeds s, ..., s+M-1; the first one continues."""

    members: int = 3
    no_conditioning: ClassVar[str] = ("the members disagree less where a view is acquired only once they are "
                                      "retrained on its image; without the image nothing they render changes")

    def validate(self, **kwargs):
        super().validate(**kwargs)
        if int(self.members) < 2:
            raise B3dgsError(f"acquisition ensemble needs members >= 2, got {self.members}",
                             fix=f"pass acquisition.members >= 2, e.g. the default {field_default(self, 'members')}")

    @torch.no_grad()
    def score(self, ctx, candidates):
        out = []
        for cam in candidates:
            imgs = torch.stack([ctx.render(cam, member=i).rgb.clamp(0, 1).double() for i in range(ctx.num_members)])
            out.append(imgs.var(0, unbiased=False).mean())
        return torch.stack(out).cpu()
