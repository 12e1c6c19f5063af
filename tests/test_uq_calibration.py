"""Issue 10: the constant-variance baseline, the NIW count scale, the calibration split and the
calibrated / conformal native regimes, and the epistemic decomposition."""
import dataclasses
import math
from statistics import NormalDist

import numpy as np
import pytest
import torch

from b3dgs.data import load_scene
from b3dgs.errors import B3dgsError
from b3dgs_plugins.posterior import niw as niwm
from b3dgs.uq.calibration import conformal_scale, fit_scale_and_level
from b3dgs.uq.metrics import coverage, epistemic_summary, epistemic_view
from b3dgs_plugins.posterior.niw import NIWBlock
from b3dgs_plugins.uq.constant import ConstantUQ
from b3dgs_plugins.uq.native import NativeUQ
from b3dgs_plugins.uq.native_calibrated import NativeCalibratedUQ, NativeConformalUQ
from test_uq_regimes import make_module  # a fresh model on a scene, opacities raised so geometry shows


@pytest.fixture(scope="module")
def scene():
    return load_scene("synthetic", None, max_side=48, n_views=32, calib_every=4)


def noisy(module, cams, sigma, gen):
    """The cameras with images = the model's render + N(0, sigma²) per value (unclipped)."""
    out = []
    for c in cams:
        r = module.render_eval(c)
        out.append(c.with_image(r + sigma * torch.randn(r.shape, generator=gen)))
    return out


# ------------------------------------------------------------------------------- uq=constant
@pytest.mark.parametrize("ratio", [1.0, 2.0])
def test_constant_cov95_equals_analytic_value(scene, ratio):
    """Residuals ~ N(0, σ²) on the training views and N(0, (ratio·σ)²) on the test views: σ̂² is the
    training MSE and Cov@95 = 2Φ(1.96·σ̂ / (ratio·σ)) − 1."""
    m = make_module(scene)
    gen = torch.Generator().manual_seed(1)
    sigma = 0.05
    sc = dataclasses.replace(scene, train=noisy(m, scene.train, sigma, gen),
                             test=noisy(m, scene.test, ratio * sigma, gen))
    reg = ConstantUQ()
    reg.fit([m], sc)
    assert reg.sigma2 == pytest.approx(sigma ** 2, rel=0.03)  # ~25k values: 1% standard error
    covs = []
    for cam in sc.test:
        pred = reg.predict(cam)
        assert float(pred.epistemic.abs().max()) == 0.0 and pred.aleatoric == reg.sigma2
        assert torch.all(pred.var == pred.var.flatten()[0])
        covs.append(coverage(pred.mean, pred.var, cam.image))
    analytic = 2 * NormalDist().cdf(1.959964 * math.sqrt(reg.sigma2) / (ratio * sigma)) - 1
    assert np.mean(covs) == pytest.approx(analytic, abs=0.01)
    if ratio == 2.0:
        assert abs(np.mean(covs) - 0.95) > 0.2  # too-narrow intervals are seen as such
    assert not ConstantUQ.has_epistemic and NativeUQ.has_epistemic


# ------------------------------------------------------------------------------- count scale
def test_count_scale_var_mu_grows_as_inverse_c_squared(scene):
    blk = NIWBlock()
    m = make_module(scene, {"niw": blk})
    st = m.states["niw"]
    st["N"].fill_(1e6)
    var = {}
    for c in (1.0, 1e-1, 1e-2, 1e-3):
        blk.count_scale = c
        post = blk.posterior(st, m.splats)
        var[c] = niwm.position_variance(post["S_n"], post["nu_n"], post["kappa_n"]).double()
    for c in (1e-1, 1e-2, 1e-3):  # c·N̂ >= 1e3 >> ν0: Var[μ] ≈ S0 / (c N̂)²
        ratio = (var[c] / var[1.0]).median().item()
        assert ratio == pytest.approx(1.0 / c ** 2, rel=0.02), (c, ratio)
    assert st["N"].max().item() == 1e6  # the stored summary is untouched

    # the posterior draws follow: the empirical variance of sampled centres grows about as 1/c²
    spread = {}
    for c in (1.0, 1e-2):
        blk.count_scale = c
        draw = blk.sampler(splats=m.splats, state=st)
        mu = draw(400, torch.Generator().manual_seed(0), {k: v.detach() for k, v in m.params().items()})["means"]
        spread[c] = mu.double().var(0).mean(-1).median().item()
    assert spread[1e-2] / spread[1.0] == pytest.approx(1e4, rel=0.25)


