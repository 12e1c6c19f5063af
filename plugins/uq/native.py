"""Native posterior uncertainty: re-render posterior samples (paper Eq. 4)."""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Optional

import torch

from b3dgs.uq.regime import Predictive, UQRegime, render_params, sample_spread


@dataclass
class NativeUQ(UQRegime):
    """Draws S parameter sets from the trained posterior blocks (each block replaces the attributes it
    models, in the configured order: geometry for NIW; activity, opacity and colour as well for DPMM),
    re-renders them in batched calls and returns var = u_p + σ̂², where σ̂² is the aleatoric variance
    of the last configured block that offers one (NIW's plug-in residual MSE, or the NoiseBlock's
    E[σ²]). The prediction is the point-estimate render.

    ``count_scale`` (None: the model's own) draws from the posterior with N̂ ← c·N̂ (Eq. 2-3) in every
    block that has that setting, on a copy of the block and of its state: the trained model and its
    training are untouched (``bench/uq_count_scale.py`` measures what c does)."""

    count_scale: Optional[float] = None

    def _blocks(self, m):
        """(block, state) pairs to draw from: the model's own, or copies with ``count_scale`` applied."""
        out = []
        for name, blk in m.posterior.items():
            st = m.states[name]
            if self.count_scale is not None and "count_scale" in {f.name for f in fields(blk)}:
                blk, st = replace(blk, count_scale=float(self.count_scale)), dict(st)
            out.append((blk, st))
        return out

    def fit(self, models, scene):
        super().fit(models, scene)
        m = self.models[0]
        if not m.posterior:
            raise ValueError("uq=native needs a model trained with posterior blocks (model=niw or model=dpmm); "
                             "use uq=proxy for a standard model")
        self.sigma2 = 0.0
        # one prepared draw function per block: posterior set-up once, not per chunk or view
        self.samplers = [blk.sampler(splats=m.splats, state=st) for blk, st in self._blocks(m)]
        self.base = render_params(m)
        for name, blk in m.posterior.items():
            v = blk.aleatoric_variance(state=m.states[name])
            if v is not None:
                self.sigma2 = float(v)

        self.fit_info["sigma2_plugin"] = self.sigma2

    @torch.no_grad()
    def spread(self, camera, generator=None):
        """(point-estimate render (H, W, 3), u_p (H, W)) of one view: Eq. 4 over ``samples`` draws."""
        m = self.models[0]

        def draw(n):
            p = dict(self.base)
            for sampler in self.samplers:
                p = sampler(n, generator, p)
            return p

        _, u = sample_spread(m, camera, draw, self.samples, self.chunk)
        return m.render_eval(camera), u

    @torch.no_grad()
    def predict(self, camera, generator=None):
        mean, u = self.spread(camera, generator)
        return Predictive(mean=mean, var=u + self.sigma2, epistemic=u, aleatoric=self.sigma2)
