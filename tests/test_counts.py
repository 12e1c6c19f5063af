"""The NIW counts (``posterior.niw.count=paper|weight|fisher|fisher3``): the view pass against exact references,
the Fisher-to-count mapping against Eq. 2-3, the direction of fisher3's centre covariance, and bad inputs."""
import math

import pytest
import torch

from b3dgs.data import load_scene
from b3dgs.fisher import pixel_set_grads
from b3dgs.types import Camera
from b3dgs_plugins.posterior.niw import (COUNTS, FisherAccumulator, NIWBlock, fisher_count, mean_variance, niw_update,
                                        prior_scale_for_expected_cov)
from test_posterior_blocks import module_with_blocks


@pytest.fixture(scope="module")
def scene():
    return load_scene("synthetic", None, max_side=24, n_views=8, n_points=600)


def test_view_pass_fisher_matches_the_exact_per_pixel_sum(scene):
    """Hutchinson's estimator of Σ_p Σ_c ∇μ C_pc ∇μ C_pcᵀ (the view pass) against the exact sum over per-pixel
    gradients (pixel_set_grads with a stride of the image side: one pixel per backward pass), float64."""
    m = module_with_blocks(scene, {"niw": NIWBlock(count="fisher")})
    cams = [scene.train[0].resized(10, 10)]
    est = m.view_sums(cams, [FisherAccumulator(300)], seed=3)["fisher"]
    sp = m.params()
    means = sp["means"].detach().clone().requires_grad_(True)
    params = {**{k: v.detach() for k, v in sp.items()}, "means": means}
    exact = torch.zeros_like(est)
    for c in cams:
        rgb = m.render_camera(c, params=params).rgb
        for (g,) in pixel_set_grads(rgb, [means], stride=10, per_channel=True):
            g = g.double()
            exact += g.unsqueeze(-1) * g.unsqueeze(-2)
    te, tx = est.diagonal(dim1=-2, dim2=-1).sum(-1), exact.diagonal(dim1=-2, dim2=-1).sum(-1)
    assert float(tx.sum()) > 0
    assert float(te.sum() / tx.sum()) == pytest.approx(1.0, abs=0.06)  # unbiased; 300 probes: ~2-3 % on the total
    big = tx > 0.1 * tx.max()
    assert float(((te - tx).abs() / tx)[big].median()) < 0.2
    # weight sums of the pass are the renderer's, summed over the views
    ws = m.view_sums(cams)["weight_sum"]
    ref = sum(m.render_camera(c, return_weights=True).weight_sum.reshape(-1).double() for c in cams)
    assert torch.allclose(ws, ref)


def test_fisher_count_gives_the_laplace_precision_under_eq_2_3():
    """With N̂ = fisher_count(tr P), the NIW centre variance of Eq. 2-3 (x̄ = m0, C = 0) has mean per-axis precision
    tr P / D; a zero P gives N̂ = 0 (the prior)."""
    torch.manual_seed(0)
    A = torch.randn(5, 3, 3, dtype=torch.float64)
    cov = A @ A.transpose(-1, -2) * 1e-4 + 1e-6 * torch.eye(3, dtype=torch.float64)
    S0 = prior_scale_for_expected_cov(cov, 5.0)
    trP = torch.tensor([0.0, 1e2, 1e4, 1e6, 1e8], dtype=torch.float64)
    n = fisher_count(trP, S0, 0.01, 5.0)
    assert n[0] == 0 and bool((n[1:] > 0).all())
    m0 = torch.zeros(5, 3, dtype=torch.float64)
    _, k_n, nu_n, S_n = niw_update(m0, torch.full((5,), 0.01, dtype=torch.float64),
                                   torch.full((5,), 5.0, dtype=torch.float64), S0, n, m0, torch.zeros_like(S0))
    V = mean_variance(S_n, nu_n, k_n)
    prec = 1.0 / (V.diagonal(dim1=-2, dim2=-1).sum(-1) / 3)  # κ_n / mean E[Σ]_dd
    pos = n > 0
    # the mapping matches the mean per-axis precision κ_n / (tr E[Σ] / D) to tr P / D
    assert torch.allclose(prec[pos], trP[pos] / 3, rtol=1e-6)


