"""Truncated Dirichlet-process stick-breaking prior with CAVI and activity gates (paper Eq. 5).

The block (:class:`DPBlock`) follows its math, the pure batched functions below
(tested against textbook formulas in tests/test_posterior_math.py):

Truncated stick-breaking DP posterior (Eq. 5; Blei & Jordan 2006) and the activity gate.

Mean-field q(v_k) = Beta(gamma_k1, gamma_k2) for components in stick order k = 1..K, given
expected usage counts N_k (the renderer's compositing weight mass sum_p w_kp, supplied by the
caller). Truncation convention (Blei & Jordan 2006, Sec. 3): q(v_K = 1) = 1, so the last
component takes all remaining stick and E[pi] sums to exactly 1. ``cavi_stick_update`` still
returns the untruncated Beta(1 + N_K, alpha) for the last entry (finite, alpha > 0); the
``truncate_last`` flag of ``expected_log_pi``/``expected_pi`` applies the convention.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Dict, Optional, Tuple, Union

import torch

from b3dgs.device import bernoulli
from b3dgs.errors import B3dgsError, check_field, field_default
from b3dgs.numerics import guard
from b3dgs.plugin import PosteriorBlock


_F64 = torch.float64
#: Relative floor on the usage share in activity_posterior (share + eps / K).
ACTIVITY_SHARE_EPS = 1e-6
_MAX_LOGIT = 80.0


def _vec(name: str, x: torch.Tensor) -> torch.Tensor:
    if not isinstance(x, torch.Tensor) or x.ndim != 1:
        raise B3dgsError(f"{name}: expected a 1-D (K,) tensor, got {getattr(x, 'shape', type(x).__name__)}",
                         fix=f"pass {name} as a 1-D torch tensor with one entry per Gaussian, shape (K,)")
    if x.numel() == 0:
        raise B3dgsError(f"{name}: K must be >= 1",
                         fix=f"pass {name} with at least one entry (one per Gaussian; K >= 1)")
    return x.to(_F64)


def _check_alpha(alpha: Union[float, torch.Tensor]) -> float:
    a = float(alpha)
    if not (math.isfinite(a) and a > 0):
        raise B3dgsError(f"alpha must be finite and > 0, got {alpha}",
                         fix="pass alpha > 0 and finite "
                             f"(posterior.dp.alpha, default {field_default(DPBlock, 'alpha')})")
    return a


def _clean_counts(counts: torch.Tensor, where: str) -> torch.Tensor:
    N = _vec("counts", counts)
    bad = ~torch.isfinite(N) | (N < 0)
    if guard(f"{where}.invalid_count", bad):
        N = torch.where(bad, torch.zeros_like(N), N)
    return N


def cavi_stick_update(counts: torch.Tensor, alpha: Union[float, torch.Tensor]) -> Tuple[torch.Tensor, torch.Tensor]:
    """CAVI update of q(v_k) = Beta(gamma1, gamma2) (Eq. 5; Blei & Jordan 2006, Eq. 18-19).

    gamma1_k = 1 + N_k, gamma2_k = alpha + sum_{j>k} N_j, in the given order (use
    ``stick_order`` first). The tail sum is a reverse cumulative sum in float64 without
    subtraction (deterministic). Negative/non-finite counts are set to 0 (guarded).
    """
    a = _check_alpha(alpha)
    N = _clean_counts(counts, "cavi_stick_update")
    incl = torch.flip(torch.cumsum(torch.flip(N, (0,)), 0), (0,))  # sum_{j>=k}
    tail = torch.cat([incl[1:], incl.new_zeros(1)])  # sum_{j>k}
    return 1.0 + N, a + tail


def _check_gammas(gamma1: torch.Tensor, gamma2: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    g1, g2 = _vec("gamma1", gamma1), _vec("gamma2", gamma2)
    if g1.shape != g2.shape:
        raise B3dgsError(f"gamma1 {tuple(g1.shape)} and gamma2 {tuple(g2.shape)} differ",
                         fix="pass gamma1 and gamma2 with one entry each per Gaussian, the same shape (K,)")
    if not bool((torch.isfinite(g1) & (g1 > 0) & torch.isfinite(g2) & (g2 > 0)).all()):
        raise B3dgsError("Beta parameters gamma1, gamma2 must be finite and > 0",
                         fix="pass Beta parameters > 0 and finite (as cavi_stick_update returns them)")
    return g1, g2


def _exclusive_cumsum(x: torch.Tensor) -> torch.Tensor:
    return torch.cat([x.new_zeros(1), torch.cumsum(x, 0)[:-1]])


def expected_log_pi(gamma1: torch.Tensor, gamma2: torch.Tensor, truncate_last: bool = True) -> torch.Tensor:
    """E_q[log pi_k] = E[log v_k] + sum_{l<k} E[log(1 - v_l)] via digamma (Eq. 5), float64 (K,)."""
    g1, g2 = _check_gammas(gamma1, gamma2)
    dsum = torch.special.digamma(g1 + g2)
    e_log_v = torch.special.digamma(g1) - dsum
    e_log_1mv = torch.special.digamma(g2) - dsum
    if truncate_last:
        e_log_v = e_log_v.clone()
        e_log_v[-1] = 0.0
    return e_log_v + _exclusive_cumsum(e_log_1mv)


def expected_pi(gamma1: torch.Tensor, gamma2: torch.Tensor, truncate_last: bool = True) -> torch.Tensor:
    """E_q[pi_k] = E[v_k] prod_{l<k} E[1 - v_l] (exact under the mean field), in log space, (K,).

    Sums to 1 with ``truncate_last`` (q(v_K = 1) = 1) and to < 1 otherwise.
    """
    g1, g2 = _check_gammas(gamma1, gamma2)
    lsum = torch.log(g1 + g2)
    log_ev = torch.log(g1) - lsum
    log_e1mv = torch.log(g2) - lsum
    if truncate_last:
        log_ev = log_ev.clone()
        log_ev[-1] = 0.0
    return torch.exp(log_ev + _exclusive_cumsum(log_e1mv))


def stick_order(counts: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Stick-breaking order: decreasing expected usage, ties broken by increasing index.

    Returns (perm, inv_perm): ``counts[perm]`` is sorted and ``x_sorted[inv_perm]`` restores
    the original order. Non-finite/negative counts are treated as 0 (guarded).
    """
    N = _clean_counts(counts, "stick_order")
    perm = torch.argsort(N, descending=True, stable=True)
    inv = torch.empty_like(perm)
    inv[perm] = torch.arange(perm.numel(), device=perm.device)
    return perm, inv


