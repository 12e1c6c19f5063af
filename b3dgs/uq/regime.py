"""Uncertainty regimes: a per-pixel predictive mean and variance for any camera.

Every regime (native posterior, position-jitter proxy, deep ensemble, residual head) implements
``fit(models, scene)`` once and ``predict(camera, generator)`` per view. Acquisition policies score
candidate views through the same interface, so a new regime is usable everywhere at once.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Optional, Sequence

import torch
from torch import Tensor

from b3dgs.errors import B3dgsError
from b3dgs.plugin import validate_once
from b3dgs.types import Camera, Scene


@dataclass
class Predictive:
    """Per-pixel predictive distribution N(mean, var·I₃) of one view."""

    mean: Tensor  # (H, W, 3) the prediction scored against the ground truth
    var: Tensor  # (H, W) predictive variance per channel (epistemic + aleatoric)
    epistemic: Tensor  # (H, W) the sample/member spread u_p alone
    aleatoric: float  # the constant aleatoric term added to u_p (0 if none)

    def cpu(self) -> "Predictive":
        """This prediction with its images on the CPU (where the metrics and ground truth live)."""
        return Predictive(self.mean.cpu(), self.var.cpu(), self.epistemic.cpu(), self.aleatoric)


@dataclass
class UQRegime:
    """Base of the uncertainty regimes; ``samples`` Monte-Carlo draws per view where relevant.

    ``has_epistemic``: whether ``Predictive.epistemic`` carries a spread of its own (False for
    ``uq=constant``); ``b3dgs-eval`` scores that part alone for the regimes that have it. ``fit_info``:
    what ``fit`` estimated (scalars, view names), copied into ``uq.json``.
    """

    has_epistemic: ClassVar[bool] = True
    samples: int = 50
    chunk: int = 10  # samples rendered per batched call (bounds memory)

    def validate(self, **kwargs) -> None:
        if self.samples < 1:
            raise B3dgsError(f"{type(self).__name__}.samples must be >= 1, got {self.samples}",
                             fix="pass uq.samples >= 1 (b3dgs-eval uq.samples=50 is the default)")
        if self.chunk < 1:
            raise B3dgsError(f"{type(self).__name__}.chunk must be >= 1",
                             fix="pass the regime's chunk >= 1 (draws rendered together, e.g. uq.native_sh.chunk=10)")

    def fit(self, models: Sequence, scene: Scene) -> None:
        validate_once(self)  # b3dgs-eval's config check did it
        if not models:
            raise B3dgsError(f"{type(self).__name__} needs at least one trained model",
                             fix="pass at least one trained SplatModule, e.g. [b3dgs.runs.load_run(run_dir).module]")
        self.models = list(models)
        self.scene = scene
        self.fit_info: dict = {}

    def predict(self, camera: Camera, generator: Optional[torch.Generator] = None) -> Predictive:
        raise NotImplementedError  # protocol: an abstract method (subclasses implement it)


def render_params(module) -> dict[str, Tensor]:
    """The point-estimate parameters of a module, detached."""
    return {k: v.detach() for k, v in module.params().items()}


@torch.no_grad()
def sample_spread(module, camera: Camera, draw, samples: int, chunk: int) -> tuple[Tensor, Tensor]:
    """Render ``samples`` parameter draws in batched calls (shared tile binning per call).

    ``draw(n)`` returns a params dict with (n, N, ...) sampled entries. Returns the sample mean image
    (H, W, 3) and u_p = mean over samples and RGB of the squared deviation from it (H, W) (Eq. 4,
    averaged over channels so that it is a per-channel variance).
    """
    # streaming moments about the first sample (no (S, H, W, 3) stack; exact enough in float64)
    ref = total = total_sq = None
    left = samples
    while left > 0:
        n = min(chunk, left)
        out = module.render_camera(camera, params=draw(n))
        rgb = (out.rgb if out.rgb.dim() == 4 else out.rgb.unsqueeze(0)).double()
        if ref is None:
            ref = rgb[0].clone()
            total, total_sq = torch.zeros_like(ref), torch.zeros_like(ref)
        d = rgb - ref
        total += d.sum(0)
        total_sq += d.square().sum(0)
        left -= n
    dmean = total / samples
    mean = ref + dmean
    u = (total_sq / samples - dmean.square()).clamp_min(0.0).mean(-1)
    return mean.float(), u.float()