def test_count_scale_widens_native_spread(scene):
    blk = NIWBlock()
    m = make_module(scene, {"niw": blk})
    m.states["niw"]["N"].fill_(1e5)
    u = []
    for c in (1.0, 1e-2, 1e-4):
        blk.count_scale = c
        reg = NativeUQ(samples=6, chunk=3)
        reg.fit([m], scene)
        u.append(float(reg.predict(scene.test[0], torch.Generator().manual_seed(0)).epistemic.mean()))
    assert u[0] < u[1] < u[2], u
    with pytest.raises(ValueError, match="count_scale"):
        NIWBlock(count_scale=0.0).validate()


# ------------------------------------------------------------------------------- calibration split
def test_calibration_split_takes_training_views_only():
    full = load_scene("synthetic", None, max_side=16, n_views=40)
    sc = load_scene("synthetic", None, max_side=16, n_views=40, calib_every=4)
    names = lambda cs: [c.name for c in cs]  # noqa: E731
    assert names(sc.test) == names(full.test)
    assert sorted(names(sc.train) + names(sc.calib)) == sorted(names(full.train))
    assert names(sc.calib) == [c.name for j, c in enumerate(full.train) if (j + 1) % 4 == 0]
    assert not set(names(sc.calib)) & set(names(sc.test))
    assert all(c.image is not None for c in sc.calib)
    assert full.calib == []
    with pytest.raises(B3dgsError, match="calib_every"):
        load_scene("synthetic", None, max_side=16, n_views=40, calib_every=1)
    from b3dgs.data.datamodule import SceneDataModule

    dm = SceneDataModule(kind="synthetic", max_side=16, n_views=40, calib_every=4)
    assert names(dm.scene.calib) == names(sc.calib)


def test_calibration_never_renders_a_test_view(scene):
    m = make_module(scene, {"niw": NIWBlock()})
    m.states["niw"]["N"].fill_(10.0)
    m.states["niw"]["mse"].fill_(1e-3)  # the plug-in σ̂² of a trained run
    m.states["niw"]["mse_n"].fill_(1.0)
    seen = []
    render = m.render_camera

    def recording(camera, *a, **kw):
        seen.append(camera.name)
        return render(camera, *a, **kw)

    m.render_camera = recording
    for cls in (NativeCalibratedUQ, NativeConformalUQ):
        seen.clear()
        reg = cls(samples=4, chunk=2)
        reg.fit([m], scene)
        assert seen and set(seen) == {c.name for c in scene.calib}
        assert not set(seen) & {c.name for c in scene.test}
        assert reg.fit_info["calib_views"] == [c.name for c in scene.calib]


def test_calibrated_regimes_refuse_a_run_without_calibration_views(scene):
    m = make_module(scene, {"niw": NIWBlock()})
    bare = dataclasses.replace(scene, calib=[])  # the same scene without calibration views
    for cls in (NativeCalibratedUQ, NativeConformalUQ):
        with pytest.raises(B3dgsError) as e:
            cls(samples=2).fit([m], bare)
        assert "data.calib_every=16" in str(e.value) and "\n" not in str(e.value)


# ------------------------------------------------------------------------------- the fits
def synthetic_predictions(n, s_true, a_true, seed=0):
    rng = np.random.default_rng(seed)
    u = rng.lognormal(mean=math.log(1e-3), sigma=1.0, size=n)
    r = rng.normal(size=(n, 3)) * np.sqrt(s_true * u + a_true)[:, None]
    return u, r


