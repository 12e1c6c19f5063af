"""Acquisition policies (issue 11 §2-3): known answers on small cases, no ground-truth leak, plugins from
an installed package, and the study's resume between rounds."""
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from b3dgs.acquisition import ScoringContext
from tests.kill_hooks import kill_args
from b3dgs.train import CONF_DIR
from b3dgs.types import Camera

ALL = ["uniform", "farthest", "ensemble", "ppu", "fisher", "proxy", "native", "oracle"]


def _policy(name, **kw):
    """The study's policy ``name`` with settings ``kw`` by name, as ``policy_settings`` passes them (a policy over a
    UQ regime takes them in its regime's node)."""
    from omegaconf import OmegaConf

    from b3dgs.study.active import load_policy

    defaults = OmegaConf.to_container(OmegaConf.load(Path(CONF_DIR) / "acquisition" / f"{name}.yaml")).get("defaults") or []
    regime = next((d["/uq@regime"] for d in defaults if isinstance(d, dict) and "/uq@regime" in d), None)
    settings = {name: {"regime": {regime: kw}} if regime else kw}
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        label, p = load_policy(name, OmegaConf.create(settings))
    return p


def _ring(n, names=None, radius=3.0, size=8):
    """Cameras on a circle in the z=0 plane looking at the origin (OpenCV: +z forward, y down)."""
    cams = []
    for i in range(n):
        a = 2 * math.pi * i / n
        c = torch.tensor([radius * math.cos(a), radius * math.sin(a), 0.0], dtype=torch.float64)
        z = -c / c.norm()
        y = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
        x = torch.linalg.cross(y, z)
        R = torch.stack([x, torch.linalg.cross(z, x), z])
        v = torch.eye(4, dtype=torch.float64)
        v[:3, :3], v[:3, 3] = R, -R @ c
        K = torch.tensor([[size, 0, size / 2], [0, size, size / 2], [0, 0, 1]], dtype=torch.float32)
        cams.append(Camera(names[i] if names else f"c{i:02d}", K, v.float(), size, size, None))
    return cams


def test_uniform_and_farthest_pick_the_expected_cameras():
    ring = _ring(8)
    train, cands = [ring[0]], ring[1:]
    ctx = ScoringContext([], train)
    assert [cands[i].name for i in _policy("uniform").select(ctx, cands, 3).indices] == ["c01", "c04", "c07"]
    far = _policy("farthest").select(ctx, cands, 3)
    # opposite camera first, then the two at 90 degrees (ties: the first in candidate order)
    assert [cands[i].name for i in far.indices] == ["c04", "c02", "c06"]
    assert far.scores[3] == pytest.approx(6.0)


# ------------------------------------------------------------------------------- model-based cases
def _cfg(extra=()):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name="train", overrides=[
            "data.max_side=32", "+data.n_views=24", "trainer.max_steps=80", "trainer.checkpoint_every=1000",
            "trainer.checkpoint_every_s=0", "logger=none", "strategy.refine_start=10", "strategy.refine_every=10",
            "strategy.refine_stop=60", "model.sh_increase_every=40", "seed=1", "threads=1", "renderer=cpu", *extra])


@pytest.fixture(scope="module")
def hole_setup(tmp_path_factory):
    """A NIW model trained on views from one half of the ring; candidates in both halves."""
    from b3dgs.data.scene import load_scene, take_candidate_store
    from b3dgs.study.active import pca_angles
    from b3dgs.study.rounds import fit_round

    cfg = _cfg(["model=niw"])
    full = load_scene("synthetic", None, max_side=32, n_views=24)
    ang = pca_angles(full.train)
    seen = [i for i in range(len(full.train)) if math.cos(ang[i]) > 0.2]
    scene = load_scene("synthetic", None, max_side=32, n_views=24, train_indices=seen[::2])
    store = take_candidate_store(scene)
    model = fit_round(cfg, scene, tmp_path_factory.mktemp("hole"), 80)
    model.eval()
    unobserved = {full.train[i].name for i in range(len(full.train)) if math.cos(ang[i]) < -0.2}
    return model, scene, store, unobserved


