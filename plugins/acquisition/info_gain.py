"""info_gain: what a candidate view would teach the directional (SH) colour posterior, in closed form (beyond the paper).

The SH posterior of Gaussian k (``plugins/posterior/sh.py``) has precision Λ_k = τI + Σ_{v ∈ train} s_kv y_kv y_kvᵀ, with
s_kv = Σ_p w_kp² / σ̂² (view v's squared compositing weights in units of the pixel noise) and y_kv = y(d_kv), the real
SH basis at the direction from v's centre to μ_k. A view c adds J_kc = s_kc y_kc y_kcᵀ, rank one per Gaussian; with
P_k = Λ_k⁻¹, u = P_k y_kc and q = y_kcᵀ u (matrix determinant lemma, Sherman–Morrison):

    params      ½ log det(I + P_k J_kc) = ½ log(1 + s_kc q)                  (BALD; FisherRF's quantity)
    predictive  tr((P_k − (Λ_k + J_kc)⁻¹) G_k) = s_kc uᵀ G_k u / (1 + s_kc q),  G_k = Σ_{t ∈ targets} s_kt y_kt y_ktᵀ

each summed over the Gaussians the view sees. ``predictive`` is the drop in the summed predictive variance of the
target views' pixel colours (Σ_t Σ_p Var[C_tp] = σ̂² Σ_k tr(P_k G_k)), in units of σ̂²: the target-aware gain of EPIG
(Smith et al., AISTATS 2023) in its Gaussian-linear form, with the candidate pool (``targets=pool``), or the pool and
the training views (``pool+train``), standing in for where the scene will be viewed from. Variance, not entropy: a
pixel's entropy drop needs that pixel's own predictive variance (a sum over the Gaussians it sees), which the
renderer's per-Gaussian sums do not give; the variance drop is additive over Gaussians and exact here.

Choices: one precision serves the three colour channels (weights and directions do not depend on the channel and σ̂²
is pooled over them), so each score is 3× one channel's; σ̂² is the training views' residual MSE at the scoring
resolution (as the SH block's pass); every view (training, candidates, targets) is rendered once at the scoring
resolution with the phase-1 model's point estimate, and only its per-Gaussian Σ_p w² enters (no image of a candidate).
Not built: a geometry (centre) term and an unexplained-pixel term, which did not help the prototype (issue 42).

``condition`` (``batch=greedy_conditioned``) adds the picked view's J exactly (rank-one downdate of P), so a re-score
equals recomputing the posterior with the view among the training views; ``conditioned_ratio`` gives every remaining
candidate's exact conditioned score over its first score (scoring is a few products per visible Gaussian).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Optional, Sequence

import torch
from torch import Tensor

from b3dgs.acquisition import AcquisitionPolicy, Selection, top_k
from b3dgs.errors import B3dgsError
from b3dgs.numerics import guard
from b3dgs.render.projection import sh_basis
from b3dgs_plugins.posterior.niw import safe_cholesky

OBJECTIVES = ("predictive", "params")
TARGETS = ("pool", "pool+train")
SIGMA2_FLOOR = 1e-6  # σ̂² below this is raised to it (guard ``info_gain.sigma2_floor``), as the SH block does
CHANNELS = 3


@dataclass
class _View:
    """One view's rank-one information per Gaussian it sees: rows ``idx``, s = Σ_p w² / σ̂² and the SH basis y."""

    idx: Tensor  # (n,) long
    s: Tensor  # (n,) float64
    y: Tensor  # (n, B) float64


