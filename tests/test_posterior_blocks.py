"""Posterior blocks as plugins: state alignment, posterior mean render, training with niw/dpmm."""
import json

import pytest
import torch

from b3dgs.data import load_scene
from b3dgs.metrics.image import psnr
from b3dgs_plugins.posterior.color import ColorBlock
from b3dgs_plugins.posterior.dp import DPBlock
from b3dgs_plugins.posterior.niw import NIWBlock
from b3dgs_plugins.posterior.noise import NoiseBlock
from b3dgs_plugins.posterior.opacity import OpacityBlock
from b3dgs_plugins.strategy.default import AdaptiveDensityControl
from test_train import QUICK, run_train


@pytest.fixture(scope="module")
def scene():
    return load_scene("synthetic", None, max_side=32, n_views=16)


def module_with_blocks(scene, blocks):
    from b3dgs.module import SplatModule

    m = SplatModule(strategy=AdaptiveDensityControl(), posterior=blocks, renderer="cpu", max_steps=100)
    m.init_from_scene(scene)
    m._loaded_step = 0
    opt = m.configure_optimizers()
    from b3dgs.ops import TopologyOps

    m.ops = TopologyOps(m.splats, {"gaussians": opt}, m.states, dict(m.plugins))
    return m


def test_block_state_follows_clone_split_prune(scene):
    blocks = {"niw": NIWBlock(), "dp": DPBlock(), "noise": NoiseBlock(), "opacity": OpacityBlock(), "color": ColorBlock()}
    m = module_with_blocks(scene, blocks)
    st = m.states["niw"]
    n = m.num_gaussians
    st["N"].copy_(torch.arange(n, dtype=torch.float64))  # a tag per Gaussian
    m.states["dp"]["usage"].copy_(torch.arange(n, dtype=torch.float64))
    mask = torch.zeros(n, dtype=torch.bool)
    mask[[3, 7]] = True
    m.ops.clone(mask)
    assert st["N"][-2:].tolist() == [1.5, 3.5]  # clones: half the parent's count (and the parent keeps its own)
    assert torch.equal(m.states["dp"]["usage"][-2:], torch.tensor([3.0, 7.0], dtype=torch.float64))
    mask = torch.zeros(n + 2, dtype=torch.bool)
    mask[5] = True
    m.ops.split(mask)
    # split children: prior re-centred at the child's birth, half the parent's count
    assert st["N"][-2:].tolist() == [2.5, 2.5]
    assert torch.allclose(st["m0"][-2:].float(), m.splats["means"].data[-2:])
    prune = torch.zeros(m.num_gaussians, dtype=torch.bool)
    prune[:10] = True
    m.ops.prune(prune, reason="test")
    k = m.num_gaussians
    for name, state in m.states.items():
        for key, v in state.items():
            if isinstance(v, torch.Tensor) and v.dim() >= 1:
                assert v.shape[0] == k, (name, key, tuple(v.shape))
    # the split parent (row 5) left, so the first ten kept rows were 0-4 and 6-10
    assert torch.equal(m.states["dp"]["usage"][:5], torch.arange(11, 16, dtype=torch.float64))


def test_posterior_mean_renders_the_point_estimate(scene):
    m = module_with_blocks(scene, {"niw": NIWBlock()})
    st = m.states["niw"]
    st["N"].fill_(2.0)  # a typical support count: m_n differs from the centre by kappa0/(kappa0+N) of the drift
    with torch.no_grad():
        m.splats["means"].add_(0.01 * torch.randn_like(m.splats["means"]))  # the centres moved since birth
    blk = m.posterior["niw"]
    cam = scene.test[0]
    point = m.render_eval(cam)
    pm = blk.posterior_mean(splats=m.splats, state=st, params={k: v.detach() for k, v in m.params().items()})
    mean_render = m.render_camera(cam, params=pm).rgb.clamp(0, 1)
    gt = cam.image
    assert abs(float(psnr(mean_render, gt)) - float(psnr(point, gt))) < 0.1


def test_niw_sample_replaces_only_geometry(scene):
    m = module_with_blocks(scene, {"niw": NIWBlock()})
    params = {k: v.detach() for k, v in m.params().items()}
    out = m.posterior["niw"].sample(splats=m.splats, state=m.states["niw"], n=4, generator=torch.Generator().manual_seed(0),
                                    params=params, info={})
    assert out["means"].shape == (4, m.num_gaussians, 3) and out["covars"].shape == (4, m.num_gaussians, 3, 3)
    for k in ("opacities", "sh0", "shN"):
        assert out[k] is params[k]
    assert torch.all(torch.linalg.eigvalsh(out["covars"].double()) > 0)


