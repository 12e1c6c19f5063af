"""Issue 53 §4: validation once, at each app's entry. ``validate`` runs once per plugin for b3dgs-eval (its regimes and
the loaded run's plugins) and once per composed config for the active study (not once per round); render, export,
view, process and report refuse a bad value of what they read (one line naming it and the fix) before they write."""
import collections
from pathlib import Path

import pytest
from omegaconf import OmegaConf, open_dict

from b3dgs.errors import B3dgsError
from b3dgs.train import CONF_DIR
from tests.inproc import compose_app
from tests.test_run_life import _spy_validate, _train


def test_eval_validates_each_regime_and_each_loaded_plugin_once(tmp_path, monkeypatch):
    from b3dgs.eval import hydra_main

    run = tmp_path / "run"
    _train(run, ["model=niw"])
    counts = _spy_validate(monkeypatch)
    hydra_main(compose_app("eval", [f"run={run}", "uq=[native,proxy]", "uq.samples=2", "max_views=1", "panels=0",
                                    f"out={tmp_path / 'uq'}"]))
    assert (tmp_path / "uq" / "uq.json").is_file()
    # before issue 53: each regime twice (the config check, then fit); the loaded run's plugins: once, as it is built
    assert dict(counts) == {"NativeUQ": 1, "ProxyUQ": 1, "AdaptiveDensityControl": 1, "NIWBlock": 1,
                            "ConstantSchedule": 1}, dict(counts)


def test_the_study_validates_each_composed_config_once_not_per_round(tmp_path, monkeypatch):
    from b3dgs.study import rounds
    from b3dgs.study.active import ActiveStudy

    counts = _spy_validate(monkeypatch)
    fits = []
    fit_round = rounds.fit_round
    monkeypatch.setattr(rounds, "fit_round", lambda *a, **k: fits.append(a[3]) or fit_round(*a, **k))
    cfg = compose_app("study", [
        "data=synthetic", "data.max_side=24", "+data.n_views=24", "renderer=cpu", "trainer.max_steps=20",
        "trainer.checkpoint_every_s=0", "strategy.refine_start=4", "strategy.refine_every=4", "strategy.refine_stop=16",
        "initial_views=6", "acquire=2", "seeds=[0]", "policies=[farthest,uniform@niw]", "family_baselines=[]",
        "threads=1", "plots=false", "share_training=false", f"out_dir={tmp_path}"], tmp_path)
    with open_dict(cfg):
        cfg.pop("hydra")  # as the app's task gets it
    study = ActiveStudy(cfg)
    study.run()
    assert len(fits) == 4  # phase 1 and a row's second round, of each family
    want = collections.Counter(type(p).__name__ for _, plugins in study._family_cfgs.values() for p in plugins.values())
    assert want["NIWBlock"] >= 1 and want["AdaptiveDensityControl"] == len(study._family_cfgs) >= 2
    assert counts == want, (dict(counts), dict(want))  # before: once more per round and per scoring model


def _app_cfg(app: str, **kw):
    """conf/<app>.yaml with ``kw`` set, as the app composes it."""
    base = OmegaConf.load(Path(CONF_DIR) / f"{app}.yaml")
    for key in ("defaults", "hydra"):
        base.pop(key, None)
    return OmegaConf.merge(base, kw)


@pytest.mark.parametrize("app, entry, kw, match", [
    ("render", "b3dgs.render_cli:render", {"frames": 60, "fps": -1}, "fps=-1 is invalid: it must be a frame rate"),
    ("render", "b3dgs.render_cli:render", {"video": "no"}, "video=no is invalid: it must be true or false"),
    ("export", "b3dgs.export:export", {"overwrite": 1}, "overwrite=1 is invalid: it must be true or false"),
    ("view", "b3dgs.viewer.app:settings_from_cfg", {"samples": 1}, "samples=1 is invalid: it must be an integer >= 2"),
    ("view", "b3dgs.viewer.app:settings_from_cfg", {"port": 70000}, "port=70000 is not a TCP port"),
    ("process", "b3dgs.process:process", {"single_camera": "maybe"}, "single_camera=maybe is invalid"),
    ("process", "b3dgs.process:process", {"seed": -1}, r"seed=-1 is invalid: it must be an integer in \[0, 2\^32\)"),
    ("report", "b3dgs.report:build_report", {"bootstrap": {"confidence": 95}}, r"bootstrap.confidence=95 is invalid"),
    ("report", "b3dgs.report:build_report", {"on_duplicate": "newset"}, "on_duplicate=newset is invalid: it must be "
                                                                          "error or newest"),
])
def test_each_app_refuses_a_bad_value_at_its_entry_before_writing(tmp_path, app, entry, kw, match):
    import importlib

    module, _, name = entry.partition(":")
    fn = getattr(importlib.import_module(module), name)
    out = tmp_path / "out"
    where = {"process": {"images": str(tmp_path), "out": str(out)}, "report": {"runs": str(tmp_path / "*"), "out": str(out)}}
    cfg = _app_cfg(app, **{"run": str(tmp_path / "no_run"), "out": str(out), **where.get(app, {}), **kw})
    if app in ("process", "report"):
        cfg.pop("run")
    if app == "view":
        cfg.pop("out")
    with pytest.raises(B3dgsError, match=match) as e:
        fn(cfg)
    assert e.value.fix and not out.exists()  # refused before the (missing) run is opened or anything is written