def dp_posterior(
    counts: torch.Tensor, alpha: Union[float, torch.Tensor], truncate_last: bool = True
) -> Dict[str, torch.Tensor]:
    """Convenience: order by usage, CAVI (Eq. 5), and return everything in the ORIGINAL order.

    Keys: gamma1, gamma2, expected_log_pi, expected_pi (K,) float64, perm, inv_perm.
    """
    perm, inv = stick_order(counts)
    N = _clean_counts(counts, "dp_posterior")
    g1, g2 = cavi_stick_update(N[perm], alpha)
    elog = expected_log_pi(g1, g2, truncate_last)
    epi = expected_pi(g1, g2, truncate_last)
    return {"gamma1": g1[inv], "gamma2": g2[inv], "expected_log_pi": elog[inv], "expected_pi": epi[inv], "perm": perm,
            "inv_perm": inv}


def prune_threshold(K: int, base: float = 0.01) -> float:
    """Threshold on E[pi_k]: ``base / K``, i.e. a fixed fraction of the uniform share 1/K.

    E[pi] sums to ~1, so a fixed absolute threshold would prune everything as K grows;
    scaling with 1/K keeps the rule "prune components carrying < base x their fair share".
    """
    if int(K) < 1 or not (base > 0):
        raise B3dgsError(f"need K >= 1 and base > 0, got K={K}, base={base}",
                         fix="pass K >= 1 (the number of Gaussians) and base > 0 (posterior.dp.prune_pi, default "
                             "0.05)")
    return float(base) / int(K)


