"""Numerical robustness of b3dgs_plugins.posterior at extreme counts, scales, opacities and alphas."""

import logging

import pytest
import torch

from b3dgs.numerics import guard, guard_counts, reset_guards
from b3dgs_plugins.posterior import (
    activity_posterior,
    cavi_stick_update,
    color_posterior_var,
    dp_posterior,
    expected_cov,
    expected_log_pi,
    expected_pi,
    ig_mean,
    ig_sample,
    ig_update,
    mean_variance,
    niw_batch_stats,
    niw_update,
    opacity_beta_moment_match,
    opacity_fisher_var,
    opacity_to_logit,
    position_variance,
    prior_scale_for_expected_cov,
    safe_cholesky,
    sample_niw,
)

F64 = torch.float64
D = 3
COUNTS = [0.0, 1e-30, 1.0, 1e30]


@pytest.fixture(autouse=True)
def _fresh_guards():
    reset_guards()
    yield
    reset_guards()


def _finite(*ts):
    return all(bool(torch.isfinite(t).all()) for t in ts)


def _spd(S):
    S = S.to(F64)
    assert torch.equal(S, S.transpose(-1, -2)), "not exactly symmetric"
    assert int(torch.linalg.cholesky_ex(S)[1].count_nonzero()) == 0, "cholesky failed"
    assert bool((torch.linalg.eigvalsh(S) > 0).all()), "non-positive eigenvalue"


def _rot(K, g):
    Q, _ = torch.linalg.qr(torch.randn(K, D, D, dtype=F64, generator=g))
    return Q


def _scene(K, coord, birth_std, dtype, g):
    m0 = (coord * (1.0 + 0.1 * torch.randn(K, D, dtype=F64, generator=g))).to(dtype)
    xbar = (m0.to(F64) + 0.5 * birth_std * torch.randn(K, D, dtype=F64, generator=g)).to(dtype)
    Sig = (birth_std**2 * torch.eye(D, dtype=F64)).repeat(K, 1, 1).to(dtype)
    return m0, xbar, Sig


@pytest.mark.parametrize("dtype", [F64, torch.float32])
@pytest.mark.parametrize("coord,birth_std", [(1e4, 1e-2), (1e-4, 1e-5), (1.0, 0.1)])
def test_niw_extreme_counts_and_scales(dtype, coord, birth_std):
    g = torch.Generator().manual_seed(0)
    K = len(COUNTS)
    m0, xbar, Sig = _scene(K, coord, birth_std, dtype, g)
    S0 = prior_scale_for_expected_cov(Sig, 5.0)
    N = torch.tensor(COUNTS, dtype=dtype)
    m_n, k_n, nu_n, S_n = niw_update(m0, 0.01, 5.0, S0, N, xbar)
    assert m_n.dtype == dtype and S_n.dtype == dtype
    assert _finite(m_n, k_n, nu_n, S_n)
    _spd(S_n)
    # N = 0 keeps the prior, N = 1e30 moves the mean onto xbar exactly
    assert torch.equal(m_n[0], m0[0])
    assert torch.equal(m_n[3], xbar[3])
    E = expected_cov(S_n, nu_n)
    V = mean_variance(S_n, nu_n, k_n)
    pv = position_variance(S_n, nu_n, k_n)
    assert _finite(E, V, pv) and bool((pv >= 0).all())
    _spd(expected_cov(S_n.double(), nu_n.double()))
    # posterior variance shrinks monotonically with the count
    pv64 = position_variance(S_n.double(), nu_n.double(), k_n.double())
    assert bool((pv64[1:] <= pv64[:-1]).all())
    mu, Sg = sample_niw(m_n, k_n, nu_n, S_n, 8, generator=g)
    assert _finite(mu, Sg)
    _spd(sample_niw(m_n.double(), k_n.double(), nu_n.double(), S_n.double(), 8, generator=g)[1])


def test_niw_with_scatter_extreme_counts():
    g = torch.Generator().manual_seed(1)
    x = 1e4 + 1e-3 * torch.randn(4, 6, D, dtype=F64, generator=g)
    w = torch.tensor(COUNTS, dtype=F64)[:, None].expand(4, 6) / 6
    N, xbar, C = niw_batch_stats(x, w)
    assert _finite(N, xbar, C)
    torch.testing.assert_close(N, torch.tensor(COUNTS, dtype=F64))
    S0 = (1e-6 * torch.eye(D, dtype=F64)).repeat(4, 1, 1)
    out = niw_update(torch.full((4, D), 1e4, dtype=F64), 0.01, 5.0, S0, N, xbar, C)
    assert _finite(*out)
    _spd(out[3])
    # empty data set (all weights 0) is a valid no-op
    N0, xb0, C0 = niw_batch_stats(x, torch.zeros(4, 6, dtype=F64))
    assert _finite(N0, xb0, C0) and float(N0.abs().sum()) == 0


