"""Native: mean u_p (paper Eq. 4) from NIW posterior samples, epistemic part only."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from b3dgs.acquisition import RegimePolicy


@dataclass
class NativePolicy(RegimePolicy):
    """Score = mean over pixels of the spread u_p of S posterior re-renders of the ``regime``, a
    :class:`b3dgs_plugins.uq.native.NativeUQ` composed from conf/uq (``native``, ``native_sh``, ``sh``,
    ``native_fisher3``, ...; the acquisition files set fewer samples). The aleatoric σ̂² is left out: it is the same
    for every view, so it cannot change the ranking.

    ``count_scale`` = 0.1 (uq=native's default; why: docs/user-guide.md, ``bench/uq_count_scale.py``).

    ``condition(ctx, camera)`` (batch=greedy_conditioned): one point-estimate render of ``camera`` at the
    scoring resolution gives each Gaussian's compositing weight sum w_k = Σ_p w_kp, scaled by the pixel-count
    ratio to the training resolution (the unit of N̂); the posterior blocks then take those pseudo-observations
    at the current centres (NIW: the closed-form update of its posterior with n_k = c·w_k, x̄_k = μ_k, C_k = 0,
    i.e. N̂ ← N̂ + w), on copies: the model is untouched."""

    family: str = "niw"

    @torch.no_grad()
    def condition(self, ctx, camera):
        regime = ctx.fit_regime(self.uq())
        if getattr(self, "_cond", None) is None:  # before the first conditioning: the reference spread
            self._cond = {"g0": regime.gaussian_spread(seed=ctx.seed), "w": {}}
        return regime.condition(self._weights(ctx, camera))

    def _weights(self, ctx, camera):
        """Σ_p w_kp of ``camera``'s point-estimate render, in training-resolution pixels (N̂'s unit)."""
        small = ctx.camera(camera)
        w = ctx.render(camera, return_weights=True).weight_sum.reshape(-1).double()
        return w * (camera.width * camera.height) / (small.width * small.height)

    @torch.no_grad()
    def conditioned_ratio(self, ctx, candidates, positions):
        """Σ_k w_ck g_k / Σ_k w_ck g⁰_k: candidate c's weight sums (one point render each, cached for the
        batch) against the per-Gaussian spread g of :meth:`NativeUQ.gaussian_spread` now and before any
        conditioning (4 draws, no render)."""
        cond = getattr(self, "_cond", None)
        if cond is None:
            return None
        g = ctx.fit_regime(self.uq()).gaussian_spread(seed=ctx.seed)
        out = []
        for i in positions:
            if i not in cond["w"]:
                cond["w"][i] = self._weights(ctx, candidates[i])
            w = cond["w"][i]
            den = float(w @ cond["g0"])
            out.append(float(w @ g) / den if den > 0 else 1.0)
        return torch.tensor(out, dtype=torch.float64)

    def reset_conditioning(self, ctx):
        self._cond = None
        ctx.fit_regime(self.uq()).reset_conditioning()
