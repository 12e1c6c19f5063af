"""Pruning scores for the compression ladder: the base class and the per-Gaussian measurements they share.

A pruning score is a plugin like any other: ``plugins/pruning/<name>.py`` (one dataclass deriving from
:class:`PruningScore`) and ``conf/pruning/<name>.yaml``. It is called with the one hook signature
``score(splats=, optimizers=, state=, step=, info=)`` and returns an (N,) tensor where higher means keep:

- ``splats``: the model's parameters (read only); ``optimizers``: None (scores never step);
- ``state``: the score's own dict, kept for the rounds of one ladder rung (e.g. a fitted posterior);
- ``step``: the prune round (0-based);
- ``info``: ``ctx`` (a :class:`b3dgs.acquisition.ScoringContext` over the training views at the scoring
  resolution), ``generator`` (seeded per scene, seed and round), ``cache`` (a dict shared by every score of
  the same model state, so two scores that need the same measurement, e.g. the DP usage counts, pay once).

The core keeps the top-K of the score (ties by index) and never branches on a score's type or name.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from b3dgs.dp import check_dp_prior, dp_cavi
from b3dgs.errors import B3dgsError
from b3dgs.fisher import pixel_set_grads
from b3dgs.plugin import Plugin


@dataclass
class PruningScore(Plugin):
    """Ranks Gaussians for retention (higher = keep).

    ``rounds``: prune-refine rounds for one keep ratio (the per-round keep factor is keep^(1/rounds); the
    score is recomputed on the fine-tuned model before every round). Scores see training views only
    (``ctx.train``), never test views.
    """

    rounds: int = 1

    def validate(self, **kwargs: Any) -> None:
        if int(self.rounds) < 1:
            raise B3dgsError(f"pruning {type(self).__name__}.rounds must be >= 1, got {self.rounds}",
                             fix="pass pruning.rounds >= 1 (the pruned model is fine-tuned after each round; most "
                                 "conf/pruning files use 2)")

    def score(self, *, splats, optimizers, state, step, info) -> Tensor:
        raise NotImplementedError  # protocol: an abstract method (subclasses implement it)


def keep_top(score: Tensor, keep: int) -> Tensor:
    """(N,) bool mask of the ``keep`` highest scores; ties go to the lower index (stable sort), NaN ranks last."""
    if score.dim() != 1:
        raise B3dgsError(f"a pruning score must be (N,), got {tuple(score.shape)}",
                         fix="return one score per Gaussian from PruningScore.score, a 1-D tensor of shape (N,)")
    n = score.numel()
    keep = max(0, min(int(keep), n))
    s = torch.nan_to_num(score.detach().double(), nan=-float("inf"))
    order = torch.sort(-s, stable=True).indices
    mask = torch.zeros(n, dtype=torch.bool, device=score.device)
    mask[order[:keep]] = True
    return mask


def cached(info: dict, key: str, fn):
    """``fn()`` computed once per model state: kept in ``info["cache"]`` under ``key``."""
    cache = info.setdefault("cache", {})
    if key not in cache:
        cache[key] = fn()
    return cache[key]


def view_sum(info: dict, key: str, per_view) -> Tensor:
    """Σ over the training views of ``per_view(ctx, camera)``, in view order, once per model state (:func:`cached`)."""
    ctx = info["ctx"]

    def run():
        total = None
        for cam in ctx.train:
            x = per_view(ctx, cam)
            total = x if total is None else total + x
        return total

    return cached(info, key, run)


@torch.no_grad()
def usage_counts(info: dict) -> Tensor:
    """(N,) float64 expected pixel responsibilities Σ_v Σ_p w_kp over the training views (the DP block's usage
    counts at a fixed model state: the limit of its per-step EMA × number of views)."""
    return view_sum(info, "usage_counts",
                    lambda ctx, cam: ctx.render(cam, return_weights=True).weight_sum.reshape(-1).double())


@dataclass
class DPPruningScore(PruningScore):
    """Base of the scores read from the DP posterior (paper Eq. 5) fitted by CAVI (:func:`b3dgs.dp.dp_cavi`) to the
    model's usage counts on the fixed structure (:func:`usage_counts`). The DP settings mirror
    ``conf/posterior/dp.yaml``; the fit is shared through the cache by every score with the same settings."""

    rounds: int = 2
    alpha: float = 5.0
    prior_active: float = 0.5
    prune_pi: float = 0.05
    gate_temperature: float = 1.0

    def validate(self, **kwargs) -> None:
        super().validate(**kwargs)
        check_dp_prior(self)

    def fit(self, info) -> dict:
        """{usage, g1, g2, e_pi, e_a} of the DP posterior at the current model state (cached per state)."""
        def fit():
            state = {"usage": usage_counts(info).clone()}
            dp_cavi(state, self.alpha, self.prior_active, self.prune_pi, self.gate_temperature)
            return state

        return cached(info, f"dp_fit_{self.alpha}_{self.prior_active}_{self.prune_pi}_{self.gate_temperature}", fit)


def position_grad_norm(info: dict) -> Tensor:
    """(N,) Σ_v ‖∂ MSE_v / ∂μ_k‖ over the training views (the paper's 'gradient' compression baseline)."""
    def grad_norm(ctx, cam):
        p = ctx.params(requires_grad=False)
        p["means"].requires_grad_(True)
        rgb = ctx.render(cam, params=p, grad=True).rgb
        loss = (rgb - cam.image.to(rgb.device)).square().mean()
        (g,) = torch.autograd.grad(loss, [p["means"]])
        return g.double().norm(dim=-1)

    return view_sum(info, "position_grad_norm", grad_norm)


def spatial_fisher(info: dict, stride: int, per_channel: bool = True) -> Tensor:
    """(N, 6, 6) float64 Fisher blocks Σ_v Σ_p (Σ_c) ∇I ∇Iᵀ over each Gaussian's mean and log-scale (the PUP
    sensitivity, Hanson et al. 2025), from :func:`b3dgs.fisher.pixel_set_grads` per view."""
    def fisher(ctx, cam):
        p = ctx.params(requires_grad=False)
        leaves = [p["means"].requires_grad_(True), p["scales"].requires_grad_(True)]
        rgb = ctx.render(cam, params=p, grad=True).rgb
        acc = torch.zeros(leaves[0].shape[0], 6, 6, dtype=torch.float64, device=rgb.device)
        for gm, gs in pixel_set_grads(rgb, leaves, stride, per_channel=per_channel):
            g = torch.cat([gm, gs], dim=-1).double()
            acc += g.unsqueeze(-1) * g.unsqueeze(-2)
        return acc

    return view_sum(info, f"spatial_fisher_s{int(stride)}_c{int(per_channel)}", fisher)