@dataclass
class InfoGainPolicy(AcquisitionPolicy):
    """Closed-form information of a view for the SH colour posterior (module docstring): ``objective`` predictive
    (target-aware, EPIG-like; the default) or params (parameter gain, BALD/FisherRF-like); ``targets`` pool or
    pool+train; ``prior_precision`` τ of the SH posterior (as ``posterior.sh.prior_precision``)."""

    family: str = "niw"
    objective: str = "predictive"
    targets: str = "pool"
    prior_precision: float = 1.0

    def validate(self, **kwargs) -> None:
        super().validate(**kwargs)
        if self.objective not in OBJECTIVES:
            raise B3dgsError(f"acquisition info_gain: objective={self.objective!r} is not one of {'|'.join(OBJECTIVES)}",
                             "pass acquisition.objective=predictive (or params)")
        if self.targets not in TARGETS:
            raise B3dgsError(f"acquisition info_gain: targets={self.targets!r} is not one of {'|'.join(TARGETS)}",
                             "pass acquisition.targets=pool (or pool+train)")
        tau = self.prior_precision
        if isinstance(tau, bool) or not isinstance(tau, (int, float)) or not (tau > 0 and math.isfinite(tau)):
            raise B3dgsError(f"acquisition info_gain: prior_precision={tau!r} must be a finite number > 0",
                             "pass acquisition.prior_precision=1.0")

    # ---------------------------------------------------------------- the posterior of the current training views
    def _view(self, ctx, camera, means: Tensor, deg: int, sigma2: float, ro=None) -> _View:
        ro = ctx.render(camera, return_weights=True) if ro is None else ro
        if ro.weight_sq_sum is None:
            raise B3dgsError("acquisition info_gain: the renderer returned no weight sums",
                             "use a renderer that gives them (cpu, torch or gsplat)")
        wsq = ro.weight_sq_sum.detach().reshape(-1).double()
        bad = ~torch.isfinite(wsq) | (wsq < 0)
        if guard("info_gain.invalid_weights", bad):
            wsq = torch.where(bad, torch.zeros_like(wsq), wsq)
        idx = torch.nonzero(wsq > 0).squeeze(-1)
        guard("info_gain.empty_view", int(idx.numel() == 0))  # a view that sees no Gaussian scores 0
        d = torch.nn.functional.normalize(means[idx] - camera.center.to(means), dim=-1)
        return _View(idx, wsq[idx] / sigma2, sh_basis(deg, d))

    @staticmethod
    def _sigma2(ctx, renders) -> float:
        """The training views' residual MSE at the scoring resolution (views without an image left out)."""
        sq, n = 0.0, 0
        for cam, ro in zip(ctx.train, renders):
            if cam.image is None:
                continue
            rgb = ro.rgb.detach().double()
            sq += float((rgb - cam.image.to(rgb)).square().sum())
            n += rgb.numel()
        s2 = sq / n if n else float("nan")
        if guard("info_gain.sigma2_floor", int(not s2 >= SIGMA2_FLOOR)):
            s2 = SIGMA2_FLOOR if not math.isfinite(s2) else max(s2, SIGMA2_FLOOR)
        return s2

    @staticmethod
    def _add(M: Tensor, v: _View) -> None:
        """M[k] += s y yᵀ for the Gaussians of view v."""
        M.index_add_(0, v.idx, v.s[:, None, None] * (v.y[:, :, None] * v.y[:, None, :]))

    @torch.no_grad()
    def prepare(self, ctx, candidates: Sequence) -> dict:
        """The posterior of the current training views and every candidate's (and target's) information, cached for
        this scoring context and candidate list."""
        key = (id(ctx), tuple(c.name for c in candidates))
        st = getattr(self, "_state", None)
        if st is not None and st["key"] == key:
            return st
        t0 = time.perf_counter()
        deg = ctx.sh_degree()
        if deg < 1:
            raise B3dgsError("acquisition info_gain: the phase-1 model renders SH degree 0, so its colour has no "
                             "direction to learn from a new view",
                             "train the phase-1 model with model.sh_degree >= 1 for more than model.sh_increase_every "
                             "steps")
        means = ctx.params()["means"].detach().double()
        N, B = means.shape[0], (deg + 1) ** 2
        renders = [ctx.render(c, return_weights=True) for c in ctx.train]  # one render per training view
        s2 = self._sigma2(ctx, renders)
        eye = torch.eye(B, dtype=torch.float64, device=means.device)
        lam = self.prior_precision * eye.expand(N, B, B).clone()
        train = [self._view(ctx, c, means, deg, s2, ro) for c, ro in zip(ctx.train, renders)]
        for v in train:
            self._add(lam, v)
        P = torch.cholesky_inverse(safe_cholesky(lam))
        views = {c.name: self._view(ctx, c, means, deg, s2) for c in candidates}
        G = None
        if self.objective == "predictive":
            G = torch.zeros(N, B, B, dtype=torch.float64, device=means.device)
            for v in list(views.values()) + (train if self.targets == "pool+train" else []):
                self._add(G, v)
        self._state = {"key": key, "P": P, "P0": None, "G": G, "views": views, "means": means, "deg": deg,
                       "sigma2": s2, "first": None, "setup_s": time.perf_counter() - t0}
        return self._state

    # ---------------------------------------------------------------- scores
    def _gain(self, st: dict, v: _View) -> float:
        if v.idx.numel() == 0:
            return 0.0
        P = st["P"][v.idx]
        u = torch.einsum("nij,nj->ni", P, v.y)
        q = (u * v.y).sum(-1)
        if self.objective == "params":
            return CHANNELS * 0.5 * float(torch.log1p(v.s * q).sum())
        Gu = torch.einsum("nij,nj->ni", st["G"][v.idx], u)
        return CHANNELS * float((v.s * (u * Gu).sum(-1) / (1.0 + v.s * q)).sum())

    @torch.no_grad()
    def score(self, ctx, candidates) -> Tensor:
        return self.score_at(ctx, candidates, range(len(candidates)))

    @torch.no_grad()
    def score_at(self, ctx, candidates, positions) -> Tensor:
        st = self.prepare(ctx, candidates)
        out = torch.tensor([self._gain(st, st["views"][candidates[i].name]) for i in positions], dtype=torch.float64)
        if st["P0"] is None and st["first"] is None and len(out) == len(candidates):
            st["first"] = out.clone()  # the unconditioned scores, for conditioned_ratio
        return out

    def select(self, ctx, candidates, budget) -> Selection:
        t0 = time.perf_counter()
        scores = self.score(ctx, candidates)
        st = self._state
        return Selection(top_k(scores, budget), [float(v) for v in scores],
                         {"scoring_s": time.perf_counter() - t0, "setup_s": st["setup_s"], "sigma2": st["sigma2"],
                          "sh_degree": st["deg"]})

    # ---------------------------------------------------------------- batch conditioning (greedy_conditioned)
    @torch.no_grad()
    def condition(self, ctx, camera) -> bool:
        """P ← (Λ + J_camera)⁻¹, exactly (a rank-one downdate per Gaussian the view sees)."""
        st = getattr(self, "_state", None)
        if st is None or st["key"][0] != id(ctx):
            raise B3dgsError("acquisition info_gain: condition() before any score() in this scoring context",
                             "score the candidates first (the batch selectors do)")
        v = st["views"].get(camera.name) or self._view(ctx, camera, st["means"], st["deg"], st["sigma2"])
        if v.idx.numel() == 0:
            return True
        if st["P0"] is None:
            st["P0"] = st["P"].clone()
        P = st["P"][v.idx]
        u = torch.einsum("nij,nj->ni", P, v.y)
        q = (u * v.y).sum(-1)
        st["P"][v.idx] = P - (v.s / (1.0 + v.s * q))[:, None, None] * (u[:, :, None] * u[:, None, :])
        return True

    def conditioned_ratio(self, ctx, candidates, positions) -> Optional[Tensor]:
        st = getattr(self, "_state", None)
        if st is None or st["first"] is None:
            return None
        now = self.score_at(ctx, candidates, positions)
        first = st["first"][list(positions)]
        return torch.where(first > 0, now / first.clamp_min(1e-300), torch.zeros_like(now))

    def reset_conditioning(self, ctx) -> None:
        st = getattr(self, "_state", None)
        if st is not None and st["P0"] is not None:
            st["P"], st["P0"] = st["P0"], None
