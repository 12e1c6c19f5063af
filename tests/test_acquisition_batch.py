"""Batch selection (issue 22): topk unchanged bit for bit, a known case where top-k picks duplicates and the
batch modes do not, conditioning the native posterior on a camera, the closed-form NIW update behind it,
and one-line errors for bad options."""
import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from b3dgs.acquisition import AcquisitionPolicy, ScoringContext, camera_centres
from b3dgs.errors import B3dgsError
from b3dgs.train import CONF_DIR
from b3dgs.types import Camera
from tests.test_acquisition import STUDY, _policy, _ring, hole_setup  # noqa: F401 - hole_setup is a fixture

BATCHES = ("topk", "diverse", "greedy_conditioned")


def _batch(name, **kw):
    from b3dgs.study.active import load_batch

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        b = load_batch(name)
    for k, v in kw.items():
        setattr(b, k, v)
    b.validate()
    return b


def _copy(cam, name):
    return Camera(name, cam.K, cam.viewmat, cam.width, cam.height, None)


def _crop(cam, x0, width, name):
    """The columns [x0, x0 + width) of ``cam``'s image: the same centre, other pixels (and Gaussians)."""
    K = cam.K.clone()
    K[0, 2] -= x0
    return Camera(name, K, cam.viewmat, width, cam.height, None)


# ------------------------------------------------------------------------------- topk: the old code path
def test_topk_is_the_policies_own_selection_bit_for_bit(hole_setup):
    """batch=topk gives what the study gave before batch options: for score-based policies the top-k of the
    scores computed as before (native/proxy: candidate i's draws salted with i), for the others their select."""
    from b3dgs_plugins.uq.native import NativeUQ
    from b3dgs_plugins.uq.proxy import ProxyUQ

    model, scene, store, _ = hole_setup
    cands = scene.candidates[:7]
    old = {  # the scoring code before issue 22, verbatim
        "native": lambda ctx: torch.stack([ctx.predict(NativeUQ(samples=4, chunk=8, count_scale=0.1), c, salt=i)
                                           .epistemic.double().mean() for i, c in enumerate(cands)]).cpu(),
        "proxy": lambda ctx: torch.stack([ctx.predict(ProxyUQ(samples=4, chunk=8, jitter=0.002), c, salt=i)
                                          .epistemic.double().mean() for i, c in enumerate(cands)]).cpu(),
    }
    topk = _batch("topk")
    for name in ("native", "proxy", "ensemble", "oracle", "ppu", "uniform", "farthest", "fisher"):
        kw = {"samples": 4} if name in ("native", "proxy") else {"steps": 5} if name == "ppu" else \
            {"pixel_stride": 4} if name == "fisher" else {}
        pol = _policy(name, **kw)

        def ctx():
            return ScoringContext([model] * int(pol.members), scene.train, score_max_side=12, extent=scene.extent,
                                  seed=3, ground_truth=store.image if pol.uses_ground_truth else None)

        got = topk.select(pol, ctx(), cands, 3)
        ref = pol.select(ctx(), cands, 3)
        assert got.indices == ref.indices and got.scores == ref.scores, name
        if name in old:
            s = old[name](ctx())
            order = sorted(range(len(s)), key=lambda i: (-float(s[i]), i))[:3]
            assert got.indices == order and got.scores == [float(v) for v in s], name
            sub = pol.score_at(ctx(), cands, [5, 2])  # a subset scores exactly as in the full call
            assert torch.equal(sub, s[[5, 2]]), name


# ------------------------------------------------------------------------------- a known duplicate case
@dataclass
class _DupScores(AcquisitionPolicy):
    """Candidates named 'dup*' score 1, the others 0.5; conditioning on a pick zeroes the score of every
    candidate within 0.5 of it (a toy posterior), or (``conditions=False``) is not offered."""

    conditions: bool = True

    def score(self, ctx, candidates):
        picked = getattr(self, "_picked", [])
        out = []
        for c in candidates:
            near = any(float((c.center - p.center).norm()) < 0.5 for p in picked)
            out.append(0.0 if near else (1.0 if c.name.startswith("dup") else 0.5))
        return torch.tensor(out, dtype=torch.float64)

    def condition(self, ctx, camera):
        if not self.conditions:
            return False
        self._picked = getattr(self, "_picked", []) + [camera]
        return True

    def reset_conditioning(self, ctx):
        self._picked = []


