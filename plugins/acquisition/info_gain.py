"""info_gain: what a candidate view would teach the directional (SH) colour posterior, in closed form (beyond the paper).

The SH posterior block (``plugins/posterior/sh.py``, composed from ``conf/posterior/sh``, fitted on the training views
by :meth:`b3dgs.acquisition.ScoringContext.fit_posterior`) gives P_k = Λ_k⁻¹ and what a view c adds, J_kc = s_kc y_kc
y_kcᵀ, rank one per Gaussian (s = Σ_p w² / σ̂², y the SH basis toward c); with u = P_k y_kc and q = y_kcᵀ u:

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
The prototype (issue 42) tried only an unexplained-pixel term (it did not help; not built).

``geometry=true`` (``info_gain_geometry``, ``info_gain_params_geometry``) adds the centres' term in the same units: per
view v and Gaussian k the 3×3 Fisher F_kv = Σ_p Σ_c ∇_μk C_pc ∇_μk C_pcᵀ (:meth:`view_fisher`: ``geometry_probes``
Hutchinson probes drawn on the CPU from the context's seed and the view's name, so a view's F never depends on scoring
order); Λ^μ_k = τ_μ I + Σ_train F_kv / σ̂², J^μ_kc = F_kc / σ̂², G^μ_k = Σ_t F_kt / σ̂², and predictive adds
tr((P^μ_k − (Λ^μ_k + J^μ_kc)⁻¹) G^μ_k) (delta method), params ½ log det(I + P^μ_k J^μ_kc); block-diagonal and linear in
the centre. τ_μ = 1 / (r · extent)², r = ``geometry_prior_scale``. Its cost and verdict (off by default) are in
``docs/studies.md``.

``condition`` (``batch=greedy_conditioned``) adds the picked view's J exactly (rank-one downdate of P; Λ^μ += J^μ and
its 3×3 Cholesky redone for the Gaussians it moves), so a re-score equals recomputing the posterior with the view among
the training views; ``conditioned_ratio`` gives every remaining candidate's exact conditioned score over its first
score (scoring is a few products per visible Gaussian).
"""
from __future__ import annotations

import math
import time
import zlib
from dataclasses import dataclass
from typing import Any, Optional, Sequence

import torch
from torch import Tensor

from b3dgs.acquisition import AcquisitionPolicy, Selection, composed, top_k
from b3dgs.errors import B3dgsError
from b3dgs.fisher import FisherAccumulator
from b3dgs.numerics import guard_fill, safe_cholesky

OBJECTIVES = ("predictive", "params")
TARGETS = ("pool", "pool+train")
CHANNELS = 3
GEOMETRY_SALT = 424242  # the probes of view v are drawn from seed · 1000003 + salt + crc32(v's name)


@dataclass
class _GeoView:
    """One view's centre information per Gaussian it moves: rows ``idx`` and J = F_kv / σ̂² (n, 3, 3), float64."""

    idx: Tensor  # (n,) long
    J: Tensor  # (n, 3, 3) float64


def _inverse(lam: Tensor) -> tuple[Tensor, Tensor]:
    """(Λ⁻¹, log det Λ) of a batch of 3×3 precisions, by Cholesky."""
    L = safe_cholesky(lam)
    return torch.cholesky_inverse(L), 2 * L.diagonal(dim1=-2, dim2=-1).log().sum(-1)


