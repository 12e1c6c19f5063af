"""Uncertainty metrics (AUSE, ECE, NLL, Cov@95, Spearman) and the UQ plots."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from b3dgs.io import write_json
from b3dgs.uq import metrics as M
from b3dgs.uq.metrics import (ause, calibration, coverage, evaluate_view, gaussian_nll, sparsification,
                              spearman_rho, summarize, to_jsonable)


def _calibrated_view(seed: int, h: int = 256, w: int = 256, scale: float = 1.0):
    """gt = mean + sqrt(var) * eps with per-pixel random var: a perfectly calibrated predictor."""
    rng = np.random.default_rng(seed)
    mean = rng.uniform(0.2, 0.8, size=(h, w, 3))
    var = rng.uniform(1e-4, 1e-2, size=(h, w))
    gt = mean + np.sqrt(var)[..., None] * rng.standard_normal((h, w, 3))
    return mean, var * scale, gt


# ---------------------------------------------------------------------------------- calibration
def test_calibrated_gaussian_cov95_ece_nll():
    mean, var, gt = _calibrated_view(0)
    res = evaluate_view(mean, var, gt)
    n = mean.size  # 196608 (pixel, channel) residuals, independent across channels
    # Monte-Carlo s.d. of an observed coverage: sqrt(p(1-p)/n) -> 4.9e-4 at p=0.95, <= 1.13e-3 at any p.
    sd95 = math.sqrt(0.95 * 0.05 / n)
    sd_max = math.sqrt(0.25 / n)
    assert abs(res["cov95"] - 0.95) < 4 * sd95  # ~2.0e-3
    assert res["cov95_err"] == pytest.approx(abs(res["cov95"] - 0.95))
    # ECE is a mean of |observed - nominal| over 19 levels, so it is bounded by the worst level's gap.
    assert res["ece"] < 4 * sd_max  # ~4.5e-3
    obs = res["curves"]["calibration"]["observed"]
    levels = res["curves"]["calibration"]["levels"]
    np.testing.assert_allclose(levels, np.arange(1, 20) * 0.05)
    assert np.max(np.abs(obs - levels)) < 5 * sd_max
    # NLL of a calibrated Gaussian: E[0.5 log(2 pi v)] + 0.5; s.d. of the per-element term is 1/sqrt(2)
    expected = float(np.mean(0.5 * np.log(2 * np.pi * var))) + 0.5
    assert res["nll"] == pytest.approx(expected, abs=4 * math.sqrt(0.5 / n))
    assert res["nll_n_floored"] == 0


def test_overconfident_prediction_undercovers():
    mean, var, gt = _calibrated_view(1, 128, 128, scale=0.01)  # variance 100x too small -> sd 10x too small
    res = evaluate_view(mean, var, gt)
    # coverage of +-1.96 * sd/10 is P(|Z| <= 0.196) = 0.155
    expected = 2 * stats.norm.cdf(M.Z95 / 10) - 1
    assert res["cov95"] < 0.3
    assert res["cov95"] == pytest.approx(expected, abs=0.01)
    assert res["cov95_err"] > 0.6
    assert res["ece"] > 0.2


def test_calibration_and_coverage_functions_agree():
    mean, var, gt = _calibrated_view(2, 32, 32)
    cal = calibration(mean, var, gt, levels=[0.5, 0.95])
    assert cal["observed"][1] == pytest.approx(coverage(mean, var, gt, level=0.95), abs=1e-12)
    # brute-force coverage at 0.5
    z = stats.norm.ppf(0.75)
    inside = np.abs(gt - mean) <= z * np.sqrt(var)[..., None]
    assert cal["observed"][0] == pytest.approx(inside.mean())
    assert cal["ece"] == pytest.approx(np.mean(np.abs(cal["observed"] - [0.5, 0.95])))


def test_zero_variance_zero_residual_counts_as_covered():
    mean = np.zeros((1, 2, 3))
    gt = mean.copy()
    gt[0, 1] = 0.5  # second pixel misses a zero-width interval
    var = np.zeros((1, 2))
    assert coverage(mean, var, gt) == pytest.approx(0.5)


# -------------------------------------------------------------------------------------- NLL
def test_nll_hand_computed_2x2():
    # var = 1/(2 pi) -> 0.5 log(2 pi var) = 0 and 0.5 r^2 / var = pi r^2
    mean = np.zeros((2, 2, 3))
    r = np.array([[[0.0, 0.1, 0.2], [0.3, 0.0, 0.0]],
                  [[1.0, 0.0, 0.0], [0.5, 0.5, 0.5]]])
    gt = mean + r
    var = np.full((2, 2), 1 / (2 * np.pi))
    hand = math.pi * (0.01 + 0.04 + 0.09 + 1.0 + 0.75) / 12
    assert gaussian_nll(mean, var, gt)["nll"] == pytest.approx(hand, rel=1e-12)
    assert evaluate_view(mean, var, gt)["nll"] == pytest.approx(hand, rel=1e-12)
    # mixed variances: pixel (0,0) var 1, r=0 -> 0.5 log(2 pi); others as above
    var2 = var.copy()
    var2[0, 0] = 1.0
    r2 = r.copy()
    r2[0, 0] = 0.0
    hand2 = (3 * 0.5 * math.log(2 * math.pi) + math.pi * (0.09 + 1.0 + 0.75)) / 12
    assert gaussian_nll(mean, var2, mean + r2)["nll"] == pytest.approx(hand2, rel=1e-12)


def test_nll_floor_is_counted():
    mean = np.zeros((2, 2, 3))
    gt = mean + 0.01
    var = np.array([[0.0, 1e-12], [1e-3, 1e-2]])
    res = gaussian_nll(mean, var, gt, var_floor=1e-8)
    assert res["nll_n_floored"] == 2
    assert res["nll_var_floor"] == 1e-8
    assert math.isfinite(res["nll"])
    v = np.array([1e-8, 1e-8, 1e-3, 1e-2])
    hand = np.mean(0.5 * np.log(2 * np.pi * v) + 0.5 * 1e-4 / v)
    assert res["nll"] == pytest.approx(hand, rel=1e-12)
    assert evaluate_view(mean, var, gt)["nll_n_floored"] == 2


# ------------------------------------------------------------------------------------- AUSE
def _error_view(seed: int, h: int = 24, w: int = 20, quantize: bool = True):
    rng = np.random.default_rng(seed)
    mean = rng.uniform(size=(h, w, 3))
    noise = rng.normal(scale=0.1, size=(h, w, 3))
    if quantize:  # coarse values -> many tied errors
        noise = np.round(noise * 20) / 20
    return mean, mean + noise


@pytest.mark.parametrize("normalize", [False, True])
def test_uncertainty_equal_to_error_gives_zero_ause(normalize):
    mean, gt = _error_view(3)
    a, s = M.per_pixel_errors(mean, gt)
    r_rmse = evaluate_view(mean, s, gt, normalize=normalize)  # uncertainty = squared error
    r_mae = evaluate_view(mean, a ** 2, gt, normalize=normalize)  # sqrt(var) = absolute error
    assert r_rmse["ause_rmse"] == pytest.approx(0.0, abs=1e-12)
    assert r_mae["ause_mae"] == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(r_rmse["curves"]["rmse"]["sparsification"], r_rmse["curves"]["rmse"]["oracle"])
    # identical error on the three channels: a_p and s_p share one order -> both AUSEs vanish together
    gt_gray = mean + (gt - mean)[..., :1]
    a, _ = M.per_pixel_errors(mean, gt_gray)
    r = evaluate_view(mean, a, gt_gray, normalize=normalize)
    assert r["ause_rmse"] == pytest.approx(0.0, abs=1e-12)
    assert r["ause_mae"] == pytest.approx(0.0, abs=1e-12)


def test_constant_uncertainty_hand_case():
    # 2x2 image, per-pixel abs error 1, 2, 3, 4 (row-major), constant uncertainty
    mean = np.zeros((2, 2, 3))
    gt = np.repeat(np.array([[1.0, 2.0], [3.0, 4.0]])[..., None], 3, axis=-1)
    var = np.full((2, 2), 0.5)
    f = [0.0, 0.25, 0.5, 0.75]
    raw = ause(mean, var, gt, metric="mae", fractions=f)
    # stable order: row-major pixels are removed first -> remaining {1..4}, {2,3,4}, {3,4}, {4}
    np.testing.assert_allclose(raw["sparsification"], [2.5, 3.0, 3.5, 4.0])
    np.testing.assert_allclose(raw["oracle"], [2.5, 2.0, 1.5, 1.0])
    assert raw["ause"] == pytest.approx(0.25 * (0 / 2 + 1 + 2 + 3 / 2))  # 1.125
    assert raw["ause_normalization"] == M.AUSE_NORMALIZATION_RAW
    norm = ause(mean, var, gt, metric="mae", fractions=f, normalize=True)
    np.testing.assert_allclose(norm["sparsification"], np.array([2.5, 3.0, 3.5, 4.0]) / 2.5)
    assert norm["sparsification"][0] == 1.0
    assert norm["ause"] == pytest.approx(1.125 / 2.5)
    assert "curve[0]=1" in norm["ause_normalization"]
    rm = ause(mean, var, gt, metric="rmse", fractions=f)
    np.testing.assert_allclose(rm["sparsification"], np.sqrt([30 / 4, 29 / 3, 25 / 2, 16.0]))
    np.testing.assert_allclose(rm["oracle"], np.sqrt([30 / 4, 14 / 3, 5 / 2, 1.0]))


def test_constant_uncertainty_default_grid_matches_hand_formula():
    mean, gt = _error_view(4, 6, 7, quantize=False)  # 42 pixels: floor(f*42) exercises rounding
    var = np.ones((6, 7))
    a, s = M.per_pixel_errors(mean, gt)
    a, s = a.reshape(-1), s.reshape(-1)
    res = evaluate_view(mean, var, gt)
    c = res["curves"]
    assert len(c["fractions"]) == 100
    n = a.size
    k = [(i * n) // 100 for i in range(100)]  # pixels removed at fraction i/100 (exact integer floor)
    np.testing.assert_allclose(c["mae"]["sparsification"], [a[j:].mean() for j in k], rtol=1e-12)
    np.testing.assert_allclose(c["rmse"]["sparsification"], [math.sqrt(s[j:].mean()) for j in k], rtol=1e-12)
    a_desc, s_desc = np.sort(a)[::-1], np.sort(s)[::-1]
    np.testing.assert_allclose(c["mae"]["oracle"], [a_desc[j:].mean() for j in k], rtol=1e-12)
    np.testing.assert_allclose(c["rmse"]["oracle"], [math.sqrt(s_desc[j:].mean()) for j in k], rtol=1e-12)
    fr = np.arange(100) / 100
    gap = np.array([a[j:].mean() for j in k]) - np.array([a_desc[j:].mean() for j in k])
    assert res["ause_mae"] == pytest.approx(np.trapezoid(gap, fr), rel=1e-10)
    assert res["mae"] == pytest.approx(a.mean())
    assert res["rmse"] == pytest.approx(math.sqrt(s.mean()))


def test_ause_nonnegative_and_random_uncertainty_is_worse_than_informative():
    mean, gt = _error_view(5, 40, 40, quantize=False)
    a, s = M.per_pixel_errors(mean, gt)
    rng = np.random.default_rng(0)
    noisy = s * np.exp(rng.normal(scale=0.5, size=s.shape))  # informative but imperfect
    rand = rng.uniform(size=s.shape)
    r_inf, r_rand = evaluate_view(mean, noisy, gt), evaluate_view(mean, rand, gt)
    for r in (r_inf, r_rand):
        for m in ("rmse", "mae"):
            assert np.all(r["curves"][m]["sparsification"] >= r["curves"][m]["oracle"] - 1e-12)
    assert 0 < r_inf["ause_rmse"] < r_rand["ause_rmse"]
    assert 0 < r_inf["ause_mae"] < r_rand["ause_mae"]
    # normalised AUSE = raw AUSE / full-set error (both curves share the divisor)
    r_n = evaluate_view(mean, noisy, gt, normalize=True)
    assert r_n["ause_rmse"] == pytest.approx(r_inf["ause_rmse"] / r_inf["rmse"], rel=1e-10)
    assert r_n["ause_mae"] == pytest.approx(r_inf["ause_mae"] / r_inf["mae"], rel=1e-10)


# --------------------------------------------------------------------------------- Spearman
def test_spearman_matches_scipy_with_ties():
    rng = np.random.default_rng(6)
    x = rng.integers(0, 6, size=1000).astype(float)
    y = x + rng.integers(0, 4, size=1000)
    rho, n = spearman_rho(x, y)
    assert n == 1000
    assert rho == pytest.approx(stats.spearmanr(x, y).statistic, abs=1e-12)
    z = rng.normal(size=300)
    assert spearman_rho(z, -z ** 3)[0] == pytest.approx(-1.0)
    assert math.isnan(spearman_rho(np.ones(10), z[:10])[0])


def test_spearman_in_evaluate_view_and_subsampling():
    mean, gt = _error_view(7, 50, 40)  # 2000 pixels, tied errors
    a, _ = M.per_pixel_errors(mean, gt)
    var = np.round(a + np.random.default_rng(1).uniform(0, 0.05, size=a.shape), 2)  # tied uncertainties
    res = evaluate_view(mean, var, gt)
    assert res["spearman_n"] == 2000
    assert res["spearman_rho"] == pytest.approx(stats.spearmanr(var.ravel(), a.ravel()).statistic, abs=1e-12)
    sub = evaluate_view(mean, var, gt, max_spearman_pixels=500, seed=3)
    assert sub["spearman_n"] == 500
    assert evaluate_view(mean, var, gt, max_spearman_pixels=500, seed=3)["spearman_rho"] == sub["spearman_rho"]
    idx = np.sort(np.random.default_rng(3).choice(2000, size=500, replace=False))
    ref = stats.spearmanr(var.ravel()[idx], a.ravel()[idx]).statistic
    assert sub["spearman_rho"] == pytest.approx(ref, abs=1e-12)


# ------------------------------------------------------------------------- masks, torch, summary
def test_mask_and_torch_inputs():
    mean, var, gt = _calibrated_view(8, 16, 12)
    mask = np.zeros((16, 12), dtype=bool)
    mask[3:11, 2:9] = True
    res = evaluate_view(mean, var, gt, mask=mask)
    ref = evaluate_view(mean[mask][:, None], var[mask][:, None], gt[mask][:, None])
    for k in ("n_pixels", "ause_rmse", "ause_mae", "ece", "cov95", "nll", "spearman_rho"):
        assert res[k] == pytest.approx(ref[k], abs=1e-12)
    assert res["n_pixels"] == 56
    rt = evaluate_view(torch.tensor(mean, dtype=torch.float32), torch.tensor(var, dtype=torch.float32),
                       torch.tensor(gt, dtype=torch.float32), mask=torch.from_numpy(mask))
    assert rt["n_pixels"] == 56
    assert rt["cov95"] == pytest.approx(res["cov95"], abs=0.02)


def test_summarize_means_and_json(tmp_path):
    views = [evaluate_view(*_calibrated_view(s, 16, 16)) for s in range(3)]
    const = _calibrated_view(9, 16, 16)
    views.append(evaluate_view(const[0], np.ones((16, 16)), const[2]))  # constant var -> rho NaN
    assert math.isnan(views[-1]["spearman_rho"])
    s = summarize(views)
    assert s["n_views"] == 4
    for k in ("ause_rmse", "ause_mae", "ece", "cov95", "cov95_err", "nll"):
        assert s[k] == pytest.approx(np.mean([v[k] for v in views]))
    assert s["spearman_rho"] == pytest.approx(np.mean([v["spearman_rho"] for v in views[:3]]))
    assert s["n_finite"] == {"spearman_rho": 3}
    assert s["n_pixels"] == 4 * 256
    assert "regime" in s["nll_note"] and "per view" in s["aggregation_note"]
    assert s["ause_normalization"] == M.AUSE_NORMALIZATION_RAW
    assert all("curves" not in v for v in s["per_view"]) and len(s["per_view"]) == 4
    assert "curves" in summarize(views, keep_curves=True)["per_view"][0]
    np.testing.assert_allclose(s["mean_curves"]["rmse"]["oracle"],
                               np.mean([v["curves"]["rmse"]["oracle"] for v in views], axis=0))
    write_json(tmp_path / "uq.json", to_jsonable(s))
    assert (tmp_path / "uq.json").stat().st_size > 0
    with pytest.raises(ValueError):
        summarize([views[0], evaluate_view(*_calibrated_view(0, 16, 16), normalize=True)])
    with pytest.raises(ValueError):
        summarize([])


# ------------------------------------------------------------------------------------ bad inputs
def test_bad_inputs_raise():
    mean, var, gt = _calibrated_view(10, 4, 5)
    with pytest.raises(ValueError, match="gt shape"):
        evaluate_view(mean, var, gt[:3])
    with pytest.raises(ValueError, match="var must have shape"):
        evaluate_view(mean, np.ones((4, 5, 3)), gt)
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        evaluate_view(mean[..., :2], var, gt[..., :2])
    bad = mean.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        evaluate_view(bad, var, gt)
    with pytest.raises(ValueError, match="NaN"):
        evaluate_view(mean, var, np.where(gt > 0.5, np.inf, gt))
    with pytest.raises(ValueError, match=">= 0"):
        evaluate_view(mean, var - 1.0, gt)
    v = var.copy()
    v[1, 1] = np.inf
    with pytest.raises(ValueError, match="NaN or Inf"):
        evaluate_view(mean, v, gt)
    with pytest.raises(ValueError, match="mask must have shape"):
        evaluate_view(mean, var, gt, mask=np.ones((5, 4), dtype=bool))
    with pytest.raises(TypeError, match="bool"):
        evaluate_view(mean, var, gt, mask=np.ones((4, 5)))
    with pytest.raises(ValueError, match="no pixels"):
        evaluate_view(mean, var, gt, mask=np.zeros((4, 5), dtype=bool))
    with pytest.raises(ValueError, match="fractions"):
        evaluate_view(mean, var, gt, fractions=[0.0, 0.5, 1.0])
    with pytest.raises(ValueError, match="levels"):
        evaluate_view(mean, var, gt, levels=[0.5, 1.0])
    with pytest.raises(ValueError, match="var_floor"):
        gaussian_nll(mean, var, gt, var_floor=0.0)
    with pytest.raises(ValueError, match="metric"):
        sparsification(var.ravel(), var.ravel(), metric="psnr")


# ----------------------------------------------------------------------------------------- plots
def test_plots_write_pngs(tmp_path):
    from b3dgs.uq.plots import plot_reliability, plot_sparsification, plot_uncertainty_panel

    mean, var, gt = _calibrated_view(11, 24, 32)
    native = evaluate_view(mean, var, gt)
    proxy = evaluate_view(mean, var * 0.01, gt)
    summary = summarize([native])
    p1 = plot_sparsification({"native": native["curves"], "proxy": proxy, "scene": summary},
                             tmp_path / "sub" / "spars.png")
    p2 = plot_reliability({"native": native["curves"]["calibration"], "proxy": proxy["curves"]},
                          tmp_path / "rel.png")
    a, _ = M.per_pixel_errors(mean, gt)
    arr = plot_uncertainty_panel(torch.tensor(mean), gt, a, np.sqrt(var), tmp_path / "panel.png", "view 0")
    for p in (p1, p2, tmp_path / "panel.png"):
        assert p.is_file() and p.stat().st_size > 1000
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert arr.dtype == np.uint8 and arr.ndim == 3 and arr.shape[2] == 3 and arr.std() > 0
    assert not [q for q in tmp_path.rglob("*.tmp")]
    assert plot_uncertainty_panel(mean, gt, a, var, None).shape == arr.shape
    with pytest.raises(ValueError):
        plot_uncertainty_panel(mean, gt, a[:3], var, None)
