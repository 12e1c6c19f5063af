"""The directional SH posterior (``posterior.sh``, ``uq=[native_sh]``): the view pass's SH information against an
exact per-pixel autograd reference, the draws' covariance against Λ⁻¹, the direction it knows, and bad input."""
import math

import pytest
import torch

from b3dgs.data import load_scene
from b3dgs.errors import B3dgsError
from b3dgs.fisher import pixel_set_grads
from b3dgs.render.projection import sh_basis
from b3dgs_plugins.posterior.sh import SHInformation, SHPosteriorBlock
from test_counts import _one_gaussian_module
from test_posterior_blocks import module_with_blocks


@pytest.fixture(scope="module")
def scene():
    return load_scene("synthetic", None, max_side=24, n_views=8, n_points=300)


def _sh_module(scene):
    m = module_with_blocks(scene, {"sh": SHPosteriorBlock()})
    m._loaded_step = 10 ** 6  # the full SH degree
    with torch.no_grad():
        m.splats["shN"].normal_(0.0, 0.02, generator=torch.Generator().manual_seed(0))
    return m


def _information(m, sums):
    """(N, B, B) Σ_views Σ_p w_kp² y yᵀ of a pass's ``sh_views``, written out (y toward each view's centre)."""
    deg, means = sums["sh_views"]["degree"], m.splats["means"].detach().double()
    info = torch.zeros(m.num_gaussians, (deg + 1) ** 2, (deg + 1) ** 2, dtype=torch.float64)
    for centre, idx, wsq in sums["sh_views"]["views"]:
        y = sh_basis(deg, torch.nn.functional.normalize(means[idx] - centre.double(), dim=-1))
        info[idx] += wsq[:, None, None] * y[:, :, None] * y[:, None, :]
    return info


def test_view_pass_sh_information_matches_per_pixel_gradients(scene):
    """Σ_p w_kp² y yᵀ of the pass equals Σ_p ∇_A C_pc ∇_A C_pcᵀ (per channel) from autograd, one pixel at a time."""
    m = _sh_module(scene)
    cam = scene.train[0].resized(8, 8)
    sums = m.view_sums([cam], [SHInformation()])
    info = _information(m, sums)
    B = (m.active_sh_degree() + 1) ** 2
    assert tuple(info.shape) == (m.num_gaussians, B, B) and B == 16
    sp = m.params()
    sh0 = sp["sh0"].detach().clone().requires_grad_(True)
    shN = sp["shN"].detach().clone().requires_grad_(True)
    rgb = m.render_camera(cam, params={**{k: v.detach() for k, v in sp.items()}, "sh0": sh0, "shN": shN}).rgb
    exact = torch.zeros((3,) + tuple(info.shape), dtype=torch.float64)  # per channel
    for g0, gN in pixel_set_grads(rgb.reshape(8, 8, 3), [sh0, shN], stride=8, per_channel=True):
        g = torch.cat([g0, gN], dim=1).double()  # (N, B, 3): one channel is non-zero
        exact += torch.einsum("nic,njc->cnij", g, g)
    # a channel clamped at 0 has no gradient: compare the Gaussians whose three channels all have one
    tr = exact.diagonal(dim1=-2, dim2=-1).sum(-1)  # (3, N)
    seen = (tr > 0).all(0)
    assert int(seen.sum()) > 5
    for c in range(3):
        assert torch.allclose(info[seen], exact[c][seen], rtol=1e-4, atol=1e-12)
    unseen = (tr == 0).all(0)
    assert not bool(info[unseen].any())  # no information where the view has no gradient
    # the residual of the pass: the render against the view's image
    ref = (m.render_camera(cam).rgb.detach().double().reshape(-1) - cam.image.double().reshape(-1)).square()
    assert float(sums["sq_err"]) == pytest.approx(float(ref.sum()), rel=1e-9)
    assert float(sums["n_values"]) == ref.numel()


