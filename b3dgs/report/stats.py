"""Statistics of the report: paired scene-level analysis (scipy), seed/scene means, Pareto fronts,
time to a fraction of the final PSNR gain."""
from __future__ import annotations

import math
import warnings
from typing import Optional, Sequence

import numpy as np
from scipy import stats

__all__ = ["paired_stats", "bootstrap_ci", "sign_flip_p", "p_floor", "mean_sem", "pareto_front", "time_to_fraction"]


def p_floor(n: int) -> Optional[float]:
    """The smallest two-sided p an exact sign-flip test over ``n`` units can give: 2 / 2**n."""
    return min(1.0, 2.0 / 2.0 ** n) if n >= 1 else None


def sign_flip_p(deltas: Sequence[float], alternative: str = "two-sided") -> Optional[float]:
    """Exact sign-flip permutation p-value of the mean of ``deltas`` (all 2**n sign patterns); None for n < 2."""
    d = np.asarray(deltas, dtype=float)
    if d.size < 2:
        return None
    res = stats.permutation_test((d,), np.mean, permutation_type="samples", n_resamples=np.inf,
                                 alternative=alternative)
    return float(res.pvalue)


def bootstrap_ci(deltas: Sequence[float], confidence: float = 0.95, n_resamples: int = 9999,
                 bca_min_n: int = 6, seed: int = 0) -> dict:
    """Bootstrap CI of the mean (resampling the given units, i.e. scenes: a cluster bootstrap).

    BCa when there are at least ``bca_min_n`` units and BCa is defined, else the percentile method;
    ``method`` and ``reason`` say which was used and why.
    """
    d = np.asarray(deltas, dtype=float)
    if d.size < 2:
        return {"low": None, "high": None, "method": None, "reason": f"{d.size} unit(s): no bootstrap CI"}
    if np.ptp(d) == 0:
        return {"low": float(d[0]), "high": float(d[0]), "method": "degenerate",
                "reason": "all differences equal: the CI is that value"}

    def run(method: str):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # DegenerateDataWarning: reported through ``reason`` instead
            return stats.bootstrap((d,), np.mean, confidence_level=confidence, n_resamples=n_resamples,
                                   method=method, rng=np.random.default_rng(seed)).confidence_interval

    reason = None
    if d.size >= bca_min_n:
        ci = run("BCa")
        if np.isfinite([ci.low, ci.high]).all():
            return {"low": float(ci.low), "high": float(ci.high), "method": "BCa", "reason": None}
        reason = "BCa undefined for these data"
    else:
        reason = f"{d.size} units < {bca_min_n}: too few for BCa"
    ci = run("percentile")
    return {"low": float(ci.low), "high": float(ci.high), "method": "percentile", "reason": reason}


def paired_stats(deltas: Sequence[float], higher_is_better: bool = True, confidence: float = 0.95,
                 n_resamples: int = 9999, bca_min_n: int = 6, seed: int = 0) -> dict:
    """Mean difference over units (scenes), its bootstrap CI, exact sign-flip p-values (two-sided and
    one-sided in the favourable direction), wins/losses/ties and the p floor 2/2**n."""
    d = np.asarray(deltas, dtype=float)
    n = int(d.size)
    good = d > 0 if higher_is_better else d < 0
    bad = d < 0 if higher_is_better else d > 0
    return {"n": n, "mean": float(d.mean()) if n else None,
            "ci": bootstrap_ci(d, confidence, n_resamples, bca_min_n, seed), "confidence": confidence,
            "p_two_sided": sign_flip_p(d, "two-sided"),
            "p_one_sided": sign_flip_p(d, "greater" if higher_is_better else "less"), "p_floor": p_floor(n),
            "wins": int(good.sum()), "losses": int(bad.sum()), "ties": int(n - good.sum() - bad.sum())}


def mean_sem(values: Sequence[float]) -> tuple[Optional[float], Optional[float]]:
    """Mean and standard error of the mean (None for the SEM of fewer than two values)."""
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], dtype=float)
    if v.size == 0:
        return None, None
    return float(v.mean()), (float(stats.sem(v)) if v.size > 1 else None)


def pareto_front(cost: Sequence[float], value: Sequence[float]) -> list[int]:
    """Indices of the points not dominated (lower ``cost`` and higher ``value`` are better), by cost."""
    pts = list(zip(cost, value))
    front = [i for i, (c, v) in enumerate(pts)
             if not any((c2 <= c and v2 >= v) and (c2 < c or v2 > v) for c2, v2 in pts)]
    return sorted(front, key=lambda i: pts[i][0])


def time_to_fraction(points: Sequence[dict], fraction: float, key: str = "psnr") -> Optional[float]:
    """Training seconds at which ``key`` first reaches ``first + fraction * (final - first)`` along a curve
    (``curve.json`` points), linearly interpolated between the two logged points around the crossing.
    None without a positive gain."""
    if len(points) < 2:
        return None
    t = [float(p["train_time_s"]) for p in points]
    y = [float(p[key]) for p in points]
    gain = y[-1] - y[0]
    if not gain > 0:
        return None
    target = y[0] + fraction * gain
    for i in range(1, len(y)):
        if y[i] >= target:
            w = (target - y[i - 1]) / (y[i] - y[i - 1]) if y[i] != y[i - 1] else 1.0
            return t[i - 1] + w * (t[i] - t[i - 1])
    return t[-1]