@pytest.mark.parametrize("name", ["native", "proxy"])
def test_native_and_proxy_prefer_views_of_an_unobserved_region(hole_setup, name):
    model, scene, store, unobserved = hole_setup
    ctx = ScoringContext([model], scene.train, score_max_side=32, extent=scene.extent, seed=0)
    pol = _policy(name, samples=8)
    scores = pol.score(ctx, scene.candidates)
    hole = [float(s) for c, s in zip(scene.candidates, scores) if c.name in unobserved]
    seen = [float(s) for c, s in zip(scene.candidates, scores) if c.name not in unobserved]
    assert hole and seen
    assert sum(hole) / len(hole) > sum(seen) / len(seen), (name, hole, seen)


def test_ensemble_of_identical_members_scores_zero(hole_setup):
    model, scene, _, _ = hole_setup
    ctx = ScoringContext([model, model, model], scene.train, score_max_side=16)
    scores = _policy("ensemble").score(ctx, scene.candidates[:4])
    assert torch.all(scores == 0)


def test_fisher_matches_float64_brute_force():
    """Exact mode (stride >= image side) against the per-pixel Jacobian in float64 (pure-torch renderer)."""
    from torch import nn

    from b3dgs.study.rounds import fit_round  # noqa: F401 - imports the module chain
    from b3dgs.lifecycle import build_module, build_plugins
    from b3dgs.data.scene import load_scene

    cfg = _cfg(["renderer=torch", "model.init_max_points=12", "model.init_num_random=0", "model.sh_degree=1"])
    scene = load_scene("synthetic", None, max_side=8, n_views=8)
    strategy, blocks = build_plugins(cfg)
    m = build_module(cfg, strategy, blocks)
    m.init_from_scene(scene)
    m.splats = nn.ParameterDict({k: nn.Parameter(v.detach().double()) for k, v in m.splats.items()})
    m.bg = m.bg.double()
    m._loaded_step = 10_000
    cam = scene.train[1]
    cam = Camera(cam.name, cam.K.double(), cam.viewmat.double(), cam.width, cam.height, None)
    ctx = ScoringContext([m], [], score_max_side=None)
    pol = _policy("fisher", pixel_stride=64)
    H = pol.view_fisher(ctx, cam)
    keys = pol.params
    base = {k: v.detach().clone() for k, v in m.params().items()}
    sizes = [base[k].numel() for k in keys]

    def f(flat):
        p = dict(base)
        for k, chunk in zip(keys, torch.split(flat, sizes)):
            p[k] = chunk.reshape(base[k].shape)
        return m.render_camera(cam, params=p).rgb.sum(-1).reshape(-1)  # Σ_c I_c(p) per pixel

    J = torch.autograd.functional.jacobian(f, torch.cat([base[k].reshape(-1) for k in keys]))
    ref = J.square().sum(0)
    assert H.dtype == torch.float64 and H.shape == ref.shape
    assert ref.abs().max() > 0
    torch.testing.assert_close(H, ref, rtol=1e-9, atol=1e-12)
    # the strided (fast) mode is an approximation that keeps the magnitude
    approx = _policy("fisher", pixel_stride=2).view_fisher(ctx, cam)
    assert 0.5 < float(approx.sum() / ref.sum()) < 4.0


def test_no_policy_but_oracle_reaches_candidate_images(hole_setup):
    model, scene, store, _ = hole_setup
    assert scene.candidates and all(c.image is None for c in scene.candidates)
    assert not hasattr(scene, "_candidate_store")  # taken by the driver
    for name in ALL:
        pol = _policy(name)
        if name in ("native", "proxy"):
            pol.samples = 4
        if name == "ppu":
            pol.steps = 5
        if name == "fisher":
            pol.pixel_stride = 2
        before = len(store.reads)
        members = [model] * int(pol.members)
        ctx = ScoringContext(members, scene.train, score_max_side=12, extent=scene.extent,
                             ground_truth=store.image if pol.uses_ground_truth else None)
        sel = pol.select(ctx, scene.candidates[:5], 2)
        assert len(sel.indices) == 2
        read = len(store.reads) - before
        assert (read > 0) == (name == "oracle"), (name, read)
        if name != "oracle":
            with pytest.raises(Exception, match="ground truth"):
                ctx.ground_truth(scene.candidates[0])


