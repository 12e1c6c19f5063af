"""acquisition=info_gain (issue 42): both objectives against a float64 brute force, the predictive score against the
variance of rendered colours under posterior draws, exact conditioning, a known geometric answer, and bad input."""

import pytest
import torch
from torch import nn

from b3dgs.acquisition import ScoringContext
from b3dgs.errors import B3dgsError
from b3dgs.numerics import guard_counts, reset_guards
from b3dgs.render.projection import sh_basis
from b3dgs.types import Camera
from tests.test_acquisition import _cfg, _policy, hole_setup  # noqa: F401 - the shared fixture


def _tiny(sh_degree=1, sh0=None):
    """A float64 model of 12 Gaussians on the synthetic scene, pure-torch renderer (exact weight sums)."""
    from b3dgs.data.scene import load_scene
    from b3dgs.lifecycle import build_module, build_plugins

    cfg = _cfg(["renderer=torch", "model.init_max_points=12", "model.init_num_random=0",
                f"model.sh_degree={sh_degree}"])
    scene = load_scene("synthetic", None, max_side=8, n_views=8)
    strategy, blocks = build_plugins(cfg)
    m = build_module(cfg, strategy, blocks)
    m.init_from_scene(scene)
    m.splats = nn.ParameterDict({k: nn.Parameter(v.detach().double()) for k, v in m.splats.items()})
    if sh0 is not None:  # colours far from the clamp at 0, so colour is linear in the SH coefficients
        m.splats["sh0"].data.fill_(sh0)
        m.splats["shN"].data.zero_()
    m.bg = m.bg.double()
    m._loaded_step = 10_000

    def f64(c):
        img = None if c.image is None else c.image.double()
        return Camera(c.name, c.K.double(), c.viewmat.double(), c.width, c.height, img)

    return m, [f64(c) for c in scene.train]


def _information(m, cam, sigma2):
    """(N, B, B) explicit s·y yᵀ of one view: Σ_p w² / σ² times the SH basis toward the view, per Gaussian."""
    deg = m.active_sh_degree()
    means = m.splats["means"].detach().double()
    wsq = m.render_camera(cam, return_weights=True).weight_sq_sum.reshape(-1).double()
    y = sh_basis(deg, torch.nn.functional.normalize(means - cam.center.double(), dim=-1))
    return (wsq / sigma2)[:, None, None] * (y[:, :, None] * y[:, None, :])


def _brute(m, train, cands, targets, tau, sigma2, objective):
    """Every score from explicit B x B matrices and inverses (float64)."""
    deg = m.active_sh_degree()
    means = m.splats["means"].detach().double()
    N, B = means.shape[0], (deg + 1) ** 2

    def J(cam):
        return _information(m, cam, sigma2)

    lam = tau * torch.eye(B, dtype=torch.float64).expand(N, B, B) + sum(J(c) for c in train)
    P = torch.linalg.inv(lam)
    G = sum(J(c) for c in targets)
    out = []
    for c in cands:
        Jc = J(c)
        if objective == "params":
            out.append(3 * 0.5 * float(torch.linalg.slogdet(torch.eye(B, dtype=torch.float64) + P @ Jc)[1].sum()))
        else:
            out.append(3 * float(((P - torch.linalg.inv(lam + Jc)) @ G).diagonal(dim1=-2, dim2=-1).sum()))
    return torch.tensor(out, dtype=torch.float64)


@pytest.mark.parametrize("objective,targets", [("predictive", "pool"), ("predictive", "pool+train"), ("params", "pool")])
def test_both_objectives_match_a_float64_brute_force(objective, targets):
    m, views = _tiny(sh_degree=2)
    train, cands = views[:3], views[3:]
    ctx = ScoringContext([m], train, score_max_side=None)
    pol = _policy("info_gain", objective=objective, targets=targets, posterior={"sh": {"prior_precision": 2.0}})
    got = pol.score(ctx, cands)
    s2 = pol._state["sigma2"]
    ref = _brute(m, train, cands, cands + (train if targets == "pool+train" else []), 2.0, s2, objective)
    assert ref.abs().max() > 0
    torch.testing.assert_close(got, ref, rtol=1e-9, atol=1e-12)


