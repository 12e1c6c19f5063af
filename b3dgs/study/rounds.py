"""Training in rounds: fit to a step, change the training set, fit on from the same model state.

A round is one ``trainer.fit`` up to ``stop_step`` of the run's TOTAL budget ``cfg.trainer.max_steps``
(the module's ``max_steps``): every schedule (means-lr decay, posterior stage thresholds, the
``${b3dgs.div:${trainer.max_steps},k}`` values, the strategy's refine window) is keyed to the global step
and the total budget, so a later round continues them. A round starts from the previous round's
``last.ckpt``: the same Gaussians, Adam moments, plugin states, RNGs and view-sampler stream (a grown
training set starts a fresh epoch of the sampler). Fitting to k then on to T on the same views is the
same run as fitting to T at once (``tests/test_rounds.py``).
"""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Optional

from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf

from b3dgs.errors import B3dgsError
from b3dgs.lifecycle import Run, build_run, checkpoint_every_s, load_checkpoint, read_checkpoint
from b3dgs.types import Scene

log = logging.getLogger(__name__)


def fit_round(cfg: DictConfig, scene: Scene, run_dir: Path, stop_step: int, ckpt_path: Optional[str] = None,
              new_round: bool = False, checkpoint_every: Optional[int] = None, plugins: Optional[dict] = None):
    """Train ``cfg``'s model on ``scene.train`` up to global step ``stop_step`` and return the module.

    ``ckpt_path``: continue from this checkpoint (an interrupted round, or the previous round when
    ``new_round``: then the training set may hold views the checkpoint's run did not have, from the same
    view pool). ``plugins``: those the study validated for ``cfg`` (by path, :func:`b3dgs.validation.validate_config`'s),
    else the model validates its own. ``run_dir/checkpoints/last.ckpt`` is written every ``checkpoint_every`` steps (default
    ``cfg.trainer.checkpoint_every``), every ``trainer.checkpoint_every_s`` seconds and at the end.
    """
    from b3dgs.callbacks import ResumeState, RunCheckpoint

    total = int(cfg.trainer.max_steps)
    if not 0 < int(stop_step) <= total:
        raise B3dgsError(f"a round must stop within the total budget: stop_step={stop_step}, trainer.max_steps={total}",
                         f"pass a stop step in 1..{total}, or raise trainer.max_steps")
    run = Run(cfg, run_dir, plugins=plugins)  # validated by the study that composed it (ActiveStudy.family_cfg)
    # a round continued from a checkpoint gets the guard counters back from it
    module = run.start(scene, reset_guards=ckpt_path is None)
    module.allow_new_views = run.dm.allow_new_views = bool(new_round)
    run.run_dir.mkdir(parents=True, exist_ok=True)
    every = int(checkpoint_every if checkpoint_every is not None else cfg.trainer.checkpoint_every)
    ckpt = RunCheckpoint(run.run_dir / "checkpoints", every_n_steps=every, every_s=checkpoint_every_s(cfg.trainer))
    run.fit([ResumeState(), ckpt], ckpt_path, max_steps=int(stop_step), enable_checkpointing=True)
    module.allow_new_views = False
    return module


def load_round(cfg: DictConfig, scene: Scene, ckpt_path: str, plugins: Optional[dict] = None):
    """A module holding ``ckpt_path``'s model for scoring or evaluation (no trainer; on the renderer's device), built
    from ``plugins`` as :func:`fit_round`."""
    return load_checkpoint(build_run(cfg, scene, plugins=plugins), read_checkpoint(ckpt_path), new_views=True)


def training_signature(cfg: DictConfig) -> str:
    """A run's training config as a string, without the model's name and without the posterior blocks that
    promise not to change training (``changes_training = False``, checked bit for bit in
    ``tests/test_rounds.py``): two configs with equal signatures train the same run."""
    d = OmegaConf.to_container(cfg, resolve=True)
    d.pop("hydra", None)
    d["model"].pop("name", None)
    d["posterior"] = {k: v for k, v in (d.get("posterior") or {}).items() if get_class(v["_target_"]).changes_training}
    return json.dumps(d, sort_keys=True, default=str)
