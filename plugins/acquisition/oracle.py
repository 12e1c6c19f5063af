"""ORACLE (analysis only, uses the candidates' ground truth): the current render error of each candidate."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch

from b3dgs.acquisition import AcquisitionPolicy


@dataclass
class OraclePolicy(AcquisitionPolicy):
    """Score = MSE of the phase-1 render against the candidate's ground truth (at the scoring resolution).
    It bounds what a policy could gain by adding the views the model renders worst; it is not a policy one
    could run, and the study labels it as such."""

    uses_ground_truth: ClassVar[bool] = True
    no_conditioning: ClassVar[str] = "the current render error changes only when the model is retrained on the view"

    @torch.no_grad()
    def score(self, ctx, candidates):
        out = []
        for c in candidates:
            rgb = ctx.render(c).rgb.clamp(0, 1).double()
            out.append((rgb - ctx.ground_truth(c).double()).square().mean())
        return torch.stack(out).cpu()