def test_predictive_score_is_the_drop_of_rendered_colour_variance_under_posterior_draws():
    """Draw the SH coefficients from the posterior before and after a candidate's information, render the targets,
    and compare the drop of the summed pixel variance (in units of σ̂²) with the closed form (Monte Carlo, 4000 draws,
    the same normal draws before and after, so their noise largely cancels in the difference)."""
    m, views = _tiny(sh_degree=1, sh0=0.0)
    train, cands = views[:3], views[3:6]
    tau = 100.0  # small colour spread: the clamp at 0 never binds
    ctx = ScoringContext([m], train, score_max_side=None)
    pol = _policy("info_gain", posterior={"sh": {"prior_precision": tau}})
    scores = pol.score(ctx, cands)
    st = pol._state
    deg, s2 = st["deg"], st["sigma2"]
    means = m.splats["means"].detach().double()
    N, B = means.shape[0], (deg + 1) ** 2

    def J(cam):
        return _information(m, cam, s2)

    lam = tau * torch.eye(B, dtype=torch.float64).expand(N, B, B) + sum(J(c) for c in train)
    S = 4000

    def total_var(precision):
        L = torch.linalg.cholesky(torch.linalg.inv(precision))
        z = torch.randn(S, N, B, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
        delta = torch.einsum("nij,snjc->snic", L, z)
        p = {k: v.detach() for k, v in m.params().items()}
        p["sh0"] = p["sh0"] + delta[:, :, :1]
        assert p["shN"].shape[-2] == B - 1  # a degree-1 model: every SH coefficient is drawn
        p["shN"] = p["shN"] + delta[:, :, 1:]
        return sum(float(m.render_camera(t, params=p).rgb.var(0).sum()) for t in cands)

    before = total_var(lam)
    for i, c in enumerate(cands):
        mc = (before - total_var(lam + J(c))) / s2
        assert float(scores[i]) > 0
        assert mc == pytest.approx(float(scores[i]), rel=0.1), (i, mc, float(scores[i]))


def test_conditioning_equals_recomputing_the_posterior_with_the_view():
    m, views = _tiny(sh_degree=2)
    train, cands = views[:3], views[3:]
    for objective in ("predictive", "params"):
        pol = _policy("info_gain", objective=objective)
        ctx = ScoringContext([m], train, score_max_side=None)
        first = pol.score(ctx, cands)
        assert pol.condition(ctx, cands[0]) is True
        cond = pol.score(ctx, cands)
        ratio = pol.conditioned_ratio(ctx, cands, range(len(cands)))
        # the view among the training views, without its image (σ̂² comes from the training images alone)
        fresh = _policy("info_gain", objective=objective)
        ctx2 = ScoringContext([m], train + [cands[0].with_image(None)], score_max_side=None)
        ref = fresh.score(ctx2, cands)
        torch.testing.assert_close(cond, ref, rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(ratio * first, cond, rtol=1e-9, atol=1e-12)
        assert float(cond[0]) < float(first[0])  # the picked view is worth less once it is known
        pol.reset_conditioning(ctx)
        torch.testing.assert_close(pol.score(ctx, cands), first, rtol=0, atol=0)


def test_greedy_conditioned_batch_runs_and_differs_from_top_k_only_through_conditioning(hole_setup):
    from b3dgs.study.active import load_batch
    from hydra import initialize_config_dir

    from b3dgs.train import CONF_DIR

    model, scene, _, _ = hole_setup
    ctx = ScoringContext([model], scene.train, score_max_side=32, extent=scene.extent, seed=0)
    pol = _policy("info_gain")
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        sel = load_batch("greedy_conditioned").select(pol, ctx, scene.candidates, 3)
    assert len(set(sel.indices)) == 3 and "fallback" not in sel.info
    # the conditioned score of each pick is what a fresh scoring with the earlier picks as training views gives
    picks = [scene.candidates[i] for i in sel.indices]
    fresh = _policy("info_gain")
    ctx2 = ScoringContext([model], list(scene.train) + [picks[0].with_image(None)], score_max_side=32,
                          extent=scene.extent, seed=0)
    s = fresh.score(ctx2, scene.candidates)
    assert sel.info["conditioned_scores"][1] == pytest.approx(float(s[sel.indices[1]]), rel=1e-9)


def test_a_view_from_an_unseen_side_scores_far_above_one_that_repeats_seen_directions(hole_setup):
    model, scene, _, unobserved = hole_setup
    # three of the training views taken five times each: their directions are seen many times
    many = list(scene.train) + [c for c in scene.train[:3] for _ in range(4)]
    ctx = ScoringContext([model], many, score_max_side=32, extent=scene.extent, seed=0)
    repeats = [c.with_image(None) for c in scene.train[:3]]  # a sixth copy of each
    hole = [c for c in scene.candidates if c.name in unobserved][:3]
    for name, factor in (("info_gain", 5.0), ("info_gain_params", 2.5)):  # the log gain saturates more slowly
        s = _policy(name).score(ctx, repeats + hole)
        assert float(s[3:].min()) > factor * float(s[:3].max()), (name, s)


def test_bad_input_is_refused_in_one_line_or_counted():
    with pytest.raises(B3dgsError, match="objective=.*fix"):
        _policy("info_gain", objective="entropy").validate()
    with pytest.raises(B3dgsError, match="targets=.*fix"):
        _policy("info_gain", targets="test").validate()
    with pytest.raises(B3dgsError, match="prior_precision.*fix"):
        _policy("info_gain", posterior={"sh": {"prior_precision": 0.0}}).validate()
    m0, views0 = _tiny(sh_degree=0)
    with pytest.raises(B3dgsError, match="SH degree 0.*fix"):
        _policy("info_gain").score(ScoringContext([m0], views0[:2]), views0[2:4])
    m, views = _tiny(sh_degree=1)
    reset_guards()
    away = views[3]
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))  # looks the other way: sees nothing
    away = Camera("away", away.K, flip @ away.viewmat, away.width, away.height, None)
    s = _policy("info_gain").score(ScoringContext([m], views[:3]), [away, views[4]])
    assert float(s[0]) == 0.0 and float(s[1]) > 0 and guard_counts().get("sh.empty_view") == 1
    ctx = ScoringContext([m], views[:3])
    render = ctx.render

    def nan_weights(camera, **kw):  # a renderer that gives one NaN weight sum: counted and left out
        out = render(camera, **kw)
        if kw.get("return_weights"):
            out.weight_sq_sum.reshape(-1)[0] = float("nan")
        return out

    ctx.render = nan_weights
    s = _policy("info_gain").score(ctx, views[3:5])
    assert torch.isfinite(s).all() and guard_counts().get("sh.invalid_weights", 0) > 0
    reset_guards()


