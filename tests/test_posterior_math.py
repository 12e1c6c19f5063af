"""Correctness of the posterior math in b3dgs_plugins.posterior against independent textbook formulas."""

import math

import numpy as np
import pytest
import torch
from scipy.special import digamma

from b3dgs_plugins.posterior import (
    activity_posterior,
    cavi_stick_update,
    color_posterior_mean,
    color_posterior_var,
    dc_var_to_rgb_var,
    dp_posterior,
    expected_cov,
    expected_log_pi,
    expected_pi,
    ig_mean,
    ig_mode,
    ig_sample,
    ig_update,
    ig_update_ema,
    logit_normal_moments,
    mean_variance,
    niw_batch_stats,
    niw_update,
    opacity_beta_moment_match,
    opacity_fisher_var,
    position_variance,
    posterior_mean_params,
    prior_scale_for_expected_cov,
    prune_threshold,
    rgb_var_to_dc_var,
    safe_cholesky,
    sample_niw,
    stick_order,
)

F64 = torch.float64
D = 3


def _rand_spd(rng, K, scale=1.0):
    A = rng.normal(size=(K, D, D))
    return scale * (A @ A.transpose(0, 2, 1) + 0.5 * np.eye(D))


def _murphy_niw(m0, k0, nu0, S0, x, w):
    """Textbook NIW posterior (Murphy 2012, Eq. 4.209-4.214) with the *uncentred* scatter form
    S_n = S0 + sum_i w_i x_i x_i^T + k0 m0 m0^T - k_n m_n m_n^T, written independently in numpy."""
    N = w.sum()
    kn = k0 + N
    xbar = (w[:, None] * x).sum(0) / N if N > 0 else np.zeros(D)
    mn = (k0 * m0 + N * xbar) / kn
    nun = nu0 + N
    Sx = (w[:, None, None] * x[:, :, None] * x[:, None, :]).sum(0)
    Sn = S0 + Sx + k0 * np.outer(m0, m0) - kn * np.outer(mn, mn)
    return mn, kn, nun, Sn


