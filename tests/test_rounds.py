"""Training in rounds (issue 11 §1): fit, acquire, fit on from the same model state."""
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from b3dgs.study.rounds import fit_round
from b3dgs.train import CONF_DIR

STEPS = 60
BASE = ["data.max_side=32", "+data.n_views=24", f"trainer.max_steps={STEPS}", "trainer.checkpoint_every=1000",
        "trainer.checkpoint_every_s=0", "trainer.enable_progress_bar=false", "logger=none", "strategy.refine_start=10",
        "strategy.refine_every=10", "strategy.refine_stop=50", "model.sh_increase_every=20", "seed=3", "threads=1",
        "renderer=cpu"]


def _cfg(extra=()):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name="train", overrides=[*BASE, *extra])


def _scene(cfg, n_train=None):
    from hydra.utils import instantiate

    dm = instantiate(cfg.data)
    dm.setup("fit")
    sc = dm.scene
    if n_train is not None:
        import dataclasses

        sc = dataclasses.replace(sc, train=sc.train[:n_train], candidates=sc.train[n_train:])
    return sc


def _params(m):
    return {k: v.detach().clone() for k, v in m.splats.items()}


def _aligned(m):
    """Adam state, parameters and every per-Gaussian plugin state agree on N and on object identity."""
    n = m.num_gaussians
    opt = m.ops.optimizers["gaussians"]
    live = m.optimizers().optimizer if hasattr(m.optimizers(), "optimizer") else m.optimizers()
    assert opt is live, "topology ops hold a stale optimizer"
    for g in opt.param_groups:
        p = g["params"][0]
        assert p is m.splats[g["name"]], g["name"]
        st = opt.state.get(p, {})
        for k, v in st.items():
            if torch.is_tensor(v) and v.dim() >= 1:
                assert v.shape == p.shape, (g["name"], k)
    assert m.states["core"]["ids"].shape[0] == n
    for name, st in m.states.items():
        for k, v in st.items():
            if torch.is_tensor(v) and v.dim() >= 1 and name != "core":
                assert v.shape[0] == n, (name, k, v.shape, n)


@pytest.mark.parametrize("model", ["standard", "niw"])
def test_fit_acquire_nothing_fit_equals_single_fit(tmp_path, model):
    cfg = _cfg([f"model={model}"])
    scene = _scene(cfg)
    one = fit_round(cfg, scene, tmp_path / "one", STEPS)
    a = fit_round(cfg, scene, tmp_path / "two", 25)
    assert a.num_gaussians > 0
    b = fit_round(cfg, scene, tmp_path / "two", STEPS, ckpt_path=str(tmp_path / "two/checkpoints/last.ckpt"),
                  new_round=True)
    pa, pb = _params(one), _params(b)
    assert one.num_gaussians == b.num_gaussians
    for k in pa:
        assert torch.equal(pa[k], pb[k]), k
    for name in one.states:
        for k, v in one.states[name].items():
            if torch.is_tensor(v):
                assert torch.equal(v, b.states[name][k]), (name, k)


def test_second_round_with_more_views_and_densification_stays_aligned(tmp_path):
    cfg = _cfg(["model=dpmm", "posterior.dp.t_dp=5", "posterior.dp.cavi_every=5"])
    small = _scene(cfg, n_train=12)
    m1 = fit_round(cfg, small, tmp_path / "r", 25)
    assert m1.states["dp"]["n_views"].item() == 12
    import dataclasses

    big = dataclasses.replace(small, train=small.train + small.candidates[:6], candidates=small.candidates[6:])
    m2 = fit_round(cfg, big, tmp_path / "r", STEPS, ckpt_path=str(tmp_path / "r/checkpoints/last.ckpt"), new_round=True)
    assert int(m2.global_step) == STEPS
    assert sum(m2.ops.added.values()) > sum(m1.ops.added.values()), "round 2 densified"
    _aligned(m2)
    for name in ("niw", "dp", "opacity", "color"):
        assert m2.states[name]["n_views"].item() == 18, name  # follows the grown training set
    # means lr continued the decay of the total budget
    assert m2.means_lr(STEPS) < m2.means_lr(25)


def test_refit_same_module_follows_the_live_optimizer(tmp_path):
    """A second trainer.fit on the same module makes a new Adam: topology ops must edit that one."""
    import lightning as L

    from b3dgs.data.datamodule import SceneDataModule

    cfg = _cfg()
    scene = _scene(cfg)
    m = fit_round(cfg, scene, tmp_path / "a", 30)
    old_ops = m.ops
    old_opt = old_ops.optimizers["gaussians"]
    tr = L.Trainer(max_steps=STEPS, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                   enable_model_summary=False, limit_val_batches=0, num_sanity_val_steps=0, accelerator="cpu")
    dm = SceneDataModule(scene=scene)
    tr.fit(m, datamodule=dm)
    assert m.ops.optimizers["gaussians"] is not old_opt
    _aligned(m)


def _observers():
    """conf/posterior/<name>.yaml blocks whose class promises ``changes_training = False``."""
    from hydra.utils import get_class
    from omegaconf import OmegaConf

    out = []
    for p in sorted((Path(CONF_DIR) / "posterior").glob("*.yaml")):
        node = next(iter(OmegaConf.load(p).values()))
        if not get_class(node["_target_"]).changes_training:
            out.append(p.stem)
    return out