def activity_posterior(expected_log_pi: torch.Tensor, usage: torch.Tensor, prior_logit: float = 0.0,
                       temperature: float = 1.0, threshold: Optional[float] = None, evidence_weight: float = 0.5,
                       eps: float = ACTIVITY_SHARE_EPS, return_logit: bool = False):
    """Approximate q(a_k = 1) = E[a_k] (Table 1 "activity: approximate fast usage gate").

    Approximation: "active" means the component's weight exceeds the prune threshold tau
    (default ``prune_threshold(K)`` = 0.01/K). Its log-weight is estimated by a log-linear pool
    of the DP posterior and the observed usage,
        ell_k = (1 - lam) * E[log pi_k] + lam * log(share_k + eps/K),   share_k = u_k / sum_j u_j,
    with lam = ``evidence_weight``, and is given a logistic error of scale ``temperature``; then
    P(log pi_k > log tau) = sigmoid((ell_k - log tau)/T), and adding the prior log-odds gives
        logit_k = prior_logit + (ell_k - log tau) / T,   E[a_k] = sigmoid(logit_k).
    Usage 0 gives a finite log(eps/K); huge usage gives share <= 1; logits are clipped to
    +-80 (sigmoid is saturated there, so no guard is needed).
    """
    elp = _vec("expected_log_pi", expected_log_pi)
    u = _vec("usage", usage)
    K = elp.numel()
    if u.numel() != K:
        raise B3dgsError(f"usage has {u.numel()} entries, expected_log_pi has {K}",
                         fix="pass usage with one entry per Gaussian, the same length as expected_log_pi")
    if not (temperature > 0):
        raise B3dgsError(f"temperature must be > 0, got {temperature}",
                         fix="pass temperature > 0 "
                             f"(posterior.dp.gate_temperature, default {field_default(DPBlock, 'gate_temperature')})")
    if not (0.0 <= evidence_weight <= 1.0):
        raise B3dgsError(f"evidence_weight must be in [0, 1], got {evidence_weight}",
                         fix="pass evidence_weight in [0, 1] (0 keeps the prior, 1 uses the usage evidence alone)")
    if not (eps > 0):
        raise B3dgsError("eps must be > 0", fix="pass eps > 0, e.g. the default")
    tau = prune_threshold(K) if threshold is None else float(threshold)
    if not (tau > 0):
        raise B3dgsError(f"threshold must be > 0, got {threshold}",
                         fix="pass threshold > 0, or threshold=None for prune_threshold(K)")
    bad = ~torch.isfinite(u) | (u < 0)
    if guard("activity_posterior.invalid_usage", bad):
        u = torch.where(bad, torch.zeros_like(u), u)
    badp = torch.isnan(elp)
    if guard("activity_posterior.nan_expected_log_pi", badp):
        elp = torch.where(badp, torch.full_like(elp, math.log(tau)), elp)
    total = u.sum()
    if not bool(torch.isfinite(total)):  # overflow of a sum of huge usages: rescale first
        u = u / u.max()
        total = u.sum()
    share = u / total if float(total) > 0 else torch.zeros_like(u)
    log_share = torch.log(share + eps / K)
    ell = (1.0 - evidence_weight) * elp.clamp_min(-1e300) + evidence_weight * log_share
    logit = (prior_logit + (ell - math.log(tau)) / temperature).clamp(-_MAX_LOGIT, _MAX_LOGIT)
    ea = torch.sigmoid(logit)
    return (ea, logit) if return_logit else ea


