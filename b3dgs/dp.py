"""Truncated stick-breaking DP posterior (Eq. 5; Blei & Jordan 2006) and the activity gate.

Mean-field q(v_k) = Beta(gamma_k1, gamma_k2) for components in stick order k = 1..K, given
expected usage counts N_k (the renderer's compositing weight mass sum_p w_kp, supplied by the
caller). Truncation convention (Blei & Jordan 2006, Sec. 3): q(v_K = 1) = 1, so the last
component takes all remaining stick and E[pi] sums to exactly 1. ``cavi_stick_update`` still
returns the untruncated Beta(1 + N_K, alpha) for the last entry (finite, alpha > 0); the
``truncate_last`` flag of ``expected_log_pi``/``expected_pi`` applies the convention.

Pure batched functions (tested against textbook formulas in tests/test_posterior_math.py), shared by the DP
posterior block (``plugins/posterior/dp.py``) and the DP pruning scores (:class:`b3dgs.compression.DPPruningScore`).
"""
from __future__ import annotations

import math
from typing import Dict, Optional, Tuple, Union

import torch

from b3dgs.errors import B3dgsError, check_field
from b3dgs.numerics import guard_fill, vector, zero_invalid


#: Relative floor on the usage share in activity_posterior (share + eps / K).
ACTIVITY_SHARE_EPS = 1e-6
_MAX_LOGIT = 80.0


def _vec(name: str, x: torch.Tensor) -> torch.Tensor:
    v = vector(name, x)
    if v.numel() == 0:
        raise B3dgsError(f"{name}: K must be >= 1",
                         fix=f"pass {name} with at least one entry (one per Gaussian; K >= 1)")
    return v


def _check_alpha(alpha: Union[float, torch.Tensor]) -> float:
    a = float(alpha)
    if not (math.isfinite(a) and a > 0):
        raise B3dgsError(f"alpha must be finite and > 0, got {alpha}",
                         fix="pass alpha > 0 and finite (posterior.dp.alpha)")
    return a


def _clean_counts(counts: torch.Tensor, where: str) -> torch.Tensor:
    return zero_invalid(f"{where}.invalid_count", _vec("counts", counts))


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
                         fix="pass temperature > 0 (posterior.dp.gate_temperature)")
    if not (0.0 <= evidence_weight <= 1.0):
        raise B3dgsError(f"evidence_weight must be in [0, 1], got {evidence_weight}",
                         fix="pass evidence_weight in [0, 1] (0 keeps the prior, 1 uses the usage evidence alone)")
    if not (eps > 0):
        raise B3dgsError("eps must be > 0", fix="pass eps > 0, e.g. the default")
    tau = prune_threshold(K) if threshold is None else float(threshold)
    if not (tau > 0):
        raise B3dgsError(f"threshold must be > 0, got {threshold}",
                         fix="pass threshold > 0, or threshold=None for prune_threshold(K)")
    u = zero_invalid("activity_posterior.invalid_usage", u)
    elp = guard_fill("activity_posterior.nan_expected_log_pi", torch.isnan(elp), elp, math.log(tau))
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


@torch.no_grad()
def dp_cavi(state: dict, alpha: float, prior_active: float, prune_pi: float, gate_temperature: float) -> None:
    """One CAVI pass (Eq. 5) and activity gate on ``state["usage"]``: sets ``g1``, ``g2``, ``e_pi``, ``e_a`` (in the
    usage's order) in ``state``. Used by the DP block and the DP pruning scores."""
    counts = state["usage"]
    perm, inv = stick_order(counts)
    g1, g2 = cavi_stick_update(counts[perm], alpha)
    elog = expected_log_pi(g1, g2)
    e_pi = expected_pi(g1, g2)
    prior_logit = float(torch.logit(torch.tensor(prior_active)))
    tau = prune_threshold(counts.numel(), prune_pi)
    e_a = activity_posterior(elog, counts[perm], prior_logit, gate_temperature, threshold=tau)
    state["g1"], state["g2"] = g1[inv], g2[inv]
    state["e_pi"], state["e_a"] = e_pi[inv], e_a[inv]


def check_dp_prior(owner) -> None:
    """The DP prior's settings of the dataclass ``owner`` (``alpha`` > 0, ``prior_active`` in (0, 1)), refused in one
    line as ``posterior.dp``'s: the DP block's and the DP pruning scores' one check."""
    check_field(owner, "posterior.dp.alpha", not owner.alpha <= 0, "> 0")
    check_field(owner, "posterior.dp.prior_active", 0 < owner.prior_active < 1, "in (0, 1)", "strictly between 0 and 1")