@pytest.mark.parametrize("block", _observers())
def test_blocks_that_promise_not_to_change_training_train_bit_for_bit_like_standard(tmp_path, block):
    """The declaration the study relies on to share runs: densification, SH schedule and all."""
    assert "niw" in _observers()  # the promise is made where the paper says so (NIW reads summaries only)
    ref = _cfg()
    sc = _scene(ref)
    a = fit_round(ref, sc, tmp_path / "std", STEPS)
    b = fit_round(_cfg([f"posterior=[{block}]"]), sc, tmp_path / block, STEPS)
    assert list(b.posterior) == [block], "the block was not built"
    pa, pb = _params(a), _params(b)
    assert a.num_gaussians == b.num_gaussians
    for k in pa:
        assert torch.equal(pa[k], pb[k]), k


def test_study_family_config_resolves_a_named_scene(tmp_path, monkeypatch):
    """A named scene's data.path is ${data_root}/<name>; the study's per-family training config (which the training
    signature resolves to compare rows) must resolve it, as b3dgs-train does."""
    from omegaconf import OmegaConf

    from b3dgs.study.active import compose_config, family_config

    monkeypatch.setenv("B3DGS_DATA", str(tmp_path))
    fam = family_config(compose_config("study", ["scene=fox"]), "niw", 0)
    assert OmegaConf.to_container(fam.data, resolve=True)["path"] == str(tmp_path / "fox")


def test_study_rounds_follow_the_study_schedule():
    """``+schedule=dash`` on the study reaches every round's training config (phase 1 and round 2); without it the
    rounds carry no schedule node, so they train as b3dgs-train's default (constant)."""
    from b3dgs.study.active import compose_config, family_config

    dash = family_config(compose_config("study", ["+schedule=dash", "schedule.keep=0.5"]), "standard", 1)
    assert dash.schedule._target_.endswith("DashSchedule") and dash.schedule.keep == 0.5 and dash.seed == 1
    from b3dgs.schedule import ConstantSchedule, make_schedule

    plain = family_config(compose_config("study", []), "niw", 0)
    assert plain.get("schedule") is None and isinstance(make_schedule(plain.get("schedule")), ConstantSchedule)


def test_study_family_posterior_pins_blocks_and_the_protocol_records_other_ones(tmp_path, monkeypatch):
    """``family_posterior`` pins a family's posterior blocks; protocol.json records a family's blocks only where they
    differ from the ones every earlier folder was run with ({standard: [], niw: [niw]}), so pinning those keeps the
    protocol (and archived folders valid), and a folder of [niw] refuses rows of a [niw,sh] NIW family."""
    from b3dgs.errors import B3dgsError
    from b3dgs.protocol import check_stored_protocol
    from b3dgs.study.active import compose_config, family_config, study_protocol

    def posteriors(cfg):
        return {f: list(family_config(cfg, f, 0).get("posterior") or {}) for f in ("standard", "niw", "dpmm")}

    monkeypatch.setenv("B3DGS_DATA", str(tmp_path / "data"))
    plain = compose_config("study", ["scene=fox"])
    pinned = compose_config("study", ["scene=fox", "family_posterior={standard:[],niw:[niw]}"])
    sh = compose_config("study", ["scene=fox", "family_posterior={niw:[niw,sh]}"])
    for c in (plain, pinned, sh):  # resolved outside a Hydra job: the run dir is a literal
        c.trainer.default_root_dir = str(tmp_path)
    dpmm = ["niw", "dp", "noise", "opacity", "color"]
    assert posteriors(plain) == posteriors(pinned) == {"standard": [], "niw": ["niw"], "dpmm": dpmm}
    assert posteriors(sh) == {"standard": [], "niw": ["niw", "sh"], "dpmm": dpmm}
    assert study_protocol(plain, posteriors(plain)) == study_protocol(pinned, posteriors(pinned))
    assert not any(k.startswith("family_posterior") for k in study_protocol(plain, posteriors(plain)))
    assert study_protocol(sh, posteriors(sh))["family_posterior.niw"] == ["niw", "sh"]
    check_stored_protocol(tmp_path, study_protocol(plain, posteriors(plain)), fix="f")
    check_stored_protocol(tmp_path, study_protocol(pinned, posteriors(pinned)), fix="f")  # the same folder
    with pytest.raises(B3dgsError, match=r"family_posterior\.niw: unset there, \[\"niw\", \"sh\"\] here"):
        check_stored_protocol(tmp_path, study_protocol(sh, posteriors(sh)), fix="f")
    with pytest.raises(B3dgsError, match="family_posterior.niw: unknown posterior block 'nope'.*fix: use blocks"):
        family_config(compose_config("study", ["family_posterior={niw:[nope]}"]), "niw", 0)
    for bad in ("niw", "3"):
        with pytest.raises(B3dgsError, match="must be a list of posterior block names"):
            family_config(compose_config("study", [f"family_posterior={{niw:{bad}}}"]), "niw", 0)
    # a family outside the table is recorded only when pinned (its folders from before the setting stay valid)
    assert study_protocol(sh, {"mcmc": []})["family_posterior.mcmc"] == []