def _dup_ring():
    ring = _ring(12)
    v = ring[6].viewmat.clone()
    v[0, 3] += 0.01
    dups = [Camera("dup_a", ring[6].K, ring[6].viewmat, 8, 8, None), Camera("dup_b", ring[6].K, v, 8, 8, None)]
    cands = ring[1:6] + [Camera("dup_c", ring[6].K, ring[6].viewmat, 8, 8, None)] + ring[7:] + dups
    return ring[:1], cands


def test_topk_picks_duplicates_and_the_batch_modes_do_not():
    train, cands = _dup_ring()
    ctx = ScoringContext([], train)
    pol = _DupScores()
    names = {b: [cands[i].name for i in _batch(b).select(pol, ctx, cands, 3).indices] for b in BATCHES}
    assert sorted(names["topk"]) == ["dup_a", "dup_b", "dup_c"]
    for b in ("diverse", "greedy_conditioned"):
        assert sum(n.startswith("dup") for n in names[b]) == 1, (b, names[b])
    # far from the training camera c00 and from each other: diverse spreads the batch
    d = _batch("diverse").select(pol, ctx, cands, 3)
    xyz = camera_centres([cands[i] for i in d.indices])
    assert min(np.linalg.norm(xyz[i] - xyz[j]) for i in range(3) for j in range(i)) > 1.0
    assert d.scores == [float(v) for v in pol.score(ctx, cands)] and d.info["radius"] == 1.0
    # a policy that cannot condition: greedy_conditioned selects as diverse, and says why
    g = _batch("greedy_conditioned").select(_DupScores(conditions=False), ctx, cands, 3)
    assert g.indices == d.indices and g.info["fallback"] == "diverse" and "condition()" in g.info["reason"]
    # radius -> 0: top-k (the diminishing return vanishes), but for an exact copy of a chosen camera (d = 0)
    tiny = _batch("diverse", radius=1e-9).select(pol, ctx, cands, 3)
    assert [cands[i].name for i in tiny.indices] == ["dup_c", "dup_b", "c01"]


# ------------------------------------------------------------------------------- native conditioning
def test_native_conditioning_lowers_its_near_duplicates_and_greedy_skips_them(hole_setup):
    """Two crops of one hole camera see disjoint pixels: conditioning the NIW posterior on crop A lowers the
    native score of A's copies (same Gaussians) and leaves crop B's nearly as it was; top-k picks A twice,
    greedy_conditioned picks A then B. The model and the unconditioned scores are untouched afterwards."""
    model, scene, _, _ = hole_setup
    ctx = ScoringContext([model], scene.train, score_max_side=32, extent=scene.extent, seed=0)
    pol = _policy("native", samples=16)
    s = pol.score(ctx, scene.candidates)
    cam = scene.candidates[int(torch.argmax(s))]
    left, right = _crop(cam, 0, cam.width // 2, "L"), _crop(cam, cam.width // 2, cam.width - cam.width // 2, "R")
    sl, sr = pol.score(ctx, [left, right])
    a, b = (left, right) if sl >= sr else (right, left)
    pool = [a, _copy(a, "A1"), _copy(a, "A2"), b]
    n_before = model.states["niw"]["N"].clone()
    s0 = pol.score(ctx, pool)
    assert pol.condition(ctx, pool[0])
    s1 = pol.score(ctx, pool)
    ratio = s1 / s0
    assert float(ratio[1:3].max()) < 0.9 and float(ratio[3]) > 0.95, ratio  # A's copies drop, B barely moves
    est = pol.conditioned_ratio(ctx, pool, [1, 2, 3])  # the cheap estimate ranks them the same way
    assert float(est[:2].max()) < float(est[2]) and float((est - ratio[1:]).abs().max()) < 0.05, (est, ratio)
    pol.reset_conditioning(ctx)
    assert torch.equal(pol.score(ctx, pool), s0)
    assert torch.equal(model.states["niw"]["N"], n_before)
    top = _batch("topk").select(pol, ctx, pool, 2)
    greedy = _batch("greedy_conditioned").select(pol, ctx, pool, 2)
    assert b.name not in [pool[i].name for i in top.indices]
    assert [pool[i].name for i in greedy.indices][1] == b.name, greedy
    assert greedy.info["rescored_per_pick"] == [1] and "fallback" not in greedy.info
    assert torch.equal(pol.score(ctx, pool), s0)  # the selector undid its conditioning


def test_niw_condition_on_view_is_the_closed_form_update():
    """N̂ ← N̂ + w equals the paper's closed-form NIW update of the current posterior with n = c·w pseudo-
    observations at the current centres (C = 0), and leaves the given state as it was."""
    from b3dgs_plugins.posterior.niw import NIWBlock
    from b3dgs_plugins.posterior import niw as niwm

    g = torch.Generator().manual_seed(0)
    n = 6
    splats = {"means": torch.randn(n, 3, generator=g), "quats": torch.randn(n, 4, generator=g),
              "scales": torch.randn(n, 3, generator=g) * 0.3 - 2.0}
    blk = NIWBlock(count_scale=0.3)
    st = blk.initialize_state(splats=splats, scene=None, info={})
    st["m0"] = st["m0"] + 0.05 * torch.randn(n, 3, generator=g, dtype=torch.float64)  # centres moved since birth
    st["N"] = torch.rand(n, generator=g, dtype=torch.float64) * 50
    post = blk.posterior(st, splats)
    keep = {k: v.clone() for k, v in st.items() if torch.is_tensor(v)}
    w = torch.rand(n, generator=g, dtype=torch.float64) * 20
    w[0] = 0.0
    new = blk.condition_on_view(splats=splats, state=st, weight_sums=w)
    ref = niwm.niw_update(post["m_n"], post["kappa_n"], post["nu_n"], post["S_n"], 0.3 * w,
                          splats["means"].double(), None)
    for got, want in zip((new["m_n"], new["kappa_n"], new["nu_n"], new["S_n"]), ref):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)
    assert all(torch.equal(st[k], v) for k, v in keep.items())
    var = lambda s: torch.diagonal(niwm.mean_variance(s["S_n"], s["nu_n"], s["kappa_n"]), dim1=-2, dim2=-1).sum(-1)  # noqa: E731
    assert bool((var(new)[1:] < var(st)[1:]).all()) and torch.equal(var(new)[0], var(st)[0])