def test_unconfigured_blocks_cost_nothing(tmp_path):
    m = run_train(tmp_path, QUICK + ["trainer.max_steps=20", "trainer.eval_every=20"])
    assert m["posterior"] == {} and m["block_time_s"] == {}
    assert set(json.loads((tmp_path / "metrics.json").read_text())["removed"]) <= {"opacity"}


@pytest.mark.parametrize("model", ["niw", "dpmm"])
def test_short_training_with_posterior(tmp_path, model):
    overrides = QUICK + [f"model={model}", "trainer.max_steps=300", "trainer.eval_every=150", "strategy.refine_start=100",
                         "strategy.refine_stop=250", "strategy.refine_every=50"]
    if model == "dpmm":
        overrides += ["posterior.dp.t_dp=100", "posterior.dp.cavi_every=25", "posterior.opacity.t_post=150",
                      "posterior.color.t_post=150", "posterior.noise.t_noise=100"]
    m = run_train(tmp_path, overrides)
    assert m["psnr"] > 20.0
    assert set(m["block_time_s"]) == ({"niw"} if model == "niw" else {"niw", "dp", "noise", "opacity", "color"})
    from b3dgs.ply import read_ply

    ply = read_ply(tmp_path / "point_cloud.ply")
    assert "niw_pos_var" in ply["extra"] and "niw_kappa" in ply["extra"]
    assert torch.all(ply["extra"]["niw_pos_var"] > 0)
    if model == "dpmm":
        assert "dp" in m["removed"]  # the DP gate ran (it may remove 0 on this tiny scene)
        for key in ("dp_e_pi", "dp_e_a", "opacity_var", "color_var"):
            assert key in ply["extra"]
        assert m["posterior"]["noise"]["sigma2_mean"] > 0
        # the data (Fisher information) tightens the opacity posterior below its prior variance 1/τ₀ = 1
        assert m["posterior"]["opacity"]["median_logit_var"] < 0.5
    else:
        assert m["posterior"]["niw"]["sigma2_plugin"] > 0
    # checkpoints carry the posterior state, so a resumed run keeps it
    ck = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=False)
    assert "niw" in ck["b3dgs"]["states"] and ck["b3dgs"]["states"]["niw"]["N"].shape[0] == m["num_gaussians"]


@pytest.mark.slow
@pytest.mark.parametrize("model", ["niw", "dpmm"])
def test_short_training_on_real_scene(tmp_path, model):
    from conftest import SHARED

    path = SHARED / "data" / "ethiopian_head"
    if not path.exists():
        pytest.skip(f"shared scene not found at {path}")
    m = run_train(tmp_path, ["data=colmap", f"data.path={path}", "data.max_side=96", "trainer.enable_progress_bar=false",
                             "logger=none", f"model={model}", "trainer.max_steps=200", "trainer.eval_every=100",
                             "strategy.refine_start=50", "strategy.refine_stop=150", "strategy.refine_every=50"]
                  + (["posterior.dp.t_dp=100", "posterior.dp.cavi_every=25"] if model == "dpmm" else []))
    assert m["psnr"] > 14.0 and m["num_gaussians"] > 0


@pytest.mark.parametrize("cov_mode", ["relative", "absolute", "none"])
def test_prepared_sampler_draws_what_sample_draws(scene, cov_mode):
    """A block's prepared sampler (set-up once, used by uq=native for every chunk and view) gives the
    same draws as one-off ``sample`` calls; the default sampler of any block delegates to ``sample``."""
    m = module_with_blocks(scene, {"niw": NIWBlock(cov_mode=cov_mode), "opacity": OpacityBlock()})
    m.states["niw"]["N"].fill_(3.0)
    base = {k: v.detach() for k, v in m.params().items()}
    for name, blk in m.posterior.items():
        st = m.states[name]
        a = blk.sample(splats=m.splats, state=st, n=4, generator=torch.Generator().manual_seed(5), params=base, info={})
        draw = blk.sampler(splats=m.splats, state=st)
        b = draw(4, torch.Generator().manual_seed(5), base)
        assert a.keys() == b.keys()
        for k in a:
            assert torch.equal(a[k], b[k]), (name, k)
    p = m.posterior["niw"].sampler(splats=m.splats, state=m.states["niw"])(3, torch.Generator().manual_seed(0), base)
    assert p["means"].shape == (3,) + base["means"].shape
    assert ("covars" in p) == (cov_mode != "none")
    if cov_mode != "none":
        assert torch.equal(p["covars"], p["covars"].transpose(-1, -2))
        assert int(torch.linalg.cholesky_ex(p["covars"].double())[1].count_nonzero()) == 0
