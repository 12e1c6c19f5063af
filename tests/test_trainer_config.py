"""The ``trainer`` node is a ``lightning.Trainer`` target: its flags are configurable, today's defaults hold, extra
callbacks come from the ``callbacks`` node, and old run dirs' trainer keys still build a trainer."""
import lightning as L
import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import open_dict

from b3dgs.errors import B3dgsError
from b3dgs.render.renderers import TorchRenderer
from b3dgs.lifecycle import build_callbacks, build_trainer
from b3dgs.train import CONF_DIR
from b3dgs.validation import validate_config
from tests.kill_hooks import KillAt


def _cfg(overrides=()):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=list(overrides))
    with open_dict(cfg):
        cfg.trainer.default_root_dir = "/tmp/unused"
    return cfg


def test_default_trainer_keeps_todays_settings(tmp_path):
    cfg = _cfg()
    trainer = build_trainer(cfg.trainer, TorchRenderer(), [], default_root_dir=str(tmp_path))
    assert isinstance(trainer, L.Trainer)
    assert trainer.max_steps == 3000 and trainer.precision == "32-true" and trainer.log_every_n_steps == 50
    assert trainer.num_sanity_val_steps == 0 and trainer.limit_val_batches == 0
    assert trainer.num_devices == 1 and trainer.accelerator.__class__.__name__ == "CPUAccelerator"


def test_trainer_flags_and_callbacks_are_configurable(tmp_path):
    cfg = _cfg(["trainer.precision=64-true", "trainer.enable_progress_bar=false",
                "+callbacks.kill._target_=tests.kill_hooks.KillAt", "+callbacks.kill.step=7",
                "+callbacks.timer._target_=lightning.pytorch.callbacks.Timer"])
    validate_config(cfg)
    extra = build_callbacks(cfg.callbacks)
    trainer = build_trainer(cfg.trainer, TorchRenderer(), extra, default_root_dir=str(tmp_path))
    assert trainer.precision == "64-true" and trainer.progress_bar_callback is None
    kinds = [type(c).__name__ for c in trainer.callbacks]
    assert "KillAt" in kinds and "Timer" in kinds
    assert next(c for c in trainer.callbacks if isinstance(c, KillAt)).step == 7


@pytest.mark.parametrize("override, message", [
    (["+trainer.max_stpes=5"], "did you mean max_steps"),
    (["+trainer.precison=16"], "did you mean precision"),
    (["trainer.log_every_n_steps=1.5"], "an integer"),
    (["+callbacks.x.every=3"], "callbacks.x has no _target_"),
    (["+callbacks.x._target_=tests.kill_hooks.KillAt", "+callbacks.x.stp=3"], "did you mean step"),
])
def test_bad_trainer_and_callback_settings_are_one_line_errors(override, message):
    with pytest.raises(B3dgsError, match=message):
        validate_config(_cfg(override))


def test_old_run_trainer_keys_build(tmp_path):
    """Run dirs written before the trainer node was a Trainer target: no _target_, progress_bar / log_every."""
    old = {"default_root_dir": str(tmp_path), "max_steps": 20, "accelerator": "auto", "eval_every": 5,
           "checkpoint_every": 10, "checkpoint_every_s": 300.0, "keep_checkpoints": False, "log_every": 7,
           "progress_bar": False, "save_renders": True, "curve_max_views": None}
    trainer = build_trainer(old, TorchRenderer(), [])
    assert trainer.max_steps == 20 and trainer.log_every_n_steps == 7 and trainer.progress_bar_callback is None