def test_nu_close_to_D_plus_1_guarded():
    nu0 = D + 1 + 1e-9
    S0 = torch.eye(D, dtype=F64)[None]
    zeros = torch.zeros(1, D, dtype=F64)
    m_n, k_n, nu_n, S_n = niw_update(zeros, 0.01, nu0, S0, torch.zeros(1, dtype=F64), zeros)
    E = expected_cov(S_n, nu_n)
    assert _finite(E)
    _spd(E)
    assert guard_counts().get("niw.expected_cov_denom_floor", 0) == 1
    assert _finite(mean_variance(S_n, nu_n, k_n))
    mu, Sg = sample_niw(m_n, k_n, nu_n, S_n, 64, generator=torch.Generator().manual_seed(2))
    assert _finite(mu, Sg)
    _spd(Sg)
    # float32 rounds D+1+1e-9 to exactly D+1: still finite, still counted
    before = guard_counts()["niw.expected_cov_denom_floor"]
    E32 = expected_cov(S_n.float(), nu_n.float())
    assert _finite(E32)
    assert guard_counts()["niw.expected_cov_denom_floor"] == before + 1


@pytest.mark.parametrize("kind", ["iso", "aniso", "rank1"])
def test_near_singular_S0(kind):
    g = torch.Generator().manual_seed(3)
    K = 4
    Q = _rot(K, g)
    if kind == "iso":
        S0 = 1e-8 * torch.eye(D, dtype=F64).repeat(K, 1, 1)
    elif kind == "aniso":
        S0 = Q @ torch.diag_embed(torch.tensor([1.0, 1.0, 1e-8], dtype=F64).repeat(K, 1)) @ Q.transpose(-1, -2)
    else:
        v = torch.randn(K, D, 1, dtype=F64, generator=g)
        S0 = v @ v.transpose(-1, -2) + 1e-8 * torch.eye(D, dtype=F64)
    S0 = 0.5 * (S0 + S0.transpose(-1, -2))
    m0 = torch.randn(K, D, dtype=F64, generator=g)
    N = torch.tensor(COUNTS, dtype=F64)
    m_n, k_n, nu_n, S_n = niw_update(m0, 0.01, 5.0, S0, N, m0 + 1e-3)
    assert _finite(m_n, k_n, nu_n, S_n)
    _spd(S_n)
    mu, Sg = sample_niw(m_n, k_n, nu_n, S_n, 16, generator=g)
    assert _finite(mu, Sg)
    _spd(Sg)


def test_safe_cholesky_guards_fire():
    A = torch.zeros(3, D, D, dtype=F64)
    A[0] = torch.eye(D)
    A[1] = torch.ones(D, D)  # singular PSD (rank 1)
    A[2] = torch.diag(torch.tensor([1.0, -1.0, 1.0]))  # indefinite: needs the eig fallback
    L = safe_cholesky(A)
    assert _finite(L)
    assert bool((L.diagonal(dim1=-2, dim2=-1) > 0).all())
    torch.testing.assert_close(L[0], torch.eye(D, dtype=F64))
    c = guard_counts()
    assert c["cholesky.jitter"] == 2 and c["cholesky.eig_fallback"] == 1
    Lnan = safe_cholesky(torch.full((1, D, D), float("nan")))
    assert _finite(Lnan) and guard_counts()["cholesky.nonfinite"] == 1
    # a singular posterior scale can still be sampled (jitter counted)
    mu, Sg = sample_niw(torch.zeros(1, D, dtype=F64), 1.0, 6.0, torch.ones(1, D, D, dtype=F64), 4)
    assert _finite(mu, Sg)
    assert guard_counts()["cholesky.jitter"] == 3


def test_single_gaussian_K1():
    g = torch.Generator().manual_seed(4)
    S0 = prior_scale_for_expected_cov(torch.eye(D)[None] * 0.01, 5.0)
    out = niw_update(torch.zeros(1, D), 0.01, 5.0, S0, torch.tensor([3.0]), torch.ones(1, D))
    assert all(t.shape[0] == 1 for t in out) and _finite(*out)
    mu, Sg = sample_niw(*out, 5, generator=g)
    assert mu.shape == (5, 1, D) and Sg.shape == (5, 1, D, D) and _finite(mu, Sg)
    for alpha in (1e-3, 5.0, 1e3):
        d = dp_posterior(torch.tensor([7.0]), alpha)
        assert float(d["expected_pi"][0]) == pytest.approx(1.0) and float(d["expected_log_pi"][0]) == 0.0
        ea = activity_posterior(d["expected_log_pi"], torch.tensor([7.0]))
        assert _finite(ea)
    a, b = opacity_beta_moment_match(torch.tensor([0.3]), torch.tensor([0.2]))
    assert _finite(a, b) and float(a) > 0 and float(b) > 0
    assert color_posterior_var(torch.tensor([0.5]), 0.01, 1.0).shape == (1,)