def test_draws_have_the_posterior_covariance(scene):
    """Draws of the block's sampler: mean Â, covariance Λ⁻¹ = (Σ w² y yᵀ/σ̂² + τI)⁻¹ per channel, float64."""
    m = _sh_module(scene)
    m.prepare_posterior()
    blk, st = m.posterior["sh"], m.states["sh"]
    sums = m.view_sums(accumulators=[SHInformation()])
    s2 = float(sums["sq_err"] / sums["n_values"])
    assert float(st["sigma2"]) == pytest.approx(s2)
    info = _information(m, sums)
    lam = info / s2 + blk.prior_precision * torch.eye(info.shape[-1], dtype=torch.float64)
    torch.testing.assert_close(st["lam"], lam, rtol=1e-12, atol=1e-12)
    k = int(info.diagonal(dim1=-2, dim2=-1).sum(-1).argmax())  # the best-observed Gaussian
    cov = torch.linalg.inv(lam[k])
    g = torch.Generator().manual_seed(1)
    p = blk.sampler(splats=m.splats, state=st)(4000, g, dict(m.params()))
    A = torch.cat([p["sh0"], p["shN"]], dim=-2)[:, k].double()  # (S, B, 3)
    base = torch.cat([m.splats["sh0"], m.splats["shN"]], dim=-2)[k].detach().double()
    dev = A - base
    assert float(dev.mean(0).abs().max()) < 4 * math.sqrt(float(cov.diagonal().max()) / 4000)
    emp = torch.einsum("sic,sjc->ij", dev, dev) / (3 * dev.shape[0])
    rel = (emp - cov).norm() / cov.norm()
    assert float(rel) < 0.05
    # the analytic colour variance along a direction matches y Λ⁻¹ y
    d = torch.nn.functional.normalize(torch.randn(m.num_gaussians, 3, dtype=torch.float64), dim=-1)
    v = blk.colour_variance(splats=m.splats, state=st, dirs=d)
    y = sh_basis(3, d[k])
    assert float(v[k]) == pytest.approx(float(y @ cov @ y), rel=1e-8)


def test_conditioning_on_a_view_equals_the_pass_with_it_and_only_a_render_conditions(scene):
    """The public method set (policies, tools): condition(view_information(render of a new view)) equals the pass
    over the training views plus that view (Λ and Λ⁻¹), leaves the given state alone, and the block hook
    condition_on_view does the same from a render and a camera, and nothing from weight sums alone."""
    m = _sh_module(scene)
    train, new_cam = scene.train[:3], scene.train[3].with_image(None)
    blk = m.posterior["sh"]
    st = blk.initialize_state(splats=m.splats, scene=None, info={})
    m.prepare_posterior(train, blocks=[("sh", blk, st)])
    lam0, cov0 = st["lam"].clone(), blk.covariance(st).clone()
    ro = m.render_camera(new_cam, return_weights=True)
    view = blk.view_information(state=st, camera=new_cam, render=ro, means=m.splats["means"])
    got = blk.condition(st, view)
    assert torch.equal(st["lam"], lam0) and torch.equal(st["cov"], cov0)  # the given state is not modified
    ref = blk.initialize_state(splats=m.splats, scene=None, info={})
    m.prepare_posterior(train + [new_cam], blocks=[("sh", blk, ref)])
    ref["sigma2"] = st["sigma2"]  # σ̂² comes from the training images alone (the new view has none)
    torch.testing.assert_close(got["lam"], blk.precision(
        [blk.view_information(state=ref, camera=c, render=m.render_camera(c, return_weights=True),
                              means=m.splats["means"]) for c in train + [new_cam]],
        n=m.num_gaussians, degree=m.active_sh_degree(), device="cpu"), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(got["cov"], torch.linalg.inv(got["lam"]), rtol=1e-7, atol=1e-12)
    assert float((got["cov"] - cov0).diagonal(dim1=-2, dim2=-1).sum()) < 0  # the view taught something
    hook = blk.condition_on_view(splats=m.splats, state=st, weight_sums=ro.weight_sum, render=ro, camera=new_cam)
    assert torch.equal(hook["cov"], got["cov"]) and torch.equal(hook["lam"], got["lam"])
    assert blk.condition_on_view(splats=m.splats, state=st, weight_sums=ro.weight_sum) is None


def test_a_colour_seen_from_one_side_is_uncertain_from_the_other():
    """Seen from +z only, the colour is certain looking from +z and uncertain from -z or x; a camera on x shrinks
    the x-variance. The paper's DC colour block (and the NIW geometry) give one variance for every direction."""
    one = _one_gaussian_module([(0, 0, 1), (0.05, 0, 1), (0, 0.05, 1)], blocks={"sh": SHPosteriorBlock()})
    blk = one.posterior["sh"]
    dirs = torch.tensor([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0]], dtype=torch.float64)

    def var(m, d):  # a camera looking along d (it sits at -3d) sees the Gaussian at the origin from direction d
        return float(blk.colour_variance(splats=m.splats, state=m.states["sh"], dirs=d[None])[0])

    front, back, side = (var(one, d) for d in dirs)
    assert back > 20 * front and side > 20 * front
    two = _one_gaussian_module([(0, 0, 1), (0.05, 0, 1), (0, 0.05, 1), (1, 0, 0)], blocks={"sh": SHPosteriorBlock()})
    assert var(two, dirs[2]) < 0.2 * side
    assert blk.summary(state=two.states["sh"])["computed"] is True