@dataclass
class InfoGainPolicy(AcquisitionPolicy):
    """Closed-form information of a view for the SH colour posterior (module docstring): ``objective`` predictive
    (target-aware, EPIG-like; the default) or params (parameter gain, BALD/FisherRF-like); ``targets`` pool or
    pool+train; ``posterior``: the SH posterior block (``defaults: [/posterior@posterior: sh]``; its settings by name,
    ``posterior: {sh: {prior_precision: 2.0}}``); ``geometry``: add the centres' term (``geometry_probes`` Hutchinson
    probes per view, prior std ``geometry_prior_scale`` × extent)."""

    family: str = "niw"  # the phase-1 model it scores with (the SH posterior needs no NIW: family=standard works too)
    objective: str = "predictive"  # predictive | params
    targets: str = "pool"  # pool | pool+train: the poses whose predictive variance counts (predictive only)
    posterior: Any = None  # the SH block, composed by the YAML (defaults: [/posterior@posterior: sh])
    geometry: bool = False  # also the centres' term (the fisher3 3x3 information; info_gain_geometry.yaml)
    geometry_probes: int = 4  # Hutchinson probes per view for the centres' Fisher (one renderer backward each)
    geometry_prior_scale: float = 0.1  # the centres' prior std / the scene extent: tau_mu = 1 / (r extent)^2

    def validate(self, **kwargs) -> None:
        super().validate(**kwargs)
        if self.objective not in OBJECTIVES:
            raise B3dgsError(f"acquisition info_gain: objective={self.objective!r} is not one of {'|'.join(OBJECTIVES)}",
                             "pass acquisition.objective=predictive (or params)")
        if self.targets not in TARGETS:
            raise B3dgsError(f"acquisition info_gain: targets={self.targets!r} is not one of {'|'.join(TARGETS)}",
                             "pass acquisition.targets=pool (or pool+train)")
        blk = self.block()
        if not callable(getattr(blk, "view_information", None)):
            raise B3dgsError(f"acquisition info_gain: posterior is {type(blk).__name__}, not the SH posterior block",
                             "compose it with defaults: [/posterior@posterior: sh]")
        blk.validate()
        if not isinstance(self.geometry, bool):
            raise B3dgsError(f"acquisition info_gain: geometry={self.geometry!r} must be true or false",
                             "pass acquisition.geometry=true (or false)")
        k = self.geometry_probes
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise B3dgsError(f"acquisition info_gain: geometry_probes={k!r} must be an integer >= 1",
                             "pass acquisition.geometry_probes=4")
        r = self.geometry_prior_scale
        if isinstance(r, bool) or not isinstance(r, (int, float)) or not (math.isfinite(r) and r > 0):
            raise B3dgsError(f"acquisition info_gain: geometry_prior_scale={r!r} must be a finite number > 0",
                             "pass acquisition.geometry_prior_scale=0.1 (the centres' prior std / the scene extent)")

    def block(self):
        """The SH posterior block this policy scores with (one instance for the policy's life)."""
        self.posterior = composed(self, "posterior", "posterior")
        return self.posterior

    # ---------------------------------------------------------------- the centres' information (geometry=true)
    def view_fisher(self, ctx, camera) -> Tensor:
        """(N, 3, 3) F_kv = Σ_p Σ_c ∇_μk C_pc ∇_μk C_pcᵀ of one view at the scoring resolution, float64 on the splats'
        device: :class:`FisherAccumulator`'s Hutchinson estimate (``geometry_probes`` ±1 probes, one backward each),
        its probes drawn on the CPU from the context's seed and the view's name, so a view's F does not depend on
        the order the views are scored in (and conditioning on it equals training on it)."""
        p = ctx.params()
        p["means"].requires_grad_(True)
        acc = FisherAccumulator(int(self.geometry_probes))
        seed = (ctx.seed * 1000003 + GEOMETRY_SALT + zlib.crc32(camera.name.encode())) % (2 ** 63)
        acc.start(params=p, sh_degree=ctx.sh_degree(), seed=seed)
        with torch.enable_grad():
            ro = ctx.render(camera, params=p, grad=True)
            acc.add(camera=camera, render=ro, params=p, sh_degree=ctx.sh_degree())
        return acc.result()["fisher"]

    def _geo_view(self, ctx, camera, sigma2: float) -> _GeoView:
        F = self.view_fisher(ctx, camera).double()
        F = guard_fill("info_gain.geometry_nonfinite", ~torch.isfinite(F).all(-1).all(-1)[:, None, None], F, 0.0)
        F = 0.5 * (F + F.transpose(-1, -2))
        idx = torch.nonzero(F.diagonal(dim1=-2, dim2=-1).sum(-1) > 0).squeeze(-1)
        return _GeoView(idx, F[idx] / sigma2)

    def _geometry(self, ctx, candidates, train_views: Sequence, sigma2: float, N: int, device) -> dict:
        """Centre precision Λ^μ = τ_μ I + Σ_train J^μ (τ_μ = 1 / (geometry_prior_scale · extent)²), its inverse and
        log-determinant, every candidate's J^μ and the targets' G^μ."""
        ext = float(ctx.extent)
        if not (math.isfinite(ext) and ext > 0):
            raise B3dgsError(f"acquisition info_gain: the scene extent is {ext!r}, so the centres' prior is undefined",
                             "score with a ScoringContext whose extent is the scene's (a finite number > 0)")
        tau = 1.0 / (float(self.geometry_prior_scale) * ext) ** 2
        eye = torch.eye(3, dtype=torch.float64, device=device)
        lam = tau * eye.expand(N, 3, 3).clone()
        train = [self._geo_view(ctx, c, sigma2) for c in train_views]
        for v in train:
            lam.index_add_(0, v.idx, v.J)
        views = {c.name: self._geo_view(ctx, c, sigma2) for c in candidates}
        G = None
        if self.objective == "predictive":
            G = torch.zeros(N, 3, 3, dtype=torch.float64, device=device)
            for v in list(views.values()) + (train if self.targets == "pool+train" else []):
                G.index_add_(0, v.idx, v.J)
        P, logdet = _inverse(lam)
        return {"lam": lam, "P": P, "logdet": logdet, "G": G, "views": views, "saved": None, "tau": tau}

    def _geo_gain(self, geo: dict, v: _GeoView) -> float:
        """Predictive tr((P^μ − (Λ^μ + J^μ)⁻¹) G^μ) or params ½ log det(I + P^μ J^μ) over the view's Gaussians."""
        if v.idx.numel() == 0:
            return 0.0
        L = safe_cholesky(geo["lam"][v.idx] + v.J)
        if self.objective == "params":
            return 0.5 * float((2 * L.diagonal(dim1=-2, dim2=-1).log().sum(-1) - geo["logdet"][v.idx]).sum())
        D = geo["P"][v.idx] - torch.cholesky_inverse(L)
        return float((D * geo["G"][v.idx].transpose(-1, -2)).sum())

    @torch.no_grad()
    def prepare(self, ctx, candidates: Sequence) -> dict:
        """The SH posterior of the current training views (the block's, fitted by the context) and every candidate's
        (and target's) information, cached for this scoring context and candidate list."""
        key = (id(ctx), tuple(c.name for c in candidates))
        st = getattr(self, "_state", None)
        if st is not None and st["key"] == key:
            return st
        t0 = time.perf_counter()
        blk = self.block()
        post = ctx.fit_posterior(blk)  # Λ and σ̂² of the training views at the scoring resolution (one pass)
        blk.covariance(post)
        means = ctx.params()["means"].detach().double()

        def info(c):
            return blk.view_information(state=post, camera=c, render=ctx.render(c, return_weights=True), means=means)

        views = {c.name: info(c) for c in candidates}
        G = None
        if self.objective == "predictive":
            G = torch.zeros_like(post["lam"])
            for v in list(views.values()) + ([info(c) for c in ctx.train] if self.targets == "pool+train" else []):
                v.add_to(G)
        s2 = float(post["sigma2"])
        geo = self._geometry(ctx, candidates, ctx.train, s2, means.shape[0], means.device) if self.geometry else None
        self._state = {"key": key, "post": post, "fitted": post, "G": G, "views": views, "means": means,
                       "deg": ctx.sh_degree(), "sigma2": s2, "first": None, "geo": geo,
                       "setup_s": time.perf_counter() - t0}
        return self._state

    # ---------------------------------------------------------------- scores
    def sh_gains(self, st: dict, v) -> Tensor:
        """The SH term of view ``v``'s score per Gaussian it sees (float64, under the current conditioning): 3 · ½
        log(1 + s q) (params) or 3 s uᵀG u / (1 + s q) (predictive), u = P y, q = yᵀu; the score's SH term is their
        sum (b3dgs-suggest spreads them over the pixels)."""
        t = self._sh_terms(st, v)
        return CHANNELS * 0.5 * t if self.objective == "params" else CHANNELS * t

    def _sh_terms(self, st: dict, v) -> Tensor:
        P = self.posterior.covariance(st["post"])[v.idx]
        u = torch.einsum("nij,nj->ni", P, v.y)
        q = (u * v.y).sum(-1)
        if self.objective == "params":
            return torch.log1p(v.s * q)
        Gu = torch.einsum("nij,nj->ni", st["G"][v.idx], u)
        return v.s * (u * Gu).sum(-1) / (1.0 + v.s * q)

    def _sh_gain(self, st: dict, v) -> float:
        if v.idx.numel() == 0:
            return 0.0
        t = self._sh_terms(st, v)
        return CHANNELS * 0.5 * float(t.sum()) if self.objective == "params" else CHANNELS * float(t.sum())

    @torch.no_grad()
    def score(self, ctx, candidates) -> Tensor:
        return self.score_at(ctx, candidates, range(len(candidates)))

    @torch.no_grad()
    def score_at(self, ctx, candidates, positions) -> Tensor:
        st = self.prepare(ctx, candidates)
        names = [candidates[i].name for i in positions]
        geo = st["geo"]
        out = torch.tensor([self._sh_gain(st, st["views"][n])
                            + (0.0 if geo is None else self._geo_gain(geo, geo["views"][n])) for n in names],
                           dtype=torch.float64)
        if st["post"] is st["fitted"] and st["first"] is None and len(out) == len(candidates):
            st["first"] = out.clone()  # the unconditioned scores, for conditioned_ratio
        return out

    def select(self, ctx, candidates, budget) -> Selection:
        t0 = time.perf_counter()
        scores = self.score(ctx, candidates)
        st = self._state
        return Selection(top_k(scores, budget), [float(v) for v in scores],
                         {"scoring_s": time.perf_counter() - t0, "setup_s": st["setup_s"], "sigma2": st["sigma2"],
                          "sh_degree": st["deg"], "geometry": self.geometry})

    # ---------------------------------------------------------------- batch conditioning (greedy_conditioned)
    @torch.no_grad()
    def condition(self, ctx, camera) -> bool:
        """The SH block's exact conditioning on the view (rank-one per Gaussian it sees); with ``geometry`` also
        Λ^μ ← Λ^μ + J^μ_camera and P^μ, log det Λ^μ recomputed for the Gaussians it moves."""
        st = getattr(self, "_state", None)
        if st is None or st["key"][0] != id(ctx):
            raise B3dgsError("acquisition info_gain: condition() before any score() in this scoring context",
                             "score the candidates first (the batch selectors do)")
        geo = st["geo"]
        if geo is not None:
            g = geo["views"].get(camera.name) or self._geo_view(ctx, camera, st["sigma2"])
            if g.idx.numel():
                if geo["saved"] is None:
                    geo["saved"] = {k: geo[k].clone() for k in ("lam", "P", "logdet")}
                lam = geo["lam"][g.idx] + g.J
                geo["lam"][g.idx], (geo["P"][g.idx], geo["logdet"][g.idx]) = lam, _inverse(lam)
        blk, post = self.posterior, st["post"]
        v = st["views"].get(camera.name) or blk.view_information(
            state=post, camera=camera, render=ctx.render(camera, return_weights=True), means=st["means"])
        st["post"] = blk.condition(post, v)
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
        if st is not None:
            st["post"] = st["fitted"]
        geo = None if st is None else st["geo"]
        if geo is not None and geo["saved"] is not None:
            geo.update(geo["saved"])
            geo["saved"] = None
