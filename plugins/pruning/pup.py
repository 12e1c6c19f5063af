"""PUP 3D-GS (Hanson et al. 2025): the dedicated-compression comparator."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from b3dgs.compression import PruningScore, spatial_fisher
from b3dgs.errors import B3dgsError, field_default


@dataclass
class PUPPruning(PruningScore):
    """Sensitivity log|F_k| of each Gaussian's 6×6 Fisher block over its mean and log-scale, summed over the
    training views' pixels and channels (a second-order approximation of the training reconstruction error);
    two prune-refine rounds, as PUP's pipeline. ``pixel_stride``: see :mod:`b3dgs.fisher`; the log-determinant
    sums the logs of the block's eigenvalues, clamped at ``eig_floor`` (a Gaussian no training pixel sees has a
    zero block and ranks last; clamps are counted in ``state["clamped"]``)."""

    rounds: int = 2
    pixel_stride: int = 4  # per-pixel gradients from s*s passes per view and channel (exact when s >= scoring side)
    per_channel: bool = True
    eig_floor: float = 1.0e-30

    def validate(self, **kwargs) -> None:
        super().validate(**kwargs)
        if int(self.pixel_stride) < 1:
            raise B3dgsError(f"pruning pup.pixel_stride must be >= 1, got {self.pixel_stride}",
                             fix="pass pruning.pixel_stride as an integer >= 1, "
                                 f"e.g. the default {field_default(self, 'pixel_stride')}")
        if not self.eig_floor > 0:
            raise B3dgsError(f"pruning pup.eig_floor must be > 0, got {self.eig_floor}",
                             fix=f"pass pruning.eig_floor > 0, e.g. the default {field_default(self, 'eig_floor')}")

    def score(self, *, splats, optimizers, state, step, info):
        F = spatial_fisher(info, int(self.pixel_stride), bool(self.per_channel))
        ev = torch.linalg.eigvalsh(F)  # F is a sum of outer products: symmetric PSD
        low = ev < self.eig_floor
        state["clamped"] = int(state.get("clamped", 0)) + int(low.any(dim=-1).sum())
        return ev.clamp_min(self.eig_floor).log().sum(dim=-1)
