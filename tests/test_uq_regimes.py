"""Uncertainty regimes behave as their definitions say."""
import pytest
import torch

from b3dgs.data import load_scene
from b3dgs_plugins.posterior.niw import NIWBlock
from b3dgs_plugins.strategy.default import AdaptiveDensityControl
from b3dgs_plugins.uq.ensemble import EnsembleUQ
from b3dgs_plugins.uq.native import NativeUQ
from b3dgs_plugins.uq.ppu import PPUHead
from b3dgs_plugins.uq.proxy import ProxyUQ


@pytest.fixture(scope="module")
def scene():
    return load_scene("synthetic", None, max_side=32, n_views=16)


def make_module(scene, blocks=None, seed=0):
    from b3dgs.module import SplatModule

    m = SplatModule(strategy=AdaptiveDensityControl(), posterior=blocks or {}, renderer="cpu", max_steps=100, seed=seed)
    m.init_from_scene(scene)
    with torch.no_grad():
        m.splats["opacities"].fill_(2.0)  # visible, so geometry changes show in the render
    m._loaded_step = 0
    return m


def native_spread(scene, count):
    blk = NIWBlock()
    m = make_module(scene, {"niw": blk})
    st = m.states["niw"]
    st["N"].fill_(count)
    reg = NativeUQ(samples=8, chunk=4)
    reg.fit([m], scene)
    pred = reg.predict(scene.test[0], generator=torch.Generator().manual_seed(0))
    return float(pred.epistemic.mean()), pred


def test_native_spread_zero_when_collapsed_and_grows_as_kappa_shrinks(scene):
    collapsed, pred = native_spread(scene, 1e12)
    assert collapsed < 1e-8
    mid, _ = native_spread(scene, 10.0)
    wide, _ = native_spread(scene, 0.1)
    assert wide > mid > collapsed
    assert pred.var.shape == pred.mean.shape[:2]
    assert torch.all(pred.var >= pred.epistemic)  # aleatoric term added


def test_native_requires_posterior(scene):
    with pytest.raises(ValueError, match="posterior blocks"):
        NativeUQ(samples=2).fit([make_module(scene)], scene)


def test_proxy_spread_grows_with_jitter(scene):
    m = make_module(scene)
    spreads = []
    for jitter in (1e-4, 1e-3, 1e-2):
        reg = ProxyUQ(samples=6, chunk=3, jitter=jitter)
        reg.fit([m], scene)
        spreads.append(float(reg.predict(scene.test[0], torch.Generator().manual_seed(0)).var.mean()))
    assert spreads[0] < spreads[1] < spreads[2]
    with pytest.raises(ValueError, match="jitter"):
        ProxyUQ(jitter=0.0).fit([m], scene)


def test_ensemble_of_identical_members_has_zero_spread(scene):
    a, b = make_module(scene, seed=0), make_module(scene, seed=0)
    reg = EnsembleUQ()
    reg.fit([a, b], scene)
    assert float(reg.predict(scene.test[0]).var.max()) == 0.0
    c = make_module(scene, seed=1)
    with torch.no_grad():
        c.splats["means"].add_(0.01)
    reg.fit([a, c], scene)
    assert float(reg.predict(scene.test[0]).var.max()) > 0.0
    with pytest.raises(ValueError, match="run dirs"):
        EnsembleUQ().fit([a], scene)


def test_ppu_head_learns_error_scale(scene):
    from b3dgs.uq.metrics import gaussian_nll

    m = make_module(scene)
    cam = scene.test[0]
    nll = {}
    for steps in (0, 150):
        reg = PPUHead(steps=steps, lr=1e-2)
        reg.fit([m], scene)
        pred = reg.predict(cam)
        nll[steps] = float(gaussian_nll(pred.mean, pred.var, cam.image)["nll"])
    # training the head on the frozen model's train views improves the held-out likelihood
    assert nll[150] < nll[0] - 0.5, nll