# ---------------------------------------------------------------------------------------------- geometry=true
def _exact_fisher(ctx, cam):
    """(N, 3, 3) Σ_p Σ_c ∇_μ C_pc ∇_μ C_pcᵀ from every pixel and channel's own gradient (no probes), float64."""
    from b3dgs.fisher import pixel_set_grads

    p = ctx.params()
    p["means"].requires_grad_(True)
    with torch.enable_grad():
        rgb = ctx.render(cam, params=p, grad=True).rgb
        F = torch.zeros(p["means"].shape[0], 3, 3, dtype=torch.float64)
        for (g,) in pixel_set_grads(rgb, [p["means"]], max(rgb.shape[:2]), per_channel=True):
            F += g.double()[:, :, None] * g.double()[:, None, :]
    return F


def _brute_geometry(Fs_train, Fs_cands, Fs_targets, tau, sigma2, objective):
    """The centres' term from explicit 3 x 3 matrices and inverses (float64)."""
    eye = torch.eye(3, dtype=torch.float64)
    lam = tau * eye + sum(F / sigma2 for F in Fs_train)
    P = torch.linalg.inv(lam)
    G = sum(F / sigma2 for F in Fs_targets)
    out = []
    for F in Fs_cands:
        J = F / sigma2
        if objective == "params":
            out.append(0.5 * float(torch.linalg.slogdet(eye + P @ J)[1].sum()))
        else:
            out.append(float(((P - torch.linalg.inv(lam + J)) @ G).diagonal(dim1=-2, dim2=-1).sum()))
    return torch.tensor(out, dtype=torch.float64)


