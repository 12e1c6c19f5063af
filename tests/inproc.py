"""Apps run inside the test process as Hydra runs them (composed with Hydra's own node, ``HydraConfig`` set): for the
tests that spy on or patch b3dgs in-process; the CLI tests run the commands themselves."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import open_dict

from b3dgs.train import CONF_DIR, train


def compose_app(config_name: str, overrides: list[str], run_dir: Optional[Path] = None):
    """``config_name``'s config with ``overrides`` (``run_dir``: ``hydra.run.dir``) and Hydra's node, as the app's
    task gets it, with ``HydraConfig`` set."""
    GlobalHydra.instance().clear()
    over = [*([f"hydra.run.dir={run_dir}"] if run_dir is not None else []), *overrides]
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name=config_name, overrides=over, return_hydra_config=True)
    HydraConfig.instance().set_config(cfg)
    return cfg


def train_here(run_dir: Path, overrides: list[str]) -> dict:
    """``b3dgs-train`` into ``run_dir`` with ``overrides``, in this process; returns its metrics."""
    cfg = compose_app("train", overrides, run_dir)
    with open_dict(cfg):
        cfg.trainer.default_root_dir = str(run_dir)
    return train(cfg)