def test_fit_recovers_known_miscalibration():
    s_true, a_true = 3.7, 2e-3  # u_p under-states the epistemic variance 3.7x; the aleatoric level is 2e-3
    u, r = synthetic_predictions(200_000, s_true, a_true)
    fit = fit_scale_and_level(u, (r ** 2).sum(-1))
    assert fit["s"] == pytest.approx(s_true, rel=0.05)
    assert fit["a"] == pytest.approx(a_true, rel=0.05)
    assert fit["converged"] and not fit["at_bound"]
    assert fit["nll"] < fit["nll_uncalibrated"]
    only_a = fit_scale_and_level(u, (r ** 2).sum(-1), fit_scale=False)
    assert only_a["s"] == 1.0 and only_a["a"] == pytest.approx(float((r ** 2).mean()))
    flat = fit_scale_and_level(np.zeros(1000), np.ones(1000))
    assert flat["a"] == pytest.approx(1 / 3) and not flat["s_identifiable"]


def test_calibrated_regime_recovers_scale_and_keeps_the_ranking(scene):
    """The regime on synthetic predictions: calibration views whose residuals have variance
    s*·u_p + a* with a known u_p (the regime's u_p is replaced by it)."""
    m = make_module(scene, {"niw": NIWBlock()})
    s_true, a_true = 0.25, 1e-3
    rng = np.random.default_rng(0)
    field = {}

    def u_of(cam):
        if cam.name not in field:
            field[cam.name] = torch.from_numpy(rng.lognormal(math.log(4e-3), 1.0, (cam.height, cam.width))).float()
        return field[cam.name]

    class Known(NativeCalibratedUQ):
        def spread(self, camera, generator=None):
            return torch.full((camera.height, camera.width, 3), 0.5), u_of(camera)

    calib = []
    for c in scene.calib:
        sd = (s_true * u_of(c).double() + a_true).sqrt()[..., None]
        calib.append(c.with_image((0.5 + sd * torch.from_numpy(rng.normal(size=(c.height, c.width, 3)))).float()))
    sc = dataclasses.replace(scene)
    sc.calib = calib
    reg = Known(samples=2)
    reg.fit([m], sc)
    assert reg.s == pytest.approx(s_true, rel=0.1) and reg.a == pytest.approx(a_true, rel=0.1)
    pred = reg.predict(scene.test[0])
    u = u_of(scene.test[0])
    assert torch.equal(torch.argsort(pred.var.flatten()), torch.argsort(u.flatten()))  # ranking from u_p


def test_conformal_quantile_covers_exchangeable_scores():
    rng = np.random.default_rng(0)
    conf = conformal_scale(np.abs(rng.standard_t(3, size=20_000)), 0.95)
    fresh = np.abs(rng.standard_t(3, size=200_000))
    cov = float(np.mean(fresh <= conf["q"]))
    assert cov >= 0.95 - 0.004 and cov == pytest.approx(0.95, abs=0.006)
    assert conf["rank"] == math.ceil(20_001 * 0.95)
    assert conf["multiplier"] == pytest.approx((conf["q"] / 1.959964) ** 2, rel=1e-6)
    assert conformal_scale(np.arange(10.0), 0.95)["q"] == math.inf  # ⌈11·0.95⌉ = 11 > 10 scores


# ------------------------------------------------------------------------------- decomposition
def test_epistemic_part_scored_alone():
    rng = np.random.default_rng(0)
    gt = rng.uniform(size=(20, 30, 3))
    mean = gt + rng.normal(scale=0.05, size=gt.shape)
    s = ((gt - mean) ** 2).mean(-1)
    good = epistemic_view(s, mean, gt, var=s + 0.01)
    assert good["epi_ause_rmse"] == pytest.approx(0.0, abs=1e-12)
    assert good["epi_spearman_sq"] == pytest.approx(1.0)
    assert good["epi_fraction"] == pytest.approx(s.mean() / (s.mean() + 0.01))
    bad = epistemic_view(rng.uniform(size=s.shape), mean, gt)
    assert bad["epi_ause_rmse"] > 0.005 and abs(bad["epi_spearman_sq"]) < 0.1
    assert math.isnan(epistemic_view(np.zeros_like(s), mean, gt)["epi_spearman_sq"])
    rows = [{"mean_epistemic": e, "mse": 2 * e, "mean_var": e + 1} for e in (0.1, 0.3, 0.2, 0.4)]
    summ = epistemic_summary(rows)
    assert summ["epi_view_spearman"] == pytest.approx(1.0) and summ["epi_view_n"] == 4
    assert summ["epistemic_fraction"] == pytest.approx(1.0 / 5.0)
    rows[0]["mse"] = 10.0
    assert epistemic_summary(rows)["epi_view_spearman"] < 1.0