def test_external_package_adds_an_acquisition_policy(tmp_path, monkeypatch):
    from b3dgs.study.active import load_policy
    from tests.fake_package import install_conf_package

    install_conf_package(tmp_path, monkeypatch, "b3dgs_acq_demo", "acquisition", "pol", '''
        from dataclasses import dataclass
        import torch
        from b3dgs.acquisition import AcquisitionPolicy

        @dataclass
        class LastFirst(AcquisitionPolicy):
            """A user's policy: the candidates in reverse name order."""
            def score(self, ctx, candidates):
                return torch.arange(len(candidates), dtype=torch.float64)
    ''', {"lastfirst": "_target_: b3dgs_acq_demo.pol.LastFirst\nfamily: dpmm\n"})  # any model= option
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        label, pol = load_policy("lastfirst")
    assert type(pol).__name__ == "LastFirst" and pol.family == "dpmm" and label == "lastfirst"
    ring = _ring(5)
    assert pol.select(ScoringContext([], ring[:1]), ring[1:], 2).indices == [3, 2]
    sys.modules.pop("b3dgs_acq_demo", None)


def test_external_package_adds_a_batch_selector(tmp_path, monkeypatch):
    """docs/extending.md's batch selector from an installed package, over a policy that conditions: each pick is
    the candidate farthest from the training and earlier picks (top-k of the first scores would take neighbours),
    and the selector leaves the policy unconditioned."""
    from b3dgs.study.active import load_batch
    from tests.fake_package import install_conf_package

    install_conf_package(tmp_path, monkeypatch, "b3dgs_batch_demo", "acquisition/batch", "sel", '''
        from dataclasses import dataclass, field
        import torch
        from b3dgs.acquisition import AcquisitionPolicy, BatchSelector, Selection, camera_centres

        @dataclass
        class OneByOne(BatchSelector):
            def select(self, policy, ctx, candidates, budget):
                first = [float(v) for v in policy.score(ctx, candidates)]
                left, picks = list(range(len(candidates))), []
                try:
                    while left and len(picks) < budget:
                        s = policy.score_at(ctx, candidates, left)
                        picks.append(left.pop(int(s.argmax())))
                        policy.condition(ctx, candidates[picks[-1]])
                finally:
                    policy.reset_conditioning(ctx)
                return Selection(picks, first, {"batch": "one_by_one"})

        @dataclass
        class Away(AcquisitionPolicy):
            """A candidate's distance to the nearest acquired camera (training, then each conditioned pick)."""
            acquired: list = field(default_factory=list)

            def score(self, ctx, candidates):
                have = torch.as_tensor(camera_centres([*ctx.train, *self.acquired]))
                return torch.cdist(torch.as_tensor(camera_centres(candidates)), have).min(1).values

            def condition(self, ctx, camera):
                self.acquired.append(camera)
                return True

            def reset_conditioning(self, ctx):
                self.acquired.clear()
    ''', {"one_by_one": "_target_: b3dgs_batch_demo.sel.OneByOne\n"})
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        batch = load_batch("one_by_one")
    from b3dgs_batch_demo.sel import Away

    pol, ring = Away(), _ring(8)
    assert type(batch).__name__ == "OneByOne" and batch.applies_to(pol)
    sel = batch.select(pol, ScoringContext([], ring[:1]), ring[1:], 3)
    names = [ring[1:][i].name for i in sel.indices]
    assert names[0] == "c04" and set(names[1:]) == {"c02", "c06"}  # opposite the training camera c00, then the gaps
    assert pol.acquired == [] and sel.info == {"batch": "one_by_one"}
    assert sel.indices[:2] != sorted(range(7), key=lambda i: -sel.scores[i])[:2]  # top-k: c04 and a neighbour
    sys.modules.pop("b3dgs_batch_demo", None)


# ------------------------------------------------------------------------------- the study, resumed
STUDY = ["active", "data=synthetic", "data.max_side=32", "+data.n_views=40", "renderer=cpu", "trainer.max_steps=60",
         "trainer.checkpoint_every=10", "trainer.checkpoint_every_s=0", "strategy.refine_start=10",
         "strategy.refine_every=10", "strategy.refine_stop=50", "initial_views=8", "acquire=4", "seeds=[0]",
         "policies=[farthest,native]", "family_baselines=[]", "+policy_settings.native.regime.native.samples=4",
         "acquisition.score_max_side=16", "threads=1", "plots=false", "variant=support_hole"]


