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
and can be added to any trained run at evaluation (``uq=[native_sh]``) or fitted by a policy at the scoring resolution
(:meth:`b3dgs.acquisition.ScoringContext.fit_posterior`; ``acquisition=info_gain``).

Public for policies and tools: ``view_information`` (a view's rank-one information per Gaussian), ``precision`` (Λ),
``covariance`` (Λ⁻¹) and ``condition`` (the state after one more view, exact; the hook ``condition_on_view``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Iterable, Optional

import torch
from torch import Tensor

from b3dgs.device import randn
from b3dgs.errors import B3dgsError
from b3dgs.numerics import guard, safe_cholesky, zero_invalid
from b3dgs.plugin import PosteriorBlock, ViewAccumulator
from b3dgs.render.projection import sh_basis

_DEGREE0 = ("posterior.sh: the model renders SH degree 0, so its colour has no direction and the directional "
            "posterior has nothing to add to a constant colour")
_DEGREE0_FIX = "train with model.sh_degree >= 1 (the default 3) for more than model.sh_increase_every steps"
#: σ̂² below this (a perfectly fitted or empty pass) is raised to it (guard ``sh.sigma2_floor``)
SIGMA2_FLOOR = 1e-6


@dataclass
class SHView:
    """One view's information s y yᵀ per Gaussian it sees, for each colour channel: rows ``idx``, s = Σ_p w² / σ̂² and
    y, the SH basis at the direction from the view's centre to the Gaussian."""

    idx: Tensor  # (n,) long
    s: Tensor  # (n,) float64
    y: Tensor  # (n, B) float64

    def add_to(self, M: Tensor) -> Tensor:
        """M[k] += s y yᵀ for the Gaussians of this view, in place; returns M."""
        return M.index_add_(0, self.idx, self.s[:, None, None] * (self.y[:, :, None] * self.y[:, None, :]))


def seen_weights(render) -> tuple[Tensor, Tensor]:
    """(rows, Σ_p w²) of the Gaussians a render sees, float64; non-finite or negative sums are left out (guard
    ``sh.invalid_weights``), a view that sees none is counted (``sh.empty_view``: it teaches nothing)."""
    if render.weight_sq_sum is None:
        raise B3dgsError("posterior.sh: the renderer gave no per-Gaussian Σ w² (weight_sq_sum)",
                         "use a renderer that returns weights (cpu, torch or gsplat)")
    wsq = render.weight_sq_sum.detach().reshape(-1).double()
    wsq = zero_invalid("sh.invalid_weights", wsq)
    idx = torch.nonzero(wsq > 0).squeeze(-1)
    guard("sh.empty_view", int(idx.numel() == 0))
    return idx, wsq[idx]


class SHInformation(ViewAccumulator):
    """``sh_views``: the SH degree and per view its centre, rows seen and their Σ_p w_kp² (Λ is assembled per view, by
    :meth:`SHPosteriorBlock.precision`); ``sq_err`` / ``n_values``: the renders' summed squared residual against the
    views' images and the number of values summed (σ̂² of the module docstring)."""

    key = "sh_information"

    def start(self, *, params, sh_degree, seed):
        dev = params["means"].device
        self.views = {"degree": int(sh_degree), "views": []}
        self.sq_err = torch.zeros((), dtype=torch.float64, device=dev)
        self.n_values = torch.zeros((), dtype=torch.float64, device=dev)

    def add(self, *, camera, render, params, sh_degree):
        self.views["views"].append((camera.center, *seen_weights(render)))
        if camera.image is not None:
            rgb = render.rgb.detach().double()
            self.sq_err += (rgb - camera.image.to(rgb)).square().sum()
            self.n_values += rgb.numel()

    def result(self):
        return {"sh_views": self.views, "sq_err": self.sq_err, "n_values": self.n_values}


@dataclass
class SHPosteriorBlock(PosteriorBlock):
    """q(A_k) = Π_channels N(Â_k, Λ_k⁻¹) over all active SH coefficients (module docstring), from one pass over the
    training views. ``prior_precision`` τ (in units of 1/SH-coefficient²): the variance of a colour no camera
    constrains is ‖y(d)‖²/τ (‖y‖² = (deg+1)²/(4π) summed over the bases, ≈ 1.27 at degree 3 for τ = 1). The state
    holds Λ (``lam``), σ̂² and N; Λ⁻¹ (``cov``) and the draws' factor (``u``) are derived from Λ when first asked."""

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

    # ---------------------------------------------------------------- what a view teaches (public: policies, tools)
    @staticmethod
    def _view(center: Tensor, idx: Tensor, wsq: Tensor, means: Tensor, degree: int, sigma2: float) -> SHView:
        d = torch.nn.functional.normalize(means[idx] - center.to(means), dim=-1)
        return SHView(idx, wsq / sigma2, sh_basis(degree, d))

    def view_information(self, *, state, camera, render, means: Tensor) -> SHView:
        """What the view ``camera`` would teach the posterior ``state``: s = Σ_p w² / σ̂² from ``render`` (its
        point-estimate render with weights, at the resolution of the pass that made ``state``) and y toward the
        camera's centre from ``means`` (N, 3). Needs no image of the view."""
        deg = int(round(math.sqrt(state["lam"].shape[-1]))) - 1
        return self._view(camera.center, *seen_weights(render), means.detach().double(), deg, float(state["sigma2"]))

    def precision(self, views: Iterable[SHView], *, n: int, degree: int, device) -> Tensor:
        """(n, B, B) Λ = τI + Σ_views s y yᵀ, float64."""
        B = (degree + 1) ** 2
        lam = self.prior_precision * torch.eye(B, dtype=torch.float64, device=device).expand(n, B, B).clone()
        for v in views:
            v.add_to(lam)
        return lam

    def covariance(self, state) -> Tensor:
        """(N, B, B) Λ⁻¹ of ``state`` (computed once, kept in it)."""
        if "cov" not in state:
            state["cov"] = torch.cholesky_inverse(safe_cholesky(state["lam"]))
        return state["cov"]

    @torch.no_grad()
    def condition(self, state, view: SHView) -> dict:
        """A new state, the posterior after ``view``'s information (``state`` is not modified): Λ + s y yᵀ and Λ⁻¹
        by the exact rank-one downdate (Sherman–Morrison) for the Gaussians the view sees."""
        P = self.covariance(state)
        new = {k: v for k, v in state.items() if k != "u"}
        if view.idx.numel():
            Pk = P[view.idx]
            u = torch.einsum("nij,nj->ni", Pk, view.y)
            q = (u * view.y).sum(-1)
            new["cov"] = P.clone()
            new["cov"][view.idx] = Pk - (view.s / (1.0 + view.s * q))[:, None, None] * (u[:, :, None] * u[:, None, :])
            new["lam"] = view.add_to(state["lam"].clone())
        return new

    def condition_on_view(self, *, splats, state, weight_sums=None, render=None, camera=None):
        """:meth:`condition` on the view of ``render`` and ``camera``; None with ``weight_sums`` alone (no direction)."""
        if render is None or camera is None:
            return None
        return self.condition(state, self.view_information(state=state, camera=camera, render=render,
                                                           means=splats["means"]))

    @torch.no_grad()
    def absorb_view_sums(self, *, splats, state, sums: dict) -> None:
        """Λ from the pass's views (:meth:`precision`) and σ̂² = the pass's residual MSE."""
        n = splats["means"].shape[0]
        views = sums.get("sh_views")
        if views is None:
            raise B3dgsError("posterior.sh: the view pass gave no sh_views", "this is a bug in b3dgs: rerun with "
                             "b3dgs.debug=true and report the traceback")
        nv = float(sums.get("n_values", 0))
        s2 = float(sums["sq_err"]) / nv if nv > 0 else float("nan")
        if guard("sh.sigma2_floor", int(not s2 >= SIGMA2_FLOOR)):
            s2 = SIGMA2_FLOOR if not math.isfinite(s2) else max(s2, SIGMA2_FLOOR)
        deg = views["degree"]
        if deg == 0:  # a view-independent colour, nothing directional to be uncertain about
            raise B3dgsError(_DEGREE0, _DEGREE0_FIX)
        means = splats["means"].detach().double()
        for k in ("u", "cov"):
            state.pop(k, None)
        state["lam"] = self.precision((self._view(*v, means, deg, s2) for v in views["views"]), n=n, degree=deg,
                                      device=means.device)
        state["n"] = torch.tensor(n, dtype=torch.int64, device=means.device)
        state["sigma2"] = torch.tensor(s2, dtype=torch.float64, device=means.device)

    def _u(self, state, splats=None) -> Tensor:
        """(N, B, B) U = L⁻ᵀ (Λ = L Lᵀ), so a draw is Â_k + U_k z with z ~ N(0, I): Cov = Λ_k⁻¹ (kept in ``state``);
        checked against the N of ``splats`` when given."""
        n = int(state["n"]) if splats is None else splats["means"].shape[0]
        if "lam" not in state or int(state["n"]) != n:
            raise B3dgsError(f"posterior.sh: the posterior was computed for {int(state['n'])} Gaussians, the model has {n}",
                             "call SplatModule.prepare_posterior() after the last topology change")
        if "u" not in state:
            L = safe_cholesky(state["lam"])
            eye = torch.eye(L.shape[-1], dtype=torch.float64, device=L.device).expand_as(L)
            state["u"] = torch.linalg.solve_triangular(L.transpose(-1, -2), eye, upper=True)
        return state["u"]

    def colour_variance(self, *, splats, state, dirs: Tensor) -> Tensor:
        """(N,) Var[c_k(d_k)] = y(d_k)ᵀ Λ_k⁻¹ y(d_k) per channel, for unit directions ``dirs`` (N, 3)."""
        u = self._u(state, splats)
        B = u.shape[-1]
        deg = int(round(math.sqrt(B))) - 1
        y = sh_basis(deg, dirs.double())
        uy = torch.einsum("nji,nj->ni", u, y)  # U_kᵀ y; Var = ‖U_kᵀ y‖² since Λ⁻¹ = U Uᵀ
        return uy.square().sum(-1)

    @torch.no_grad()
    def sample(self, *, splats, state, n, generator, params, info):
        """SH draws Â_k + U_k z (z ~ N(0, I), independent per channel), added to ``params``' sh0 / shN (which may
        already hold (n, N, ...) draws of an earlier block)."""
        u = self._u(state, splats)
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

    def _trace(self, state) -> Tensor:
        """(N,) tr Λ_k⁻¹ = ‖U_k‖²_F."""
        return self._u(state).square().sum((-1, -2))

    def export(self, *, splats=None, state):
        return {"sh_var_trace": self._trace(state).float()} if "lam" in state else {}

    def summary(self, *, state):
        if "lam" not in state:
            return {"computed": False}
        tr = self._trace(state)
        return {"computed": True, "sigma2": float(state["sigma2"]), "bases": int(state["lam"].shape[-1]),
                "trace_median": float(tr.median()), "trace_max": float(tr.max())}