@dataclass
class DPBlock(PosteriorBlock):
    """q(v_k) = Beta(γ_k1, γ_k2) under a truncated stick-breaking prior v_k ~ Beta(1, α) (Eq. 5),
    updated by CAVI (Blei & Jordan 2006) every ``cavi_every`` steps after ``t_dp``.

    Usage counts: an EMA over steps of each Gaussian's total compositing weight Σ_p w_kp in the
    step's view, scaled by the number of training views (expected pixel responsibilities). The EMA is a
    recurrence over every step's view: usage at a CAVI step depends on each earlier step's Σ_p w (weight
    (1 - ema)·ema^age), so the paper's block reads the renderer's pair sums on every step (the default,
    ``pair_sums_every`` = 1), although CAVI itself runs only every ``cavi_every`` steps. ``pair_sums_every`` = k > 1
    updates the EMA on every k-th step only, with decay ema^k (the same memory in steps, from 1/k of the views):
    the renderer computes the sums on 1/k of the steps (the cost DPMM adds on gsplat), and results change
    (``bench/dp_cadence.py`` measures by how much).
    Ordering for the stick-breaking: by decreasing expected usage (ties by index), re-sorted at
    every CAVI step, the usual choice that makes the truncated prior's size bias match the data.
    Gates: E[π_k] and an approximate activity posterior E[a_k] (see the functions above).
    Pruning: where E[π_k] < ``prune_pi`` / K (a fraction of the uniform share 1/K, so the rule
    scales with K) or E[a_k] < ``prune_activity``, every ``cavi_every`` steps after ``t_dp``.
    It augments, and does not replace, the strategy's densification.
    """

    per_gaussian_state: ClassVar[tuple[str, ...]] = ("usage", "g1", "g2", "e_pi", "e_a")

    alpha: float = 5.0
    cavi_every: int = 50
    t_dp: Optional[int] = None  # None: max_steps / 6
    ema: float = 0.99  # usage EMA; its window (~1/(1-ema) steps) should cover an epoch of views
    prune_pi: float = 0.05  # prune where E[pi_k] < prune_pi / K
    prune_activity: float = 0.05  # prune where E[a_k] < prune_activity
    prior_active: float = 0.5
    gate_temperature: float = 1.0
    prune: bool = True
    #: read the pair sums (Σ_p w) on every k-th step only (step % k == 0), the usage EMA then decaying by ema^k per
    #: read; 1: every step (the paper, and the runs archived; a run's protocol leaves 1 out: upgrade.RUN_DEFAULTS),
    #: e.g. ``posterior.dp.pair_sums_every=4`` (see ``bench/dp_cadence.py``)
    pair_sums_every: int = 1
    needs_weights: ClassVar[bool] = True

    def validate(self, max_steps: int = 0, **kw) -> None:
        check_field(self, "posterior.dp.alpha", not self.alpha <= 0, "> 0")
        check_field(self, "posterior.dp.cavi_every", not self.cavi_every < 1, ">= 1", "as an integer >= 1")
        if not isinstance(self.pair_sums_every, int) or self.pair_sums_every < 1:
            raise B3dgsError(f"posterior.dp.pair_sums_every={self.pair_sums_every} must be an integer >= 1",
                             fix="pass posterior.dp.pair_sums_every as an integer >= 1 (1, the default: every step)")
        check_field(self, "posterior.dp.ema", 0 <= self.ema < 1, "in [0, 1)")
        check_field(self, "posterior.dp.prior_active", 0 < self.prior_active < 1, "in (0, 1)",
                    "strictly between 0 and 1")

    def initialize_state(self, *, splats, scene, info):
        n, dev = splats["means"].shape[0], splats["means"].device
        return {"usage": torch.zeros(n, dtype=torch.float64, device=dev),
                "g1": torch.ones(n, dtype=torch.float64, device=dev),
                "g2": torch.full((n,), float(self.alpha), dtype=torch.float64, device=dev),
                "e_pi": torch.full((n,), 1.0 / max(n, 1), dtype=torch.float64, device=dev),
                "e_a": torch.ones(n, dtype=torch.float64, device=dev),
                "n_views": torch.tensor(float(len(scene.train)) if scene is not None else 1.0, device=dev)}

    @torch.no_grad()
    def step_post_backward(self, *, splats, optimizers, state, step, info):
        ws = info["per_gaussian"].get("weight_sum")
        if ws is not None and self.reads_pair_sums(step, info):
            w = ws[0].double()
            rs = info.get("resolution_scale", 1.0)
            if rs != 1.0:  # a downsampled step (schedule=dash): the weights in full-resolution pixels
                w = w / (rs * rs)
            d = self.strided_decay(self.ema, self.pair_sums_every)
            state["usage"].mul_(d).add_((1 - d) * w * self.train_views(state, info))
        if "cavi" not in self.periodic(step, info):
            return
        self.cavi(state)
        if self.prune:
            k = state["usage"].numel()
            mask = (state["e_pi"] < prune_threshold(k, self.prune_pi)) | (state["e_a"] < self.prune_activity)
            state["last_pruned"] = mask.sum()
            info["ops"].prune(mask, reason="dp")

    def reads_pair_sums(self, step: int, info: dict) -> bool:
        """Every step by default (the usage EMA is a per-step recurrence); every ``pair_sums_every``-th if set."""
        return step % self.pair_sums_every == 0

    def periodic(self, step: int, info: dict) -> tuple[str, ...]:
        """``cavi`` (and activity pruning) every ``cavi_every`` steps from ``t_dp``."""
        if step >= self.stage_start(self.t_dp, info, 6) and step % self.cavi_every == 0:
            return ("cavi",)
        return ()

    @torch.no_grad()
    def cavi(self, state) -> None:
        counts = state["usage"]
        perm, inv = stick_order(counts)
        g1, g2 = cavi_stick_update(counts[perm], self.alpha)
        elog = expected_log_pi(g1, g2)
        e_pi = expected_pi(g1, g2)
        prior_logit = float(torch.logit(torch.tensor(self.prior_active)))
        tau = prune_threshold(counts.numel(), self.prune_pi)
        e_a = activity_posterior(elog, counts[perm], prior_logit, self.gate_temperature, threshold=tau)
        state["g1"], state["g2"] = g1[inv], g2[inv]
        state["e_pi"], state["e_a"] = e_pi[inv], e_a[inv]

    @torch.no_grad()
    def sample(self, *, splats, state, n, generator, params, info):
        """Activity draws a_k ~ Bernoulli(E[a_k]); inactive Gaussians render with zero opacity."""
        out = dict(params)
        a = bernoulli(state["e_a"].float().expand(n, -1), generator)
        base = out["opacities"] if out["opacities"].dim() == 2 else out["opacities"].unsqueeze(0).expand(n, -1)
        out["opacities"] = torch.where(a > 0, base, torch.full_like(base, -30.0))
        return out

    def export(self, *, splats=None, state):
        return {"dp_e_pi": state["e_pi"].float(), "dp_e_a": state["e_a"].float()}

    def summary(self, *, state):
        return {"alpha": self.alpha, "expected_active": float(state["e_a"].sum()),
                "usage_total": float(state["usage"].sum())}