# ------------------------------------------------------------------------------- options and errors
def _study_cfg(*overrides):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name="study", overrides=["data=synthetic", *overrides])


def _rows(*overrides):
    from b3dgs.study.active import ActiveStudy

    stub = SimpleNamespace(cfg=_study_cfg(*overrides))
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        rows = ActiveStudy._policies(stub)
    return [label for label, _ in rows], stub.batches


def test_study_rows_are_policy_times_batch():
    labels, batches = _rows("policies=[uniform,farthest,fisher,native,ensemble]", "family_baselines=[uniform]",
                            "acquisition.batch=[topk,greedy_conditioned,diverse]")
    assert labels == ["uniform", "farthest", "fisher", "native", "native+greedy_conditioned", "native+diverse",
                      "ensemble", "ensemble+greedy_conditioned", "ensemble+diverse", "uniform@niw"]
    assert type(batches["native+diverse"]).__name__ == "Diverse" and type(batches["farthest"]).__name__ == "TopK"
    labels, _ = _rows("policies=[native,native+diverse,proxy@standard+greedy_conditioned]", "family_baselines=[]")
    assert labels == ["native", "native+diverse", "proxy@standard+greedy_conditioned"]
    labels, batches = _rows("policies=[farthest,native]", "family_baselines=[]", "acquisition.batch=diverse",
                            "+acquisition.batch_settings.diverse.radius=2.5")
    assert labels == ["farthest", "native+diverse"] and batches["native+diverse"].radius == 2.5


@pytest.mark.parametrize("name", sorted(p.stem for p in (Path(CONF_DIR) / "acquisition" / "batch").glob("*.yaml")))
def test_every_batch_option_builds(name):
    from b3dgs.acquisition import BatchSelector

    b = _batch(name)
    assert isinstance(b, BatchSelector) and b.applies_to(_policy("native")) and name in BATCHES
    assert b.applies_to(_policy("farthest")) == (name == "topk")


@pytest.mark.parametrize("overrides,message", [
    (["acquisition.batch=nope"], "unknown acquisition/batch option 'nope'"),
    (["acquisition.batch=[]"], "acquisition.batch=[] is invalid"),
    (["policies=[farthest+diverse]"], "policy farthest builds its batch itself, so batch diverse does not apply"),
    (["acquisition.batch=diverse", "+acquisition.batch_settings.diverse.radius=0"], "radius=0 must be a finite number > 0"),
    (["acquisition.batch=greedy_conditioned", "+acquisition.batch_settings.greedy_conditioned.max_rescore=0"],
     "max_rescore=0 must be an integer >= 1"),
    (["acquisition.batch=diverse", "+acquisition.batch_settings.diverse.radious=2"], "acquisition batch diverse: bad settings"),
])
def test_bad_batch_options_are_one_line_errors(overrides, message):
    with pytest.raises(B3dgsError) as e:
        _rows("policies=[native]", "family_baselines=[]", *overrides)
    text = str(e.value)
    assert message in text and "\n" not in text and "(fix: pass " in text, text