# ------------------------------------------------------------------------------- end to end
def test_calib_run_trains_without_its_calibration_views_and_uq_json_reports_them(tmp_path):
    """A tiny NIW run with data.calib_every=4: validated config, calibration views out of training and
    out of the test set, and uq.json with the calibration view names, the fitted scalars and the
    epistemic decomposition for the regimes that have one (none for uq=constant)."""
    import json

    from b3dgs.eval import evaluate_uq
    from b3dgs_plugins.uq.constant import ConstantUQ
    from tests.inproc import train_here

    metrics = train_here(tmp_path, ["model=niw", "data.max_side=32", "+data.n_views=24", "data.calib_every=4",
                                    "trainer.max_steps=30", "trainer.enable_progress_bar=false", "logger=none",
                                    "trainer.save_renders=false"])
    full = load_scene("synthetic", None, max_side=32, n_views=24)
    assert metrics["num_train_views"] == len(full.train) - len(full.train) // 4
    res = evaluate_uq([str(tmp_path)], {"constant": ConstantUQ(), "native": NativeUQ(samples=3),
                                        "native_calibrated": NativeCalibratedUQ(samples=3)}, panels=0)
    saved = json.loads((tmp_path / "uq.json").read_text())
    calib = saved["_meta"]["calib_views"]
    assert calib == [c.name for j, c in enumerate(full.train) if (j + 1) % 4 == 0]
    assert not set(calib) & set(saved["_meta"]["views"])
    assert saved["native_calibrated"]["fit"]["calib_views"] == calib
    assert saved["native_calibrated"]["fit"]["s"] > 0 and saved["native_calibrated"]["fit"]["a"] > 0
    for name in ("native", "native_calibrated"):
        r = saved[name]
        assert r["has_epistemic"] and 0 < r["epistemic_fraction"] <= 1
        assert r["epi_ause_rmse"] is not None and -1 <= r["epi_spearman_sq"] <= 1
        assert all("epi_ause_rmse" in v for v in r["per_view"])
    # the calibrated variance keeps the native ranking: same AUSE of the epistemic part
    assert saved["native_calibrated"]["epi_ause_rmse"] == pytest.approx(saved["native"]["epi_ause_rmse"], rel=0.2)
    assert not saved["constant"]["has_epistemic"] and "epi_ause_rmse" not in saved["constant"]
    assert saved["constant"]["fit"]["sigma2"] > 0 and res["constant"]["samples"] == 0


def test_native_count_scale_override_widens_draws_and_leaves_the_model_alone(scene):
    """uq=native with count_scale draws from a copy of the block and state: more spread, same trained model."""
    from b3dgs_plugins.uq.native import NativeUQ

    m = make_module(scene, {"niw": NIWBlock()})
    m.states["niw"]["N"].fill_(1e5)  # a trained model's counts (the prior alone does not depend on c)
    m.posterior["niw"].posterior(m.states["niw"], m.splats)  # its posterior as training leaves it
    before = {k: v.clone() for k, v in m.states["niw"].items() if torch.is_tensor(v)}
    cam = scene.test[0]
    u = {}
    for c in (None, 0.01):
        reg = NativeUQ(samples=8, chunk=4, count_scale=c)
        reg.fit([m], scene)
        u[c] = float(reg.predict(cam, generator=torch.Generator().manual_seed(0)).epistemic.mean())
    assert u[0.01] > 2 * u[None] > 0
    assert m.posterior["niw"].count_scale == 1.0
    for k, v in before.items():
        assert torch.equal(m.states["niw"][k], v), k