def test_native_sh_on_a_standard_model_and_bad_input(scene):
    from b3dgs_plugins.uq.native import NativeUQ

    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from b3dgs.train import CONF_DIR

    m = module_with_blocks(scene, {})
    m._loaded_step = 10 ** 6
    cfg = OmegaConf.load(f"{CONF_DIR}/uq/native_sh.yaml").native_sh
    cfg.samples = 4
    uq = instantiate(cfg)  # as b3dgs-eval builds it: Hydra keeps the nested block as a structured node
    uq.fit([m], scene)
    assert isinstance(uq._fitted[0][0], SHPosteriorBlock)
    from b3dgs.study.active import load_policy  # acquisition=native_sh / sh as the study composes them

    pol = load_policy("native_sh")[1]
    assert pol.uq().add is not None and pol.uq().model_blocks
    assert not load_policy("sh")[1].uq().model_blocks
    pred = uq.predict(scene.test[0])
    assert float(pred.epistemic.mean()) > 0 and uq.sigma2 > 0  # the added block's σ̂² on a standard model
    assert tuple(pred.var.shape) == tuple(pred.mean.shape[:-1])
    with pytest.raises(B3dgsError, match="at least one posterior block|posterior blocks"):
        NativeUQ(samples=2).fit([m], scene)
    with pytest.raises(B3dgsError, match=r"prior_precision=-1.*> 0"):
        SHPosteriorBlock(prior_precision=-1.0).validate()
    # drawn after a topology change without a new pass: refused with the fix
    blk, st = uq._fitted[0]
    m2 = module_with_blocks(scene, {})
    m2.splats["means"] = m2.splats["means"][:-3]
    with pytest.raises(B3dgsError, match="prepare_posterior"):
        blk.sample(splats=m2.splats, state=st, n=1, generator=None, params=dict(m2.params()), info={})


def test_sh_alone_leaves_out_the_model_blocks(scene):
    """uq=[sh] (model_blocks=false) on a NIW model draws the SH posterior only, with the pass's σ̂²."""
    from b3dgs_plugins.posterior.niw import NIWBlock
    from b3dgs_plugins.uq.native import NativeUQ

    m = module_with_blocks(scene, {"niw": NIWBlock()})
    m._loaded_step = 10 ** 6
    uq = NativeUQ(samples=2, chunk=2, model_blocks=False, add={"sh": SHPosteriorBlock()})
    uq.fit([m], scene)
    assert [type(b).__name__ for b, _ in uq._fitted] == ["SHPosteriorBlock"]
    assert uq.sigma2 == pytest.approx(float(uq._fitted[0][1]["sigma2"]))
    with pytest.raises(B3dgsError, match="posterior blocks"):
        NativeUQ(samples=2, model_blocks=False).fit([m], scene)


def test_a_model_carrying_the_sh_block_keeps_niws_sigma2(scene):
    """posterior=[niw,sh] with uq=native (c = 0.1) is uq=[native_plus_sh] on posterior=[niw], the combination the
    counts and active-view tables measured: NIW's plug-in σ̂² comes first (the SH pass residual is only a fallback,
    ``aleatoric_fallback``), and the draws are the same."""
    from b3dgs_plugins.posterior.niw import NIWBlock
    from b3dgs_plugins.uq.native import NativeUQ

    def model(blocks):
        torch.manual_seed(0)
        m = module_with_blocks(scene, blocks)
        m._loaded_step = 10 ** 6
        with torch.no_grad():
            m.splats["shN"].normal_(0.0, 0.02, generator=torch.Generator().manual_seed(0))
        m.states["niw"]["mse"] = torch.as_tensor(0.0123, dtype=torch.float64)
        m.states["niw"]["mse_n"] = torch.as_tensor(1.0, dtype=torch.float64)
        return m

    carried = NativeUQ(samples=4, chunk=2, count_scale=0.1)
    carried.fit([model({"niw": NIWBlock(), "sh": SHPosteriorBlock()})], scene)
    added = NativeUQ(samples=4, chunk=2, count_scale=0.1, add={"sh": SHPosteriorBlock()})
    added.fit([model({"niw": NIWBlock()})], scene)
    assert carried.sigma2 == pytest.approx(0.0123) and added.sigma2 == pytest.approx(0.0123)
    assert float(carried._fitted[1][1]["sigma2"]) != pytest.approx(0.0123)  # the SH pass's own residual
    pc = carried.predict(scene.test[0], generator=torch.Generator().manual_seed(1))
    pa = added.predict(scene.test[0], generator=torch.Generator().manual_seed(1))
    assert torch.allclose(pc.mean, pa.mean) and torch.allclose(pc.var, pa.var)
    assert float(pc.epistemic.mean()) > 0