def _one_gaussian_module(directions, blocks=None, sh_degree=3):
    """One small isotropic Gaussian at the origin seen by cameras looking at it along ``directions``; posterior
    ``blocks`` (default: NIW with the fisher3 count), prepared on those views."""
    from b3dgs.module import SplatModule
    from b3dgs.types import Scene
    from b3dgs_plugins.strategy.default import AdaptiveDensityControl

    def look(d):
        d = torch.tensor(d, dtype=torch.float64)
        z = d / d.norm()
        up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        if abs(float(z @ up)) > 0.9:
            up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
        x = torch.linalg.cross(up, z)
        x = x / x.norm()
        y = torch.linalg.cross(z, x)
        R = torch.stack([x, y, z])
        centre = -3.0 * z
        V = torch.eye(4, dtype=torch.float64)
        V[:3, :3], V[:3, 3] = R, -R @ centre
        return V.float()

    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])
    cams = [Camera(f"c{i}", K, look(d), 32, 32, torch.zeros(32, 32, 3)) for i, d in enumerate(directions)]
    sc = Scene("one", cams, cams[:1], points=torch.zeros(1, 3), point_colors=torch.full((1, 3), 0.8))
    blocks = {"niw": NIWBlock(count="fisher3")} if blocks is None else blocks
    m = SplatModule(strategy=AdaptiveDensityControl(), posterior=blocks, renderer="cpu", max_steps=10,
                    init_num_random=0, sh_degree=sh_degree, sh_increase_every=1)
    m.init_from_scene(sc)
    with torch.no_grad():
        m.splats["scales"].fill_(math.log(0.05))
        m.splats["opacities"].fill_(2.0)
        m.splats["quats"].copy_(torch.tensor([[1.0, 0, 0, 0]]))
        m.splats["means"].zero_()
    for name, blk in m.posterior.items():
        m.states[name] = blk.initialize_state(splats=m.splats, scene=sc, info={})
    if "niw" in m.states:
        m.states["niw"]["mse"] = torch.tensor(1e-3, dtype=torch.float64)
        m.states["niw"]["mse_n"] = torch.tensor(1.0, dtype=torch.float64)
    m._loaded_step = 10
    m.prepare_posterior(cams)
    return m


def test_fisher3_is_uncertain_along_the_rays_of_a_single_direction():
    """Seen only along z, the centre's posterior is widest along z (the depth no single view constrains); seen from
    z and x as well, the z-variance shrinks. The scalar counts cannot do this: their Var[μ] is shaped like Σ_k."""
    one = _one_gaussian_module([(0, 0, 1), (0.05, 0, 1), (0, 0.05, 1)])
    cov = one.posterior["niw"].export(splats=one.splats, state=one.states["niw"])
    c1 = torch.cholesky_inverse(one.states["niw"]["mu_prec_chol"])[0]
    evals, evecs = torch.linalg.eigh(c1)
    assert abs(float(evecs[2, -1])) > 0.95  # the largest variance is along z
    assert float(evals[-1] / evals[0]) > 10
    two = _one_gaussian_module([(0, 0, 1), (1, 0, 0)])
    c2 = torch.cholesky_inverse(two.states["niw"]["mu_prec_chol"])[0]
    assert float(c2[2, 2]) < 0.2 * float(c1[2, 2])
    assert float(cov["niw_pos_var"][0]) > 0


def test_counts_validate_and_degrade_gracefully(scene):
    from b3dgs.numerics import guard_counts, reset_guards

    with pytest.raises(ValueError, match=r"posterior.niw.count=fishr is not a count.*did you mean fisher"):
        NIWBlock(count="fishr").validate()
    with pytest.raises(ValueError, match=r"fisher_probes must be an integer >= 1"):
        NIWBlock(fisher_probes=0).validate()
    assert COUNTS == ("paper", "weight", "fisher", "fisher3")
    reset_guards()
    m = module_with_blocks(scene, {"niw": NIWBlock(count="fisher3")})
    st = m.states["niw"]
    # no residual tracked yet (σ̂² unknown): floored and counted; cameras that see nothing: zero counts, the prior
    away = [Camera("away", c.K, c.viewmat @ torch.diag(torch.tensor([1.0, 1.0, -1.0, 1.0])), c.width, c.height)
            for c in scene.train[:2]]
    m.prepare_posterior(away)
    assert guard_counts().get("niw.sigma2_floor", 0) >= 1
    assert float(st["N"].abs().max()) == 0.0 and bool(torch.isfinite(st["mu_prec_chol"]).all())
    # the weight count on the training views: non-negative, finite, and it sums the renderer's weights
    mw = module_with_blocks(scene, {"niw": NIWBlock(count="weight")})
    mw.prepare_posterior()
    n = mw.states["niw"]["N"]
    assert bool(torch.isfinite(n).all()) and float(n.min()) >= 0 and float(n.sum()) > 0


@pytest.mark.parametrize("count", ["paper", "fisher3"])
def test_the_count_pass_is_timed_into_the_blocks_share(tmp_path, count):
    """A count from a view pass (not the paper's EMA) is computed once after training: metrics.json records the
    pass's seconds (posterior_pass_s, 0 for the paper count) and the report's block share includes them."""
    from pathlib import Path

    from b3dgs.report.collect import Run
    from test_train import QUICK, run_train

    m = run_train(tmp_path, QUICK + ["model=niw", f"posterior.niw.count={count}", "trainer.max_steps=30",
                                     "trainer.eval_every=30", "strategy.refine_start=10", "strategy.refine_stop=25",
                                     "strategy.refine_every=10"])
    assert (m["posterior_pass_s"] > 0) == (count != "paper")
    share = Run(Path(tmp_path), {}, m).value("block_time_pct")
    blocks = sum(m["block_time_s"].values())
    assert share == pytest.approx(100 * (blocks + m["posterior_pass_s"]) / (m["train_time_s"] + m["posterior_pass_s"]))
