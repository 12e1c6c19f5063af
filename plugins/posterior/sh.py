"""Directional appearance posterior: a Laplace (here exact Gaussian) posterior over every SH coefficient of a Gaussian.

Beyond the paper. The colour a Gaussian shows along direction d is linear in its SH coefficients,
c_k(d) = y(d)ᵀ A_k + 0.5 (y: the real SH basis, A_k: (B, 3)), and it enters pixel p with compositing weight w_kp.
Under the Gaussian pixel likelihood with variance σ² and an isotropic prior N(Â, τ⁻¹ I), the posterior of each colour
channel's coefficients, with the geometry and the other Gaussians held at the trained values, is Gaussian with
precision

    Λ_k = (1/σ²) Σ_views Σ_p w_kp² y(d_kv) y(d_kv)ᵀ + τ I,        d_kv = (μ_k − o_v) / ‖μ_k − o_v‖,

so Var[c_k(d)] = y(d)ᵀ Λ_k⁻¹ y(d): small along the directions the training cameras looked from, up to 1/τ·‖y(d)‖²
along directions none did. This is what the paper's geometry posterior cannot express (its Var[μ_k] is E[Σ_k]/κ_n,
shaped like the Gaussian whatever the cameras), and what a deep ensemble shows on badly supported views: higher-order
SH fitted from a few directions extrapolate arbitrarily. The paper's ``ColorBlock`` is this block restricted to the
DC coefficient (view-independent), which does not know the directions.

Approximations: the clamp of the colour at 0 is ignored; the precision is diagonal across Gaussians (the Gauss-Newton
cross terms between Gaussians that share pixels are dropped, as in FisherRF's diagonal); σ² is the plug-in residual
MSE of the same pass over the training views. The posterior is a function of the trained Gaussians, computed in one
pass over the training views (:meth:`b3dgs.module.SplatModule.prepare_posterior`), so it needs no training-time state
and can be added to any trained run at evaluation (``uq=[native_sh]``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Optional

import torch

from b3dgs.device import randn
from b3dgs.errors import B3dgsError
from b3dgs.numerics import guard
from b3dgs.plugin import PosteriorBlock, ViewAccumulator
from b3dgs_plugins.posterior.niw import safe_cholesky

_DEGREE0 = ("posterior.sh: the model renders SH degree 0, so its colour has no direction and the directional "
            "posterior has nothing to add to a constant colour")
_DEGREE0_FIX = "train with model.sh_degree >= 1 (the default 3) for more than model.sh_increase_every steps"
#: σ̂² below this (a perfectly fitted or empty pass) is raised to it (guard ``sh.sigma2_floor``)
SIGMA2_FLOOR = 1e-6


class SHInformation(ViewAccumulator):
    """Σ_views Σ_p w_kp² y(d_kv) y(d_kv)ᵀ (``sh_information``, (N, B, B)): the information of Gaussian k's SH
    coefficients under a unit-variance pixel likelihood (y: the real SH basis at the active degree, B = (deg+1)²,
    d_kv the unit direction from view v's centre to μ_k); ``sq_err`` / ``n_values``: the summed squared residual of
    the renders against the views' images and the number of values summed (σ̂² of the module docstring)."""

    key = "sh_information"

    def start(self, *, params, sh_degree, seed):
        n, dev = params["means"].shape[0], params["means"].device
        nb = (sh_degree + 1) ** 2
        self.sums = {"sh_information": torch.zeros(n, nb, nb, dtype=torch.float64, device=dev),
                     "sq_err": torch.zeros((), dtype=torch.float64, device=dev),
                     "n_values": torch.zeros((), dtype=torch.float64, device=dev)}

    def add(self, *, camera, render, params, sh_degree):
        from b3dgs.render.projection import sh_basis

        means = params["means"].detach()
        dev = means.device
        if render.weight_sq_sum is None:
            raise B3dgsError("posterior.sh: the renderer gave no per-Gaussian Σ w² (weight_sq_sum)",
                             "use a renderer that returns weights (cpu, torch or gsplat)")
        wsq = render.weight_sq_sum.detach().reshape(-1).double()
        seen = torch.nonzero(wsq > 0).squeeze(-1)
        d = torch.nn.functional.normalize(means[seen].double() - camera.center.to(dev, torch.float64), dim=-1)
        y = sh_basis(sh_degree, d)
        self.sums["sh_information"].index_add_(0, seen, wsq[seen, None, None] * (y[:, :, None] * y[:, None, :]))
        if camera.image is not None:
            diff = render.rgb.detach().double().reshape(-1) - camera.image.to(dev).double().reshape(-1)
            self.sums["sq_err"] += diff.square().sum()
            self.sums["n_values"] += diff.numel()

    def result(self):
        return self.sums


@dataclass
class SHPosteriorBlock(PosteriorBlock):
    """q(A_k) = Π_channels N(Â_k, Λ_k⁻¹) over all active SH coefficients (module docstring), from one pass over the
    training views. ``prior_precision`` τ (in units of 1/SH-coefficient²): the variance of a colour no camera
    constrains is ‖y(d)‖²/τ (‖y‖² = (deg+1)²/(4π) summed over the bases, ≈ 1.27 at degree 3 for τ = 1)."""

    prior_precision: float = 1.0
    per_gaussian_state: ClassVar[tuple[str, ...]] = ()  # computed after training, checked against N when drawn

    def validate(self, **kw) -> None:
        if not (self.prior_precision > 0 and math.isfinite(self.prior_precision)):
            raise B3dgsError(f"posterior.sh.prior_precision={self.prior_precision} must be a finite number > 0 "
                             "(the precision of an unconstrained SH coefficient)",
                             fix="pass posterior.sh.prior_precision as a finite number > 0, e.g. the default 1.0")
        if kw.get("sh_degree") == 0:
            raise B3dgsError(_DEGREE0, _DEGREE0_FIX)

    def initialize_state(self, *, splats, scene, info):
        dev = splats["means"].device
        return {"n": torch.tensor(-1, dtype=torch.int64, device=dev),
                "sigma2": torch.tensor(float("nan"), dtype=torch.float64, device=dev)}

    def view_pass(self, *, state) -> Optional[list[ViewAccumulator]]:
        return [SHInformation()]

    @torch.no_grad()
    def absorb_view_sums(self, *, splats, state, sums: dict) -> None:
        """Λ_k from the pass's Σ w² y yᵀ and σ̂² = the pass's residual MSE; keeps the upper Cholesky inverse
        U_k = L_kᵀ⁻¹ (Λ_k = L_k L_kᵀ), so a draw is Â_k + U_k z with z ~ N(0, I): Cov = Λ_k⁻¹."""
        n = splats["means"].shape[0]
        info = sums.get("sh_information")
        if info is None or info.dim() != 3 or info.shape[0] != n or info.shape[1] != info.shape[2]:
            raise B3dgsError(f"posterior.sh: the view pass gave SH information of shape "
                             f"{None if info is None else tuple(info.shape)}, expected ({n}, B, B)",
                             fix="this is a bug in b3dgs (the SH block's own accumulator): rerun with "
                                 "b3dgs.debug=true and report the traceback")
        nv = float(sums.get("n_values", 0))
        s2 = float(sums["sq_err"]) / nv if nv > 0 else float("nan")
        if guard("sh.sigma2_floor", int(not s2 >= SIGMA2_FLOOR)):
            s2 = SIGMA2_FLOOR if not math.isfinite(s2) else max(s2, SIGMA2_FLOOR)
        B = info.shape[-1]
        if B == 1:  # SH degree 0: a view-independent colour, nothing directional to be uncertain about
            raise B3dgsError(_DEGREE0, _DEGREE0_FIX)
        lam = info.double() / s2 + self.prior_precision * torch.eye(B, dtype=torch.float64, device=info.device)
        L = safe_cholesky(lam)
        eye = torch.eye(B, dtype=torch.float64, device=info.device).expand_as(L)
        state["u"] = torch.linalg.solve_triangular(L.transpose(-1, -2), eye, upper=True)  # (N, B, B) = L^-T
        state["n"] = torch.tensor(n, dtype=torch.int64, device=info.device)
        state["sigma2"] = torch.tensor(s2, dtype=torch.float64, device=info.device)

    def _u(self, splats, state) -> torch.Tensor:
        n = splats["means"].shape[0]
        if "u" not in state or int(state["n"]) != n:
            raise B3dgsError(f"posterior.sh: the posterior was computed for {int(state['n'])} Gaussians, the model has {n}",
                             "call SplatModule.prepare_posterior() after the last topology change")
        return state["u"]

    def colour_variance(self, *, splats, state, dirs: torch.Tensor) -> torch.Tensor:
        """(N,) Var[c_k(d_k)] = y(d_k)ᵀ Λ_k⁻¹ y(d_k) per channel, for unit directions ``dirs`` (N, 3)."""
        from b3dgs.render.projection import sh_basis

        u = self._u(splats, state)
        B = u.shape[-1]
        deg = int(round(math.sqrt(B))) - 1
        y = sh_basis(deg, dirs.double())
        uy = torch.einsum("nji,nj->ni", u, y)  # U_kᵀ y; Var = ‖U_kᵀ y‖² since Λ⁻¹ = U Uᵀ
        return uy.square().sum(-1)

    @torch.no_grad()
    def sample(self, *, splats, state, n, generator, params, info):
        """SH draws Â_k + U_k z (z ~ N(0, I), independent per channel), added to ``params``' sh0 / shN (which may
        already hold (n, N, ...) draws of an earlier block)."""
        u = self._u(splats, state)
        B = u.shape[-1]
        out = dict(params)
        sh0, shN = out["sh0"], out.get("shN")
        N = u.shape[0]
        z = randn((n, N, B, 3), generator=generator, dtype=torch.float64, device=u.device)
        delta = torch.einsum("nij,snjc->snic", u, z).to(sh0.dtype)  # (n, N, B, 3)
        out["sh0"] = sh0 + delta[:, :, :1]
        if B > 1:
            if shN is None or shN.shape[-2] < B - 1:
                raise B3dgsError(f"posterior.sh: the posterior has {B} SH bases, the model's shN holds "
                                 f"{None if shN is None else shN.shape[-2]}", "compute it at the model's SH degree")
            extra = shN[..., B - 1:, :]
            pad = extra.expand((n,) + extra.shape[-3:]) if extra.dim() == 3 else extra
            out["shN"] = torch.cat([shN[..., : B - 1, :] + delta[:, :, 1:], pad], dim=-2)
        return out

    aleatoric_fallback: ClassVar[bool] = True  # NIW's or the noise block's σ̂² first, when the model has one

    def aleatoric_variance(self, *, state) -> Optional[float]:
        """The pass's residual MSE σ̂² (None before the pass)."""
        s2 = float(state["sigma2"])
        return s2 if math.isfinite(s2) else None

    @staticmethod
    def _trace(state) -> torch.Tensor:
        """(N,) tr Λ_k⁻¹ = ‖U_k‖²_F."""
        return state["u"].square().sum((-1, -2))

    def export(self, *, splats=None, state):
        return {"sh_var_trace": self._trace(state).float()} if "u" in state else {}

    def summary(self, *, state):
        if "u" not in state:
            return {"computed": False}
        tr = self._trace(state)
        return {"computed": True, "sigma2": float(state["sigma2"]), "bases": int(state["u"].shape[-1]),
                "trace_median": float(tr.median()), "trace_max": float(tr.max())}