def test_native_plus_sh_on_a_model_that_carries_the_sh_block(scene):
    """uq=[native_plus_sh] and acquisition=native_plus_sh as configured (Hydra) on a posterior=[niw,sh] model: the
    added SH block is the model's own, so the draws are uq=native's there; an added block with other settings than
    the model's is a one-line error naming the setting."""
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from b3dgs.train import CONF_DIR
    from b3dgs_plugins.posterior.niw import NIWBlock
    from b3dgs_plugins.uq.native import NativeUQ

    torch.manual_seed(0)
    m = module_with_blocks(scene, {"niw": NIWBlock(), "sh": SHPosteriorBlock()})
    m._loaded_step = 10 ** 6
    with torch.no_grad():
        m.splats["shN"].normal_(0.0, 0.02, generator=torch.Generator().manual_seed(0))
    cfg = OmegaConf.load(f"{CONF_DIR}/uq/native_plus_sh.yaml").native_plus_sh
    cfg.samples, cfg.chunk = 4, 2
    plus = instantiate(cfg)
    plus.fit([m], scene)
    assert plus.fit_info["add_carried"] == ["sh"]
    assert [type(b).__name__ for b, _ in plus._fitted] == ["NIWBlock", "SHPosteriorBlock"]
    own = NativeUQ(samples=4, chunk=2, count_scale=0.1)
    own.fit([m], scene)
    assert "add_carried" not in own.fit_info
    pp = plus.predict(scene.test[0], generator=torch.Generator().manual_seed(1))
    po = own.predict(scene.test[0], generator=torch.Generator().manual_seed(1))
    assert torch.equal(pp.var, po.var) and torch.equal(pp.mean, po.mean)
    from b3dgs.study.active import load_policy

    pol = load_policy("native_plus_sh")[1]
    pol.uq().fit([m], scene)  # the acquisition's regime (conf/uq/native_plus_sh.yaml) on the same model: accepted
    assert len(pol.uq()._fitted) == 2
    with pytest.raises(B3dgsError, match=r"add\.sh differs from the model's own sh block \(prior_precision 1\.0 vs 4\.0\)"):
        NativeUQ(samples=2, add={"sh": SHPosteriorBlock(prior_precision=4.0)}).fit([m], scene)


def test_sh_degree_0_is_refused_with_the_fix(scene):
    """A model without directional colour (SH degree 0) has nothing for the SH posterior to add: a run that would
    carry it is refused before training, and an evaluation that would add it is refused at its pass (issue 46 §5)."""
    from b3dgs.module import SplatModule
    from b3dgs_plugins.strategy.default import AdaptiveDensityControl
    from b3dgs_plugins.uq.native import NativeUQ

    with pytest.raises(B3dgsError, match="SH degree 0.*fix"):
        SplatModule(strategy=AdaptiveDensityControl(), posterior={"sh": SHPosteriorBlock()}, sh_degree=0,
                    renderer="cpu", max_steps=100)
    m = module_with_blocks(scene, {})  # at step 0 the model renders degree 0
    assert m.active_sh_degree() == 0
    with pytest.raises(B3dgsError, match="SH degree 0.*fix"):
        NativeUQ(samples=2, add={"sh": SHPosteriorBlock()}, model_blocks=False).fit([m], scene)
    m._loaded_step = 10 ** 6  # degree 3: accepted
    NativeUQ(samples=2, add={"sh": SHPosteriorBlock()}, model_blocks=False).fit([m], scene)


def test_viewer_sh_sigma_mode_and_native_label(scene):
    """b3dgs-view / b3dgs-render panel=sh_sigma: σ of draws of the SH coefficients alone (the uq=sh regime), on any
    run at SH degree >= 1; native σ's legend names every block it draws (issue 44 §5)."""
    from b3dgs.viewer.modes import ModeRenderer
    from b3dgs_plugins.posterior.niw import NIWBlock

    m = module_with_blocks(scene, {"niw": NIWBlock(), "sh": SHPosteriorBlock()})
    m._loaded_step = 10 ** 6
    with torch.no_grad():
        m.splats["shN"].normal_(0.0, 0.02, generator=torch.Generator().manual_seed(0))
    mr = ModeRenderer(m, scene, samples=4)
    assert "sh_sigma" in mr.available() and "sh_sigma" not in mr.unavailable()
    assert "niw, sh" in mr.specs["native_sigma"].what and "directional SH" in mr.specs["native_sigma"].what
    cam = scene.test[0]
    f = mr.render("sh_sigma", cam)
    assert f.values.shape == (cam.height, cam.width) and torch.isfinite(f.values).all()
    assert float(f.values.max()) > 0 and mr.regime("sh_sigma").model_blocks is False
    assert f.mode.hi == mr.specs["proxy_sigma"].hi  # one σ scale for the σ modes