@pytest.mark.parametrize("alpha", [1e-3, 1e3])
def test_dp_extreme_alpha_and_counts(alpha):
    g = torch.Generator().manual_seed(5)
    K = 20000
    counts = torch.rand(K, dtype=F64, generator=g) * 100
    counts[:10] = 0.0
    counts[10] = 1e30
    counts[11:20] = 1e-30
    d = dp_posterior(counts, alpha)
    for key in ("gamma1", "gamma2", "expected_log_pi", "expected_pi"):
        assert _finite(d[key]), key
    epi = d["expected_pi"]
    assert bool((epi >= 0).all()) and float(epi.sum()) == pytest.approx(1.0, abs=1e-9)
    g1, g2 = cavi_stick_update(counts[d["perm"]], alpha)
    assert float(expected_pi(g1, g2, truncate_last=False).sum()) <= 1.0 + 1e-12
    assert _finite(expected_log_pi(g1, g2, truncate_last=False))
    for usage in (counts, torch.zeros(K, dtype=F64), torch.full((K,), 1e300, dtype=F64)):
        ea = activity_posterior(d["expected_log_pi"], usage, prior_logit=2.0, temperature=0.5)
        assert _finite(ea) and bool(((ea >= 0) & (ea <= 1)).all())
    ea = activity_posterior(d["expected_log_pi"], counts)
    assert float(ea[10]) > 0.99 and float(ea[:10].max()) < 0.5


def test_dp_invalid_inputs_are_guarded():
    counts = torch.tensor([1.0, float("nan"), -2.0, 3.0])
    g1, g2 = cavi_stick_update(counts, 1.0)
    assert _finite(g1, g2)
    assert guard_counts()["cavi_stick_update.invalid_count"] == 2
    with pytest.raises(ValueError):
        cavi_stick_update(counts, 0.0)


def test_opacity_at_exactly_0_and_1():
    op = torch.tensor([0.0, 1.0, 0.5, 1e-40])
    lg = opacity_to_logit(op)
    assert _finite(lg)
    assert guard_counts()["opacity.logit_clamp"] >= 2
    for var in (torch.zeros(4), torch.full((4,), 1e-12), torch.ones(4), torch.full((4,), 1e6)):
        a, b = opacity_beta_moment_match(lg, var)
        assert _finite(a, b) and bool((a > 0).all()) and bool((b > 0).all())
    a, b = opacity_beta_moment_match(torch.tensor([-float("inf"), float("inf")]), torch.ones(2))
    assert _finite(a, b) and float(a[0] / (a[0] + b[0])) < 1e-3 and float(b[1] / (a[1] + b[1])) < 1e-3
    v = opacity_fisher_var(torch.tensor([0.0, float("inf"), float("nan"), 1e300], dtype=F64), 1.0)
    assert _finite(v) and bool((v > 0).all())
    assert guard_counts()["opacity_fisher_var.invalid_grad_sq_ema"] == 2


def test_noise_edge_cases():
    a, b = ig_update(1.0, 1e-8, 0.0, 0)
    m = ig_mean(a, b)  # a <= 1: infinite mean, floored denominator and counted
    assert _finite(m) and guard_counts()["ig_mean.a_le_1"] == 1
    s = ig_sample(1e-3, 1e10, 200, generator=torch.Generator().manual_seed(6))
    assert _finite(s) and bool((s > 0).all())
    assert guard_counts().get("ig_sample.gamma_floor", 0) + guard_counts().get("ig_sample.overflow", 0) > 0
    a, b = ig_update(2.0, 1.0, torch.tensor(-1e-18, dtype=F64), 10)  # rounding-negative SS is clamped
    assert float(b) == 1.0 and guard_counts()["ig_update.negative_ss"] == 1
    a, b = ig_update(2.0, 1.0, 1e300, 1e30)
    assert _finite(a, b, ig_mean(a, b), ig_sample(a, b, 3))
    with pytest.raises(ValueError):
        ig_update(2.0, 1.0, 1.0, -1)


def test_color_extremes():
    v = color_posterior_var(torch.tensor([0.0, 1e30, float("nan")]), 0.0, 1e-3)
    assert _finite(v) and bool((v > 0).all())
    c = guard_counts()
    assert c["color_posterior_var.sigma2_floor"] == 3 and c["color_posterior_var.invalid_weight_sq_sum"] == 1


def test_guard_counter_and_logging(caplog):
    with caplog.at_level(logging.WARNING, logger="b3dgs.numerics"):
        assert guard("test.g", torch.tensor([True, False, True])) == 2
        assert guard("test.g", 0) == 0
        guard("test.g", 3)
    assert guard_counts()["test.g"] == 5
    msgs = [r.getMessage() for r in caplog.records if "test.g" in r.getMessage()]
    assert len(msgs) == 1  # logged once, not on every call
    reset_guards()
    assert "test.g" not in guard_counts()