def _study(out, kill_at=None, extra=()):
    kill = kill_args(step=kill_at) if kill_at is not None else []
    return subprocess.run([sys.executable, "-m", "b3dgs.study.active", *STUDY, *extra, *kill, f"out_dir={out}"],
                          capture_output=True, text=True, timeout=600, cwd=Path(__file__).resolve().parents[1])


def test_study_resumes_after_interruption_between_and_within_rounds(tmp_path):
    ref, cut = tmp_path / "ref", tmp_path / "cut"
    r = _study(ref)
    assert r.returncode == 0, r.stderr[-3000:]
    r = _study(cut, kill_at=45)  # phase 1 ends at 20; killed in the first row's second round
    assert r.returncode != 0
    sc = cut / "synthetic"
    assert (sc / "phase1" / "standard_s0" / "phase1.json").exists()
    assert (sc / "farthest_s0" / "selection.json").exists() and not (sc / "farthest_s0" / "result.json").exists()
    # a row is a run: its records are listed in its manifest as they are written (b3dgs.lifecycle.Run.record)
    from b3dgs.rundir import run_files
    assert run_files(sc / "farthest_s0") == ["selection.json"]
    assert run_files(sc / "phase1" / "standard_s0") == ["phase1.json"]
    p1 = (sc / "phase1" / "standard_s0" / "phase1.json").stat().st_mtime_ns
    r = _study(cut)
    assert r.returncode == 0, r.stderr[-3000:]
    assert (sc / "phase1" / "standard_s0" / "phase1.json").stat().st_mtime_ns == p1  # never retrained
    a, b = (json.loads((d / "synthetic" / "study.json").read_text()) for d in (ref, cut))
    for pol in ("farthest", "native"):
        assert a["table"][pol]["psnr"] == b["table"][pol]["psnr"], pol
    done = (sc / "native_s0" / "result.json").stat().st_mtime_ns
    r = _study(cut)  # everything finished: nothing is retrained
    assert r.returncode == 0 and (sc / "native_s0" / "result.json").stat().st_mtime_ns == done
    assert run_files(sc / "native_s0") == ["result.json", "selection.json"]
    meta = json.loads((sc / "meta.json").read_text())
    assert meta["hole"] and not set(meta["hole"]) & set(meta["initial_views"])
    assert (sc / "study.md").read_text().count("|") > 10
    # the same out_dir with other settings: refused in one line naming the keys, no row reused or touched
    r = _study(cut, extra=["acquire=3", "trainer.max_steps=80"])
    err = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(err) == 1 and "holds results of other settings (acquire: 4 there, 3 here; " \
        "trainer.max_steps: 60 there, 80 here)" in err[0], r.stderr[-2000:]
    assert (sc / "native_s0" / "result.json").stat().st_mtime_ns == done
    for bad in ("acquire=0", "initial_views=0"):  # refused before anything trains, naming the key the user set
        r = _study(tmp_path / "bad", extra=[bad])
        assert r.returncode == 2 and f"error: {bad} is invalid" in r.stderr, r.stderr[-2000:]
        assert not (tmp_path / "bad" / "synthetic").exists()
    # restored from an archive on another machine: the small JSON files without any checkpoint, one row unfinished;
    # the phase-1 model it needs is trained again and the row comes out bit for bit the same
    import shutil

    for ck in sorted(sc.rglob("checkpoints")):
        shutil.rmtree(ck)
    (sc / "native_s0" / "result.json").unlink()
    r = _study(cut)
    assert r.returncode == 0, r.stderr[-3000:]
    assert json.loads((sc / "native_s0" / "result.json").read_text())["psnr"] == a["table"]["native"]["psnr"]


