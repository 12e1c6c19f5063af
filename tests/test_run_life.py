"""Issue 53 §1 and §4: one ``Run`` owns a run's life. Validation runs once per plugin per app (the config check builds
and validates each plugin, the model is built from those); the study validates each train-shaped config it composes;
anything added to a finished run goes through ``Run.amend_metrics`` (under its lock, listed in its manifest)."""
import collections
import json
from types import SimpleNamespace

import pytest
from hydra.core.global_hydra import GlobalHydra

from b3dgs.errors import B3dgsError
from tests.inproc import train_here

TINY = ["data.max_side=32", "+data.n_views=8", "trainer.enable_progress_bar=false", "logger=none",
        "trainer.max_steps=4", "trainer.eval_every=4", "trainer.save_renders=false"]


def _spy_validate(monkeypatch) -> collections.Counter:
    """Count ``validate`` calls per class over every plugin, schedule and UQ regime class loaded now."""
    import importlib
    import pkgutil

    import b3dgs_plugins
    from b3dgs.plugin import Plugin
    from b3dgs.schedule import TrainingSchedule
    from b3dgs.uq.regime import UQRegime

    for m in pkgutil.walk_packages(b3dgs_plugins.__path__, "b3dgs_plugins."):  # every plugin class, loaded now
        importlib.import_module(m.name)
    counts: collections.Counter = collections.Counter()
    depth = [0]  # a subclass's validate calling super().validate() is one validation

    def subclasses(c):
        for s in c.__subclasses__():
            yield s
            yield from subclasses(s)

    for cls in [base for b in (Plugin, TrainingSchedule, UQRegime) for base in (b, *subclasses(b))]:
        if "validate" in vars(cls):
            def spy(self, *a, _orig=vars(cls)["validate"], **k):
                depth[0] += 1
                try:
                    counts[type(self).__name__] += depth[0] == 1
                    return _orig(self, *a, **k)
                finally:
                    depth[0] -= 1
            monkeypatch.setattr(cls, "validate", spy)
    return counts


def _train(tmp_path, over):
    return train_here(tmp_path, [*TINY, *over])


def test_train_validates_each_plugin_once_and_amends_through_the_run(tmp_path, monkeypatch):
    counts = _spy_validate(monkeypatch)
    m = _train(tmp_path, ["model=niw", "schedule=dash"])
    # before issue 53: each plugin twice (the config check, the module), the dash schedule three times
    assert dict(counts) == {"AdaptiveDensityControl": 1, "DashSchedule": 1, "NIWBlock": 1}, dict(counts)

    from b3dgs.lifecycle import Run

    before = json.loads((tmp_path / "metrics.json").read_text())
    out = Run(run_dir=tmp_path).amend_metrics({"lpips": 0.25, "lpips_reason": None})
    after = json.loads((tmp_path / "metrics.json").read_text())
    assert out == after and after["lpips"] == 0.25 and after["psnr"] == before["psnr"] == m["psnr"]
    manifest = json.loads((tmp_path / ".b3dgs-run.json").read_text())
    assert manifest["amended"][-1]["keys"] == ["lpips", "lpips_reason"] and "metrics.json" in manifest["files"]
    (tmp_path / "metrics.json").unlink()
    with pytest.raises(B3dgsError, match="holds no finished run"):
        Run(run_dir=tmp_path).amend_metrics({"lpips": 0.5})


def test_the_study_validates_each_family_config_it_composes():
    from b3dgs.study.active import ActiveStudy, compose_config

    GlobalHydra.instance().clear()
    study = SimpleNamespace(cfg=compose_config("study", ["scene=fox"]), _family_cfgs={})
    assert ActiveStudy.family_cfg(study, "niw", 3).seed == 3
    GlobalHydra.instance().clear()
    bad = SimpleNamespace(cfg=compose_config("study", ["scene=fox", "strategy.refine_every=0"]), _family_cfgs={})
    with pytest.raises(B3dgsError, match="strategy.refine_every"):
        ActiveStudy.family_cfg(bad, "niw", 0)
