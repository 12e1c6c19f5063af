"""Shared proxy uncertainty: position-jitter Monte Carlo around any checkpoint."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from b3dgs.device import randn
from b3dgs.errors import check_field
from b3dgs.uq.regime import Predictive, UQRegime, render_params, sample_spread


@dataclass
class ProxyUQ(UQRegime):
    """Every Gaussian centre is jittered by isotropic N(0, (jitter·extent)² I) (extent: the normalised
    scene's camera-rig radius, 1.0 by default); u_p is the spread of the S re-renders. The same
    protocol applies to every method, standard models included. As in the paper, its intervals are
    reported raw: var = u_p, with no aleatoric term and no recalibration."""

    jitter: float = 0.002

    def validate(self, **kwargs):
        super().validate(**kwargs)
        check_field(self, "uq.proxy.jitter", self.jitter > 0, "> 0", "> 0 (a fraction of the scene extent)", got=True)

    @torch.no_grad()
    def predict(self, camera, generator=None):
        m = self.models[0]
        base = render_params(m)
        sigma = self.jitter * float(self.scene.extent)

        def draw(n):
            p = dict(base)
            means = base["means"]
            noise = randn((n,) + tuple(means.shape), generator=generator, dtype=means.dtype, device=means.device)
            p["means"] = means.unsqueeze(0) + sigma * noise
            return p

        _, u = sample_spread(m, camera, draw, self.samples, self.chunk)
        return Predictive(mean=m.render_eval(camera), var=u, epistemic=u, aleatoric=0.0)