def test_the_study_cli_refuses_a_bad_batch_in_one_line(tmp_path):
    r = subprocess.run([sys.executable, "-m", "b3dgs.study.active", *STUDY, "acquisition.batch=[topk,divers]",
                        f"out_dir={tmp_path}"], capture_output=True, text=True, timeout=600)
    err = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(err) == 1 and "unknown acquisition/batch option 'divers'" in err[0], r.stderr[-2000:]
    assert not (tmp_path / "synthetic" / "phase1").exists()


def test_study_runs_batch_rows_and_records_them(tmp_path):
    """A tiny study with native × {topk, greedy_conditioned, diverse}: every row trains (or shares a twin's
    run), its selection.json names its batch and what it did, and study.md lists the rows."""
    args = [a for a in STUDY if not a.startswith(("policies=", "variant="))]
    r = subprocess.run([sys.executable, "-m", "b3dgs.study.active", *args, "policies=[native]",
                        "acquisition.batch=[topk,greedy_conditioned,diverse]", f"out_dir={tmp_path}"],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    sc = tmp_path / "synthetic"
    sel = {lab: json.loads((sc / f"{lab}_s0" / "selection.json").read_text())
           for lab in ("native", "native+greedy_conditioned", "native+diverse")}
    assert sel["native"]["batch"] == "topk" and sel["native"]["batch_info"] is None
    g = sel["native+greedy_conditioned"]["batch_info"]
    assert g["batch"] == "greedy_conditioned" and len(g["rescored_per_pick"]) == 3 and max(g["rescored_per_pick"]) <= 4
    assert sel["native+diverse"]["batch_info"]["batch"] == "diverse"
    assert sel["native"]["scores"] == sel["native+diverse"]["scores"] == sel["native+greedy_conditioned"]["scores"]
    assert all(len(s["selected"]) == 4 for s in sel.values())
    assert sel["native+greedy_conditioned"]["selected"][0] == sel["native"]["selected"][0]  # both start at the top score
    study = json.loads((sc / "study.json").read_text())
    assert {"native", "native+greedy_conditioned", "native+diverse"} <= set(study["table"])
    assert "native+diverse" in (sc / "study.md").read_text()


def test_a_study_row_is_a_config_node_and_the_shorthand_is_the_same_node():
    """policies=[...] takes nodes {policy, family, batch, blocks}; native@niw+diverse is the same row."""
    from b3dgs.study.active import StudyRow, row_pins

    assert StudyRow.parse("native@niw+diverse") == StudyRow("native", "niw", "diverse")
    assert StudyRow.parse("native+diverse@niw") == StudyRow("native", "niw", "diverse")
    assert StudyRow.parse({"policy": "sh", "family": "niw", "blocks": ["niw", "sh"]}) == StudyRow(
        "sh", "niw", None, ("niw", "sh"))
    short, _ = _rows("policies=[native,native@niw+diverse,proxy@standard+greedy_conditioned]", "family_baselines=[]")
    nodes, batches = _rows("policies=[native,{policy:native,family:niw,batch:diverse},"
                           "{policy:proxy,family:standard,batch:greedy_conditioned}]", "family_baselines=[]")
    assert nodes == short == ["native", "native+diverse", "proxy@standard+greedy_conditioned"]  # niw: native's own
    assert type(batches["native+diverse"]).__name__ == "Diverse"
    # a row's blocks pin its family's posterior, as family_posterior does
    cfg = _study_cfg("policies=[{policy:sh,family:niw,blocks:[niw,sh]},native]", "family_baselines=[]")
    assert row_pins(cfg) == {"niw": ["niw", "sh"]}
    assert row_pins(_study_cfg("policies=[native]", "family_posterior={niw:[niw]}")) == {"niw": ["niw"]}


@pytest.mark.parametrize("policies,message", [
    ("[{policy:native,famly:niw}]", "a study row has no field 'famly'; did you mean family?"),
    ("[{family:niw}]", "a study row needs its policy"),
    ("[{policy:native,blocks:niw}]", "study row native: blocks must be a list of posterior block names"),
    ("[{policy:sh,family:niw,blocks:[niw,sh]},{policy:native,family:niw,blocks:[niw]}]",
     "study row native: blocks ['niw'] differ from ['niw', 'sh']"),
])
def test_bad_study_rows_are_one_line_errors(policies, message):
    with pytest.raises(B3dgsError) as e:
        _rows(f"policies={policies}", "family_baselines=[]")
    text = str(e.value)
    assert message in text and "\n" not in text and "(fix: " in text, text