# ----------------------------------------------------------------------------- NIW
def test_niw_update_matches_textbook_batch_posterior():
    rng = np.random.default_rng(0)
    K, n = 5, 40
    m0 = rng.normal(size=(K, D))
    k0 = rng.uniform(0.01, 2.0, size=K)
    nu0 = rng.uniform(D + 2, 10, size=K)
    S0 = _rand_spd(rng, K)
    x = rng.normal(size=(K, n, D)) * 2 + 1
    w = rng.uniform(0.1, 3.0, size=(K, n))
    N, xbar, C = niw_batch_stats(torch.tensor(x), torch.tensor(w))
    assert N.shape == (K,) and xbar.shape == (K, D) and C.shape == (K, D, D)
    assert float(torch.linalg.matrix_norm(C).min()) > 0  # nonzero scatter
    m_n, k_n, nu_n, S_n = niw_update(
        torch.tensor(m0), torch.tensor(k0), torch.tensor(nu0), torch.tensor(S0), N, xbar, C
    )
    for k in range(K):
        mn, kn, nun, Sn = _murphy_niw(m0[k], k0[k], nu0[k], S0[k], x[k], w[k])
        np.testing.assert_allclose(m_n[k].numpy(), mn, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(float(k_n[k]), kn, rtol=1e-12)
        np.testing.assert_allclose(float(nu_n[k]), nun, rtol=1e-12)
        np.testing.assert_allclose(S_n[k].numpy(), Sn, rtol=1e-9, atol=1e-9)
    assert torch.equal(S_n, S_n.transpose(-1, -2))


def test_niw_online_special_case_C0():
    """C = 0 (paper's online path) is the textbook update for a single pseudo-observation xbar of weight N."""
    rng = np.random.default_rng(1)
    K = 4
    m0 = rng.normal(size=(K, D))
    S0 = _rand_spd(rng, K)
    xb = rng.normal(size=(K, D)) * 3
    N = np.array([0.0, 0.3, 7.0, 250.0])
    m_n, k_n, nu_n, S_n = niw_update(torch.tensor(m0), 0.01, 5.0, torch.tensor(S0), torch.tensor(N), torch.tensor(xb))
    for k in range(K):
        mn, kn, nun, Sn = _murphy_niw(m0[k], 0.01, 5.0, S0[k], xb[k][None], np.array([N[k]]))
        np.testing.assert_allclose(m_n[k].numpy(), mn, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(S_n[k].numpy(), Sn, rtol=1e-8, atol=1e-8)
        assert float(k_n[k]) == pytest.approx(kn) and float(nu_n[k]) == pytest.approx(nun)
    # N = 0 leaves the prior untouched exactly
    assert torch.equal(m_n[0], torch.tensor(m0[0])) and torch.equal(S_n[0], torch.tensor(S0[0]))


def test_niw_sequential_equals_batch():
    rng = np.random.default_rng(2)
    K, n = 3, 30
    x = torch.tensor(rng.normal(size=(K, 2 * n, D)))
    m0, S0 = torch.zeros(K, D, dtype=F64), torch.eye(D, dtype=F64).repeat(K, 1, 1)
    full = niw_update(m0, 0.5, 6.0, S0, *niw_batch_stats(x))
    a = niw_update(m0, 0.5, 6.0, S0, *niw_batch_stats(x[:, :n]))
    b = niw_update(a[0], a[1], a[2], a[3], *niw_batch_stats(x[:, n:]))
    for u, v in zip(full, b):
        torch.testing.assert_close(u, v, rtol=1e-10, atol=1e-10)


def test_niw_posterior_concentrates_at_truth():
    rng = np.random.default_rng(3)
    mu_true = np.array([1.0, -2.0, 0.5])
    L = np.array([[1.0, 0, 0], [0.5, 0.8, 0], [-0.3, 0.2, 0.4]])
    Sig_true = L @ L.T
    errs_m, errs_S, pos_var = [], [], []
    for n in (10, 100, 10000):
        x = torch.tensor(rng.normal(size=(1, n, D)) @ L.T + mu_true)
        S0 = prior_scale_for_expected_cov(torch.eye(D, dtype=F64)[None], 5.0)
        m_n, k_n, nu_n, S_n = niw_update(torch.zeros(1, D, dtype=F64), 0.01, 5.0, S0, *niw_batch_stats(x))
        mean, E = posterior_mean_params(m_n, k_n, nu_n, S_n)
        errs_m.append(float((mean[0] - torch.tensor(mu_true)).norm()))
        errs_S.append(float((E[0] - torch.tensor(Sig_true)).norm() / np.linalg.norm(Sig_true)))
        pos_var.append(float(position_variance(S_n, nu_n, k_n)[0]))
    assert errs_m[-1] < 0.05 and errs_S[-1] < 0.05
    assert pos_var[0] > pos_var[1] > pos_var[2]
    assert pos_var[-1] < 1e-3


def test_prior_scale_gives_birth_covariance():
    rng = np.random.default_rng(4)
    Sig = torch.tensor(_rand_spd(rng, 6))
    nu0 = torch.linspace(4.5, 20.0, 6, dtype=F64)
    S0 = prior_scale_for_expected_cov(Sig, nu0)
    torch.testing.assert_close(expected_cov(S0, nu0), Sig, rtol=1e-12, atol=1e-12)
    V = mean_variance(S0, nu0, 2.0)
    torch.testing.assert_close(V, Sig / 2.0, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError):
        prior_scale_for_expected_cov(Sig, 4.0)


def test_shape_errors():
    m0 = torch.zeros(2, D)
    S0 = torch.eye(D).repeat(2, 1, 1)
    with pytest.raises(ValueError):
        niw_update(m0, 1.0, 5.0, S0, torch.ones(3), torch.zeros(2, D))
    with pytest.raises(ValueError):
        niw_update(m0, 1.0, 5.0, S0[:, :2, :2], torch.ones(2), torch.zeros(2, D))
    with pytest.raises(ValueError):
        niw_update(m0[0], 1.0, 5.0, S0, torch.ones(2), torch.zeros(2, D))
    with pytest.raises(ValueError):
        sample_niw(m0, 1.0, 5.0, S0[:1], 3)
    with pytest.raises(ValueError):
        cavi_stick_update(torch.ones(2, 2), 1.0)
    with pytest.raises(ValueError):
        color_posterior_var(torch.ones(2, 1), 1.0, 1.0)


def test_sample_niw_moments_and_spd():
    rng = np.random.default_rng(5)
    K, S = 3, 20000
    Sn = torch.tensor(_rand_spd(rng, K))
    m = torch.tensor(rng.normal(size=(K, D)) * 10)
    nu = torch.tensor([12.0, 20.0, 40.0], dtype=F64)
    kap = torch.tensor([0.5, 2.0, 10.0], dtype=F64)
    g = torch.Generator().manual_seed(0)
    mu, Sig = sample_niw(m, kap, nu, Sn, S, generator=g)
    assert mu.shape == (S, K, D) and Sig.shape == (S, K, D, D)
    assert int(torch.linalg.cholesky_ex(Sig)[1].count_nonzero()) == 0
    assert torch.equal(Sig, Sig.transpose(-1, -2))
    # Monte-Carlo tolerance: 5 standard errors estimated from the S draws (false-fail rate ~1e-6 per entry)
    E = expected_cov(Sn, nu)
    se = Sig.std(0) / math.sqrt(S)
    assert bool(((Sig.mean(0) - E).abs() <= 5 * se).all())
    dev = mu - m
    outer = dev[..., :, None] * dev[..., None, :]
    V = mean_variance(Sn, nu, kap)
    se_mu = outer.std(0) / math.sqrt(S)
    assert bool(((outer.mean(0) - V).abs() <= 5 * se_mu).all())
    assert bool((dev.mean(0).abs() <= 5 * dev.std(0) / math.sqrt(S)).all())
    # deterministic given the generator
    mu2, Sig2 = sample_niw(m, kap, nu, Sn, S, generator=torch.Generator().manual_seed(0))
    assert torch.equal(mu, mu2) and torch.equal(Sig, Sig2)


def test_whitened_draw_is_a_function_of_the_bartlett_factor():
    """E[Σ]^{-1/2} Σ E[Σ]^{-T/2} = (ν - D - 1)(A Aᵀ)^{-1}: what NIWBlock renders in relative mode."""
    from b3dgs_plugins.posterior.niw import sample_niw_factors, tril_solve

    rng = np.random.default_rng(7)
    K, S = 4, 6
    Sn = torch.tensor(_rand_spd(rng, K))
    nu = torch.tensor([5.5, 8.0, 20.0, 100.0], dtype=F64)
    mu, X, A = sample_niw_factors(torch.zeros(K, D, dtype=F64), 1.0, nu, Sn, S, generator=torch.Generator().manual_seed(3))
    Sig = X.transpose(-1, -2) @ X
    Le = torch.linalg.cholesky(expected_cov(Sn, nu))
    Y = torch.linalg.solve_triangular(Le.expand(S, K, D, D), Sig, upper=False)
    W_ref = torch.linalg.solve_triangular(Le.expand(S, K, D, D), Y.transpose(-1, -2), upper=False)
    W = (nu - D - 1)[None, :, None, None] * torch.linalg.inv(A @ A.transpose(-1, -2))
    assert torch.allclose(W, W_ref, rtol=1e-9, atol=1e-12)
    B = torch.tensor(rng.normal(size=(S, K, D, 2)))
    assert torch.allclose(tril_solve(A, B), torch.linalg.solve_triangular(A, B, upper=False), rtol=1e-12, atol=1e-12)


def test_safe_cholesky_plain_matches_torch():
    rng = np.random.default_rng(6)
    A = torch.tensor(_rand_spd(rng, 5))
    torch.testing.assert_close(safe_cholesky(A), torch.linalg.cholesky(A))


# ----------------------------------------------------------------------------- noise
def test_ig_update_conjugate_and_recovers_sigma2():
    a, b = ig_update(2.0, 0.1, 3.0, 10)
    assert float(a) == pytest.approx(7.0) and float(b) == pytest.approx(1.6)
    assert float(ig_mean(a, b)) == pytest.approx(1.6 / 6.0)
    assert float(ig_mode(a, b)) == pytest.approx(1.6 / 8.0)
    g = torch.Generator().manual_seed(1)
    sigma2 = 0.05**2
    r = torch.randn(200000, dtype=F64, generator=g) * math.sqrt(sigma2)
    a, b = ig_update(1.0, 1e-4, float((r**2).sum()), r.numel())
    assert float(ig_mean(a, b)) == pytest.approx(sigma2, rel=0.02)
    draws = ig_sample(a, b, 4000, generator=g)
    assert draws.shape == (4000,)
    assert float(draws.mean()) == pytest.approx(float(ig_mean(a, b)), rel=0.01)


def test_ig_ema_tracks_nonstationary_residual():
    a, b = torch.tensor(2.0, dtype=F64), torch.tensor(1.0, dtype=F64)
    n = 1000
    for _ in range(200):
        a, b = ig_update_ema(a, b, 0.04 * n, n, decay=0.9, a0=2.0, b0=1.0)
    assert float(ig_mean(a, b)) == pytest.approx(0.04, rel=0.01)
    for _ in range(200):  # residual shrinks during training: the posterior follows
        a, b = ig_update_ema(a, b, 0.01 * n, n, decay=0.9, a0=2.0, b0=1.0)
    assert float(ig_mean(a, b)) == pytest.approx(0.01, rel=0.02)
    a1, b1 = ig_update_ema(3.0, 2.0, 5.0, 4, decay=1.0, a0=1.0, b0=1.0)
    a2, b2 = ig_update(3.0, 2.0, 5.0, 4)
    assert float(a1) == float(a2) and float(b1) == float(b2)


# ----------------------------------------------------------------------------- DP
def test_cavi_matches_blei_jordan_hand_case():
    counts = torch.tensor([5.0, 3.0, 2.0], dtype=F64)
    g1, g2 = cavi_stick_update(counts, 2.0)
    assert g1.tolist() == [6.0, 4.0, 3.0]
    assert g2.tolist() == [7.0, 4.0, 2.0]  # alpha + sum_{j>k} N_j
    # E[log pi] by hand (scipy digamma), untruncated and truncated (v_K = 1)
    elv = [digamma(6) - digamma(13), digamma(4) - digamma(8), digamma(3) - digamma(5)]
    el1 = [digamma(7) - digamma(13), digamma(4) - digamma(8)]
    hand = np.array([elv[0], el1[0] + elv[1], el1[0] + el1[1] + elv[2]])
    np.testing.assert_allclose(expected_log_pi(g1, g2, truncate_last=False).numpy(), hand, rtol=1e-12)
    hand_t = hand.copy()
    hand_t[2] = el1[0] + el1[1]
    np.testing.assert_allclose(expected_log_pi(g1, g2).numpy(), hand_t, rtol=1e-12)
    epi = expected_pi(g1, g2, truncate_last=False).numpy()
    np.testing.assert_allclose(epi, [6 / 13, 7 / 13 * 4 / 8, 7 / 13 * 4 / 8 * 3 / 5], rtol=1e-12)
    assert epi.sum() <= 1.0
    assert float(expected_pi(g1, g2).sum()) == pytest.approx(1.0, abs=1e-12)
    # Monte-Carlo check of E[pi] and E[log pi] from Beta draws
    rng = np.random.default_rng(7)
    n = 200000
    v = rng.beta(g1.numpy(), g2.numpy(), size=(n, 3))
    rest = np.cumprod(np.concatenate([np.ones((n, 1)), 1 - v[:, :-1]], 1), 1)
    pi = v * rest
    se = pi.std(0) / math.sqrt(n)
    assert np.all(np.abs(pi.mean(0) - epi) <= 5 * se)
    lp = np.log(pi)
    assert np.all(np.abs(lp.mean(0) - hand) <= 5 * lp.std(0) / math.sqrt(n))


def test_stick_order_and_dp_posterior():
    counts = torch.tensor([1.0, 3.0, 3.0, 0.0, 3.0])
    perm, inv = stick_order(counts)
    assert perm.tolist() == [1, 2, 4, 0, 3]  # decreasing, ties by index
    assert torch.equal(counts[perm][inv], counts)
    out = dp_posterior(counts, 1.0)
    g1, g2 = cavi_stick_update(counts[perm].double(), 1.0)
    torch.testing.assert_close(out["expected_pi"], expected_pi(g1, g2)[inv])
    assert float(out["expected_pi"].sum()) == pytest.approx(1.0)
    # more usage -> more expected weight
    assert float(out["expected_pi"][1]) > float(out["expected_pi"][0]) > float(out["expected_pi"][3])


def test_activity_and_threshold():
    assert prune_threshold(1000, 0.01) == pytest.approx(1e-5)
    assert prune_threshold(10, 0.5) == pytest.approx(0.05)
    usage = torch.tensor([1000.0, 100.0, 10.0, 0.1, 0.0], dtype=F64)
    dp = dp_posterior(usage, 5.0)
    ea = activity_posterior(dp["expected_log_pi"], usage, prior_logit=0.0, temperature=1.0)
    assert bool(((ea >= 0) & (ea <= 1)).all())
    assert ea.tolist() == sorted(ea.tolist(), reverse=True)
    assert float(ea[0]) > 0.99 and float(ea[-1]) < 0.1
    # higher prior log-odds -> more active; colder temperature -> sharper
    ea_hi = activity_posterior(dp["expected_log_pi"], usage, prior_logit=3.0)
    assert bool((ea_hi >= ea).all())


# ----------------------------------------------------------------------------- appearance
def test_color_posterior_var_and_mean():
    w2 = torch.tensor([0.0, 1.0, 10.0, 100.0], dtype=F64)
    var = color_posterior_var(w2, 0.01, 4.0)
    assert float(var[0]) == pytest.approx(0.25)
    assert bool((var[1:] < var[:-1]).all())
    np.testing.assert_allclose(var.numpy(), 1.0 / (w2.numpy() / 0.01 + 4.0))
    # a prior precision in RGB units maps to DC units as precision_dc = C0^2 precision_rgb
    var_dc = color_posterior_var(w2, 0.01, 4.0 * 0.28209479177387814**2, space="dc")
    torch.testing.assert_close(dc_var_to_rgb_var(var_dc), var)
    torch.testing.assert_close(rgb_var_to_dc_var(var), var_dc)
    # linear model I_p = w_p c + noise: posterior mean is exact from any linearisation point
    rng = np.random.default_rng(8)
    w = rng.uniform(0, 1, size=(2, 50))
    c_true = np.array([[0.2, 0.5, 0.9], [0.7, 0.1, 0.4]])
    I = w[..., None] * c_true[:, None, :] + 0.05 * rng.normal(size=(2, 50, 3))
    c0 = np.full((2, 3), 0.5)
    r = I - w[..., None] * c0[:, None, :]
    s2, tau, eta = 0.05**2, 2.0, 0.5
    mean = color_posterior_mean(
        torch.tensor(c0), torch.tensor((w[..., None] * r).sum(1)), torch.tensor((w**2).sum(1)), s2, eta, tau
    )
    exact = ((w[..., None] * I).sum(1) / s2 + tau * eta) / ((w**2).sum(1)[:, None] / s2 + tau)
    np.testing.assert_allclose(mean.numpy(), exact, rtol=1e-10)
    assert np.abs(mean.numpy() - c_true).max() < 0.1


def test_opacity_beta_matches_logit_normal_mc():
    logit = torch.tensor([-4.0, -1.0, 0.0, 0.5, 2.0, 6.0], dtype=F64)
    lvar = torch.tensor([0.5, 2.0, 0.1, 9.0, 1.0, 4.0], dtype=F64)
    a, b = opacity_beta_moment_match(logit, lvar)
    g = torch.Generator().manual_seed(3)
    n = 400000
    s = torch.sigmoid(logit + lvar.sqrt() * torch.randn(n, 6, dtype=F64, generator=g))
    mc_mean, mc_var = s.mean(0), s.var(0)
    beta_mean = a / (a + b)
    beta_var = a * b / ((a + b) ** 2 * (a + b + 1))
    # tolerances: 5 MC standard errors (+ tiny absolute slack for the quadrature)
    se_mean = s.std(0) / math.sqrt(n)
    se_var = ((s - mc_mean) ** 2).std(0) / math.sqrt(n)
    assert bool(((beta_mean - mc_mean).abs() <= 5 * se_mean + 1e-6).all())
    assert bool(((beta_var - mc_var).abs() <= 5 * se_var + 1e-7).all())
    m2, v2 = logit_normal_moments(logit, lvar)
    torch.testing.assert_close(m2, beta_mean)
    # zero variance -> the Beta concentrates at sigmoid(logit)
    a0, b0 = opacity_beta_moment_match(logit, torch.zeros(6, dtype=F64))
    torch.testing.assert_close(a0 / (a0 + b0), torch.sigmoid(logit))


def test_opacity_fisher_var():
    g2 = torch.tensor([0.0, 1.0, 10.0], dtype=F64)
    v = opacity_fisher_var(g2, 1.0)
    np.testing.assert_allclose(v.numpy(), [1.0, 0.5, 1 / 11])
    v2 = opacity_fisher_var(g2, 1.0, data_scale=100.0)
    assert bool((v2[1:] < v[1:]).all())


@pytest.mark.parametrize("mode", ["absolute", "relative"])
def test_cpu_niw_draws_have_the_posterior_moments(mode):
    """The one-pass C++ sampler (uq=native's default) draws from the same NIW as the torch reference:
    E[mu] = m_n, Cov[mu] = E[Σ]/κ_n, E[Σ] = S_n/(ν-D-1) (absolute) and E[Σ_render] = the rendered
    covariance (relative: L c(AAᵀ)^{-1} Lᵀ with E[(AAᵀ)^{-1}] = I/(ν-D-1)); 5 Monte-Carlo standard errors."""
    from b3dgs_plugins.posterior.niw import niw_sampler
    from b3dgs.render._ext import load_extension

    rng = np.random.default_rng(9)
    K, S = 3, 20000
    Sn = torch.tensor(_rand_spd(rng, K))
    m = torch.tensor(rng.normal(size=(K, D)))
    nu = torch.tensor([12.0, 20.0, 40.0], dtype=F64)
    kap = torch.tensor([0.5, 2.0, 10.0], dtype=F64)
    prep = niw_sampler(m, kap, nu, Sn)
    cov_r = torch.tensor(_rand_spd(rng, K))
    LrT = torch.linalg.cholesky(cov_r).transpose(-1, -2).contiguous()
    sqrt_c = (nu - D - 1).sqrt()
    e = load_extension()
    args = (prep.m, prep.kappa, prep.nu, prep.L.contiguous(), LrT, sqrt_c, S, {"absolute": 1, "relative": 2}[mode],
            1e-12, 77, True, 2)
    mu, Sig, floored = e.niw_draw(*args)
    assert int(floored) == 0 and mu.shape == (S, K, D) and Sig.shape == (S, K, D, D)
    assert torch.equal(Sig, Sig.transpose(-1, -2))
    assert int(torch.linalg.cholesky_ex(Sig)[1].count_nonzero()) == 0
    target = expected_cov(Sn, nu) if mode == "absolute" else cov_r
    assert bool(((Sig.mean(0) - target).abs() <= 5 * Sig.std(0) / math.sqrt(S)).all())
    dev = mu - m
    assert bool((dev.mean(0).abs() <= 5 * dev.std(0) / math.sqrt(S)).all())
    outer = dev[..., :, None] * dev[..., None, :]
    assert bool(((outer.mean(0) - mean_variance(Sn, nu, kap)).abs() <= 5 * outer.std(0) / math.sqrt(S)).all())
    # a seed reproduces the draws, whatever the thread count
    mu2, Sig2, _ = e.niw_draw(*args[:-1], 1)
    assert torch.equal(mu, mu2) and torch.equal(Sig, Sig2)
