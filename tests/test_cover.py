"""COVER acquisition policy (plugins/acquisition/cover.py): a known answer on a sphere of Gaussians, the greedy
batch, the Hydra option on a small trained model, refusals and determinism."""
import math

import pytest
import torch
from torch import nn

from b3dgs.acquisition import ScoringContext
from b3dgs.errors import B3dgsError
from tests.test_acquisition import _cfg, _policy, _ring, hole_setup  # noqa: F401 - hole_setup is a fixture


def _angle(cam):
    c = cam.center.double()
    return math.degrees(math.atan2(float(c[1]), float(c[0]))) % 360.0


def _apart(a, b):
    d = abs(_angle(a) - _angle(b)) % 360.0
    return min(d, 360.0 - d)


@pytest.fixture(scope="module")
def sphere():
    """A module whose Gaussians are 600 small opaque splats on the unit sphere; 24 cameras on a ring of radius 4."""
    from b3dgs.data.scene import load_scene
    from b3dgs.lifecycle import build_module, build_plugins
    from b3dgs_plugins.acquisition.cover import sphere_directions

    cfg = _cfg(["model.sh_degree=0"])
    m = build_module(cfg, *build_plugins(cfg))
    m.init_from_scene(load_scene("synthetic", None, max_side=8, n_views=2))
    n = 600
    m.splats = nn.ParameterDict({
        "means": nn.Parameter(sphere_directions(n, "cpu")), "scales": nn.Parameter(torch.full((n, 3), math.log(0.08))),
        "quats": nn.Parameter(torch.tensor([1.0, 0, 0, 0]).repeat(n, 1)),
        "opacities": nn.Parameter(torch.full((n,), 4.0)), "sh0": nn.Parameter(torch.full((n, 1, 3), 0.5)),
        "shN": nn.Parameter(torch.zeros(n, 0, 3))})
    return m, _ring(24, radius=4.0, size=24)


def test_cover_picks_the_unseen_side_first_and_then_no_near_duplicate(sphere):
    m, ring = sphere
    train = [ring[i] for i in (23, 0, 1)]  # -15, 0, +15 degrees: one side of the sphere seen
    cands = [c for c in ring if c not in train]
    pol = _policy("cover")
    sel = pol.select(ScoringContext([m], train), cands, 3)
    s = dict(zip([c.name for c in cands], sel.scores))
    unseen = [s[c.name] for c in cands if math.cos(math.radians(_angle(c))) < -0.5]
    seen = [s[c.name] for c in cands if math.cos(math.radians(_angle(c))) > 0.5]
    assert unseen and seen and min(unseen) > max(seen), (unseen, seen)
    first, second = cands[sel.indices[0]], cands[sel.indices[1]]
    assert _apart(first, ring[0]) >= 165  # the view opposite the training cameras
    # top-k on the first-round scores would take first's neighbour; the greedy rule goes elsewhere
    runner_up = cands[sorted(range(len(cands)), key=lambda i: -sel.scores[i])[1]]
    assert _apart(runner_up, first) <= 30
    assert _apart(second, first) >= 60, (first.name, second.name)
    # the greedy second pick is the first pick of COVER run with the first pick added to the training cameras
    rest = [c for c in cands if c is not first]
    again = pol.select(ScoringContext([m], train + [first]), rest, 1)
    assert rest[again.indices[0]].name == second.name
    # the first-round score is the select's score
    torch.testing.assert_close(pol.score(ScoringContext([m], train), cands),
                               torch.tensor(sel.scores, dtype=torch.float64))


@pytest.mark.parametrize("settings", [{}, {"visibility": "weights", "aggregate": "sum"}])
def test_cover_option_composes_and_prefers_views_of_an_unobserved_region(hole_setup, settings):
    from b3dgs_plugins.acquisition.cover import CoverPolicy

    model, scene, _, unobserved = hole_setup
    pol = _policy("cover", **settings)
    pol.validate()
    assert isinstance(pol, CoverPolicy) and pol.family == "standard" and pol.selects_batch
    if not settings:  # the YAML's values
        assert (pol.bins, pol.visibility, pol.min_weight, pol.aggregate) == (128, "frustum", 0.05, "mean")
    ctx = ScoringContext([model], scene.train, score_max_side=32, extent=scene.extent, seed=0)
    sel = pol.select(ctx, scene.candidates, 3)
    assert len(set(sel.indices)) == 3 and len(sel.scores) == len(scene.candidates)
    assert all(0.0 <= v <= 1.0 for v in sel.scores)
    hole = [v for c, v in zip(scene.candidates, sel.scores) if c.name in unobserved]
    seen = [v for c, v in zip(scene.candidates, sel.scores) if c.name not in unobserved]
    assert hole and seen and sum(hole) / len(hole) > sum(seen) / len(seen), (hole, seen)
    assert scene.candidates[sel.indices[0]].name in unobserved


@pytest.mark.parametrize("field,value", [("bins", 0), ("bins", 2.5), ("visibility", "occluded"),
                                         ("min_weight", -1.0), ("min_weight", float("nan")), ("aggregate", "max")])
def test_cover_refuses_bad_settings(field, value):
    with pytest.raises(B3dgsError, match=rf"cover\.{field}.*\(fix: "):
        _policy("cover", **{field: value}).validate()


def test_cover_refuses_bad_input_and_handles_empty_requests(sphere):
    m, ring = sphere
    pol = _policy("cover")
    ctx = ScoringContext([m], ring[:1])
    assert pol.select(ctx, [], 3).indices == [] and pol.score(ctx, []).numel() == 0
    assert pol.select(ctx, ring[1:4], 0).indices == []
    with pytest.raises(B3dgsError, match=r"no model.*\(fix: "):
        pol.select(ScoringContext([], ring[:1]), ring[1:3], 1)
    bad = ring[5].with_image(None)
    bad.viewmat = bad.viewmat.clone()
    bad.viewmat[0, 3] = float("nan")
    with pytest.raises(B3dgsError, match=r"'c05' has a non-finite pose.*\(fix: "):
        pol.select(ctx, [ring[3], bad], 1)
    empty = ScoringContext([m], [bad])  # a bad training camera is refused too
    with pytest.raises(B3dgsError, match="non-finite"):
        pol.score(empty, ring[1:3])
    saved = m.splats
    try:
        m.splats = nn.ParameterDict({k: nn.Parameter(v.detach()[:0]) for k, v in saved.items()})
        with pytest.raises(B3dgsError, match=r"no Gaussians.*\(fix: "):
            pol.select(ScoringContext([m], ring[:1]), ring[1:3], 1)
    finally:
        m.splats = saved


def test_cover_is_deterministic(sphere):
    m, ring = sphere
    train, cands = ring[:4], ring[4:]
    a = _policy("cover").select(ScoringContext([m], train), cands, 4)
    b = _policy("cover").select(ScoringContext([m], train), cands, 4)
    assert a.indices == b.indices and a.scores == b.scores
    assert len(set(a.indices)) == 4