def test_geometry_off_is_the_colour_score_bit_for_bit_and_renders_no_gradient():
    m, views = _tiny(sh_degree=2)
    train, cands = views[:3], views[3:]
    assert _policy("info_gain").geometry is False and _policy("info_gain_params").geometry is False
    for name in ("info_gain", "info_gain_params"):
        off = _policy(name)
        off.view_fisher = None  # never called: calling it would raise
        got = off.score(ScoringContext([m], train, score_max_side=None), cands)
        on = _policy(name + "_geometry")
        on.score(ScoringContext([m], train, score_max_side=None), cands)
        colour = torch.tensor([on._sh_gain(on._state, on._state["views"][c.name]) for c in cands], dtype=torch.float64)
        torch.testing.assert_close(got, colour, rtol=0, atol=0)
        assert off._state["geo"] is None and on._state["geo"] is not None


@pytest.mark.parametrize("objective,targets", [("predictive", "pool"), ("predictive", "pool+train"), ("params", "pool")])
def test_geometry_term_matches_a_float64_brute_force_from_exact_per_pixel_gradients(objective, targets):
    m, views = _tiny(sh_degree=1)
    train, cands = views[:3], views[3:]
    ctx = ScoringContext([m], train, score_max_side=None, extent=2.0)
    pol = _policy("info_gain_geometry", objective=objective, targets=targets, geometry_prior_scale=0.05)
    pol.view_fisher = _exact_fisher  # the F source, injected: no probes
    got = pol.score(ctx, cands)
    s2 = pol._state["sigma2"]
    tau = 1.0 / (0.05 * 2.0) ** 2
    assert pol._state["geo"]["tau"] == pytest.approx(tau, rel=1e-12)
    Ft, Fc = [_exact_fisher(ctx, c) for c in train], [_exact_fisher(ctx, c) for c in cands]
    geo = _brute_geometry(Ft, Fc, Fc + (Ft if targets == "pool+train" else []), tau, s2, objective)
    colour = _brute(m, train, cands, cands + (train if targets == "pool+train" else []), 1.0, s2, objective)
    assert geo.min() > 0 and geo.max() > 1e-3 * colour.max()  # the term is there and not lost in the colour's
    torch.testing.assert_close(got, colour + geo, rtol=1e-9, atol=1e-12)


def test_the_probe_estimate_of_a_views_fisher_is_the_exact_one_in_expectation():
    m, views = _tiny(sh_degree=1)
    ctx = ScoringContext([m], views[:3], score_max_side=None)
    exact = _exact_fisher(ctx, views[4])
    est = _policy("info_gain_geometry", geometry_probes=400).view_fisher(ctx, views[4])
    assert est.dtype == torch.float64 and est.shape == exact.shape
    tr = lambda F: F.diagonal(dim1=-2, dim2=-1).sum()  # noqa: E731
    assert float(tr(exact)) > 0 and float(tr(est)) == pytest.approx(float(tr(exact)), rel=0.1)
    assert float((est - exact).norm() / exact.norm()) < 0.2  # √(2/400) per entry, pooled over 12 Gaussians
    # the probes are drawn from the seed and the view's name: the same F whenever and wherever the view is scored
    again = _policy("info_gain_geometry", geometry_probes=400).view_fisher(ctx, views[4].with_image(None))
    torch.testing.assert_close(again, est, rtol=0, atol=0)