def test_study_shares_a_second_round_only_when_it_is_the_same_run(tmp_path):
    """uniform@niw picks what uniform picks and NIW only observes training: shared, and the sharing is
    exact (a study with share_training=false trains it and gets the same PSNR to the bit)."""
    base = [a for a in STUDY if not a.startswith(("policies=", "variant="))] + ["policies=[uniform,uniform@niw]"]

    def run(out, *extra):
        r = subprocess.run([sys.executable, "-m", "b3dgs.study.active", *base, *extra, f"out_dir={out}"],
                           capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr[-3000:]
        return {p: json.loads((out / "synthetic" / f"{p}_s0" / "result.json").read_text()) for p in ("uniform", "uniform@niw")}

    shared = run(tmp_path / "a")
    assert shared["uniform@niw"]["training_shared_with"] == "uniform"
    assert not (tmp_path / "a" / "synthetic" / "uniform@niw_s0" / "checkpoints").exists()
    trained = run(tmp_path / "b", "share_training=false", "pairs=[[uniform,uniform@niw]]")
    assert "training_shared_with" not in trained["uniform@niw"]
    assert trained["uniform@niw"]["psnr"] == trained["uniform"]["psnr"] == shared["uniform@niw"]["psnr"]
    paired = json.loads((tmp_path / "b" / "synthetic" / "study.json").read_text())["paired"]  # asked for: its
    assert list(paired) == ["uniform-uniform@niw"] and paired["uniform-uniform@niw"]["delta_psnr"] == 0.0  # side


def test_phase1_lock_serialises_jobs_that_share_a_phase1_model(tmp_path):
    """Parallel seed jobs (``-m`` with a parallel launcher) share the ensemble's phase-1 members: the second
    job waits for the first instead of training the same model into the same directory."""
    from b3dgs.lifecycle import Run

    d = tmp_path / "phase1" / "standard_s1"
    code = ("import sys, time; from pathlib import Path; from b3dgs.lifecycle import Run\n"
            f"with Run(run_dir=Path({str(d)!r})).exclusive():\n"
            f"    Path({str(tmp_path / 'held')!r}).write_text('1'); time.sleep(1.5)\n"
            f"    Path({str(tmp_path / 'child_end')!r}).write_text(repr(time.time()))\n")
    child = subprocess.Popen([sys.executable, "-c", code])
    deadline = time.time() + 60
    while not (tmp_path / "held").exists():
        assert time.time() < deadline and child.poll() is None, "the child never took the lock"
        time.sleep(0.02)
    with Run(run_dir=d).exclusive():
        got = time.time()
    child.wait(timeout=60)
    assert got >= float((tmp_path / "child_end").read_text())


@pytest.mark.parametrize("name", sorted(p.stem for p in (Path(CONF_DIR) / "acquisition").glob("*.yaml")))
def test_every_acquisition_option_builds(name):
    from b3dgs.acquisition import AcquisitionPolicy
    from b3dgs.confs import option_names

    GlobalHydra.instance().clear()
    pol = _policy(name)
    # docs/extending.md: `family` is any `model=` option (b3dgs's or a package's)
    assert isinstance(pol, AcquisitionPolicy) and pol.family in option_names("model")
    assert pol.uses_ground_truth == (name == "oracle")


def test_study_md_states_the_scoring_resolution_and_point_filter_in_words():
    from b3dgs.study.active_tables import markdown

    base = {"scene": "s", "seeds": [0], "table": {}, "paired": [], "jaccard": {}}
    head = markdown({**base, "meta": {"score_max_side": None, "point_filter": None}}).splitlines()[2]
    assert "scoring at the training resolution;" in head and "initial points: all (not filtered)." in head
    pf = {"method": "sfm_tracks", "total": 4767, "kept": 1265, "train_views": 16}
    head = markdown({**base, "meta": {"score_max_side": 64, "point_filter": pf}}).splitlines()[2]
    assert "scoring at 64 px" in head and "1265 of 4767 kept" in head


def test_study_extended_by_a_subset_keeps_every_row(tmp_path):
    """A scene folder extended with fewer (or other) policies than it first ran keeps every finished row in its
    per-scene table, and its meta.json keeps listing the earlier policies first."""
    import json

    from b3dgs.study.active import merged_policies
    from b3dgs.study.active_tables import summarize

    meta = tmp_path / "meta.json"
    assert merged_policies(meta, ["uniform", "native"]) == ["uniform", "native"]  # a fresh folder
    meta.write_text(json.dumps({"policies": ["uniform", "ppu", "native"]}))
    assert merged_policies(meta, ["native", "sh"]) == ["uniform", "ppu", "native", "sh"]
    meta.write_text(json.dumps({"policies": ["native"]}))  # written by a subset invocation (older code)
    for pol, seed, psnr in [("uniform", 0, 20.0), ("ppu", 0, 18.0), ("native", 0, 21.0), ("native", 1, 23.0)]:
        d = tmp_path / f"{pol}_s{seed}"
        d.mkdir()
        (d / "result.json").write_text(json.dumps({"policy": pol, "seed": seed, "family": "standard", "psnr": psnr,
                                                   "ssim": 0.9, "lpips": 0.1, "train_time_s": 1.0,
                                                   "scoring_time_s": 0.0, "selected": ["a", "b"]}))
    table = summarize(tmp_path)["table"]
    assert list(table) == ["native", "ppu", "uniform"]
    assert table["native"]["psnr"] == pytest.approx(22.0) and table["native"]["n_seeds"] == 2
    assert table["ppu"]["psnr"] == pytest.approx(18.0)


def test_study_pairs_every_policy_with_the_baselines_by_rule_and_the_pairs_asked_for(tmp_path):
    """A new policy gets its paired rows against farthest, uniform and the ensemble without editing the core, plus
    any ``pairs=`` the study records in meta.json; a malformed pair is a one-line error."""
    from omegaconf import OmegaConf

    from b3dgs.errors import B3dgsError
    from b3dgs.study.active import study_pairs
    from b3dgs.study.active_tables import summarize

    pols = ["uniform", "farthest", "ensemble", "mine", "native"]
    (tmp_path / "meta.json").write_text(json.dumps({"policies": pols, "pairs": [["native", "mine"]]}))
    for i, pol in enumerate(pols):
        for seed in (0, 1):
            d = tmp_path / f"{pol}_s{seed}"
            d.mkdir()
            (d / "result.json").write_text(json.dumps({"policy": pol, "seed": seed, "family": "standard",
                                                       "psnr": 20.0 + i + seed, "selected": ["a"]}))
    paired = summarize(tmp_path)["paired"]
    assert list(paired) == ["native-mine", "uniform-farthest", "uniform-ensemble", "farthest-ensemble",
                            "mine-farthest", "mine-uniform", "mine-ensemble", "native-farthest", "native-uniform",
                            "native-ensemble"]
    assert paired["mine-uniform"]["delta_psnr"] == pytest.approx(3.0) and paired["mine-uniform"]["n"] == 2
    assert list(summarize(tmp_path, pairs=[("native", "uniform")])["paired"]) == ["native-uniform"]
    assert study_pairs(OmegaConf.create({"pairs": [["native", "proxy"]]})) == [["native", "proxy"]]
    with pytest.raises(B3dgsError, match="not a pair of policies"):
        study_pairs(OmegaConf.create({"pairs": ["native", "proxy"]}))


def test_regime_policies_are_their_uq_regime():
    """A score policy over a UQ regime composes conf/uq/<name>.yaml (issue 45: one policy over one regime): the
    regime's own settings except the draws, overridden by name; two regimes or none is a one-line error."""
    from omegaconf import OmegaConf

    from b3dgs.acquisition import RegimePolicy
    from b3dgs.errors import B3dgsError
    from b3dgs.study.active import load_policy
    from b3dgs_plugins.uq.native import NativeUQ
    from b3dgs_plugins.uq.proxy import ProxyUQ

    _, nat = load_policy("native")
    assert isinstance(nat, RegimePolicy) and isinstance(nat.uq(), NativeUQ)
    assert (nat.uq().samples, nat.uq().chunk, nat.uq().count_scale) == (16, 8, 0.1)  # count_scale: conf/uq/native's
    _, sh = load_policy("sh")
    assert sh.uq().model_blocks is False and "sh" in sh.uq().add
    _, px = load_policy("proxy", OmegaConf.create({"proxy": {"regime": {"proxy": {"jitter": 0.01}}}}))
    assert isinstance(px.uq(), ProxyUQ) and px.uq().jitter == 0.01 and px.uq().samples == 16
    with pytest.raises(B3dgsError, match=r"no setting 'samples' .*policy_settings\.native\.regime\.native\.samples"):
        load_policy("native", OmegaConf.create({"native": {"samples": 4}}))  # the field moved into the regime
    with pytest.raises(B3dgsError, match="holds 2 entries"):
        RegimePolicy(regime={"a": ProxyUQ(), "b": ProxyUQ()}).uq()
    with pytest.raises(B3dgsError, match="not a UQ regime"):
        RegimePolicy(regime={"a": 3}).uq()