def test_geometry_conditioning_equals_recomputing_the_posterior_with_the_view():
    m, views = _tiny(sh_degree=1)
    train, cands = views[:3], views[3:]
    for objective in ("predictive", "params"):
        pol = _policy("info_gain_geometry", objective=objective, geometry_prior_scale=0.05)
        ctx = ScoringContext([m], train, score_max_side=None)
        first = pol.score(ctx, cands)
        geo_first = [pol._geo_gain(pol._state["geo"], pol._state["geo"]["views"][c.name]) for c in cands]
        assert pol.condition(ctx, cands[0]) is True
        cond = pol.score(ctx, cands)
        geo_cond = [pol._geo_gain(pol._state["geo"], pol._state["geo"]["views"][c.name]) for c in cands]
        ratio = pol.conditioned_ratio(ctx, cands, range(len(cands)))
        fresh = _policy("info_gain_geometry", objective=objective, geometry_prior_scale=0.05)
        ref = fresh.score(ScoringContext([m], train + [cands[0].with_image(None)], score_max_side=None), cands)
        torch.testing.assert_close(cond, ref, rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(ratio * first, cond, rtol=1e-9, atol=1e-12)
        assert geo_cond[0] < geo_first[0]  # the picked view's centres' information is known now
        pol.reset_conditioning(ctx)
        torch.testing.assert_close(pol.score(ctx, cands), first, rtol=0, atol=0)


def test_a_repeated_training_pose_teaches_the_centres_far_less_than_an_unseen_side(hole_setup):
    model, scene, _, unobserved = hole_setup
    many = list(scene.train) + [c for c in scene.train[:3] for _ in range(4)]
    ctx = ScoringContext([model], many, score_max_side=32, extent=scene.extent, seed=0)
    repeats = [c.with_image(None) for c in scene.train[:3]]
    hole = [c for c in scene.candidates if c.name in unobserved][:3]
    for name, factor in (("info_gain_geometry", 3.0), ("info_gain_params_geometry", 1.8)):  # the log saturates slower
        pol = _policy(name)
        pol.score(ctx, repeats + hole)
        geo = pol._state["geo"]
        g = [pol._geo_gain(geo, geo["views"][c.name]) for c in repeats + hole]
        assert min(g[3:]) > factor * max(g[:3]), (name, g)


def test_bad_geometry_settings_are_refused_in_one_line_and_bad_fisher_entries_counted():
    for bad in (0, -2, 1.5, True, "4"):
        with pytest.raises(B3dgsError, match="geometry_probes=.*fix"):
            _policy("info_gain_geometry", geometry_probes=bad).validate()
    for bad in (0.0, -0.1, float("inf"), float("nan"), True):
        with pytest.raises(B3dgsError, match="geometry_prior_scale=.*fix"):
            _policy("info_gain_geometry", geometry_prior_scale=bad).validate()
    with pytest.raises(B3dgsError, match="geometry=.*fix"):
        _policy("info_gain", geometry="yes").validate()
    m, views = _tiny(sh_degree=1)
    with pytest.raises(B3dgsError, match="extent.*fix"):
        _policy("info_gain_geometry").score(ScoringContext([m], views[:3], extent=float("nan")), views[3:5])
    reset_guards()
    pol = _policy("info_gain_geometry")
    probe = pol.view_fisher

    def nan_row(ctx, cam):  # one non-finite Fisher row per view: counted and left out
        F = probe(ctx, cam)
        F[0, 0, 0] = float("nan")
        return F

    pol.view_fisher = nan_row
    s = pol.score(ScoringContext([m], views[:3]), views[3:5])
    assert torch.isfinite(s).all() and guard_counts().get("info_gain.geometry_nonfinite", 0) == 5
    reset_guards()
