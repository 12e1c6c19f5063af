"""One run's lifecycle, the one home of what every run does (training, a study's rounds, the compression study's
fine-tunes, loading a run):

* :func:`start_run`: :func:`seed_run`, the data module (:func:`data_module`) and the model (:func:`build_run`);
* :class:`Run`, one run's life: validation once, :meth:`Run.fit` (the one trainer, :func:`build_trainer`),
  ``b3dgs-train``'s run (:meth:`Run.train`), ``metrics.json`` (:meth:`Run.finish`, :meth:`Run.amend_metrics`) and a
  study's records of a run (:meth:`Run.record`);
* :func:`load_checkpoint` and the checks of a resume (:func:`check_resume`, :func:`check_resume_renderer`);
* the checks of a run's settings (:func:`check_devices`, :func:`warn_slow_renderer`, :func:`warn_disabled_options`,
  :func:`warn_long_cpu_run`).

The run dir (lock, claim, resume and overwrite) is :mod:`b3dgs.rundir`'s.
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import warnings
from collections import OrderedDict
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

import torch
from omegaconf import DictConfig, OmegaConf

from b3dgs.checkpoint import check_sealed, checkpoint_record, renderer_identity, renderer_mismatch
from b3dgs.device import machine
from b3dgs.errors import B3dgsError
from b3dgs.io import write_json
from b3dgs.numerics import guard_counts, reset_guards as _reset
from b3dgs.render.renderers import Renderer, make_renderer
from b3dgs.rundir import (claim_run_dir, finished_metrics, manifest_lock, prepare_run_dir, record_amended,
                          record_written, run_dir_lock, save_config, start_manifest, write_manifest)
from b3dgs.signals import Interrupted, interrupt_handlers
from b3dgs.types import Scene
from b3dgs.upgrade import renderer_option, trainer_arg

if TYPE_CHECKING:
    from b3dgs.data.datamodule import SceneDataModule

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------------ the model
def build_plugins(cfg: DictConfig, built: Optional[dict] = None):
    """Instantiate the strategy and the configured posterior blocks (in their listed order), but those in ``built``
    (by path, ``strategy`` and ``posterior.<name>``: the plugins the config check built, :class:`Run`)."""
    from hydra.utils import instantiate

    def make(path, node):
        return built[path] if built and path in built else instantiate(node)

    strategy = make("strategy", cfg.strategy)
    return strategy, OrderedDict((name, make(f"posterior.{name}", node)) for name, node in (cfg.get("posterior") or {}).items())


def build_renderer(node) -> "Renderer":
    """The renderer plugin of a config's ``renderer`` node (an older node: the option it names,
    :func:`b3dgs.upgrade.renderer_option`), checked to run on this machine."""
    from hydra.utils import instantiate

    option = renderer_option(node)
    renderer = instantiate(node) if option is None else make_renderer(option)
    renderer.check_available()
    return renderer


def build_module(cfg: DictConfig, strategy, blocks, renderer=None, schedule=None):
    """The ``model`` node's module with the arguments the run fills itself (b3dgs.validation.MODEL_SET_BY_RUN);
    ``schedule``: one built already, else the ``schedule`` node's."""
    from hydra.utils import instantiate

    from b3dgs.schedule import make_schedule

    return instantiate(cfg.model, _partial_=True)(
        strategy=strategy, posterior=blocks, renderer=renderer if renderer is not None else build_renderer(cfg.get("renderer")),
        max_steps=int(cfg.trainer.max_steps), seed=int(cfg.seed),
        schedule=make_schedule(schedule if schedule is not None else cfg.get("schedule")),
    )


def build_run(cfg: DictConfig, scene: "Scene", *, renderer=None, init: bool = True, plugins: Optional[dict] = None):
    """The model of a run, the one build sequence of b3dgs: :func:`build_plugins` (but ``plugins``, built already, by
    path) -> :func:`build_renderer` (or ``renderer``: a plugin, or a function of the config that makes one) ->
    :func:`build_module` -> ``init_from_scene(scene)``; ``init=False`` only attaches ``scene``."""
    plugins = plugins or {}
    strategy, blocks = build_plugins(cfg, plugins)
    if renderer is None or callable(renderer):
        renderer = renderer(cfg) if renderer else build_renderer(cfg.get("renderer"))
    module = build_module(cfg, strategy, blocks, renderer, plugins.get("schedule"))
    if init:
        module.init_from_scene(scene)
    else:
        module.scene = scene
    return module


# ------------------------------------------------------------------------------------ start of a run
def seed_run(seed: int, threads: Optional[int] = None, reset_guards: bool = True) -> None:
    """Seed every RNG for a run (``lightning.seed_everything``, workers included; ``PL_GLOBAL_SEED`` is dropped
    first, as it survives between multirun jobs), reset the numerical guard counters (``reset_guards``; a round
    continued from a checkpoint gets its counters back from it) and set torch's CPU threads (``threads``)."""
    import lightning as L

    os.environ.pop("PL_GLOBAL_SEED", None)
    L.seed_everything(int(seed), workers=True, verbose=False)
    if reset_guards:
        _reset()
    if threads:
        torch.set_num_threads(int(threads))


def data_module(data, keep_raw: bool = False) -> "SceneDataModule":
    """A run's data module with its scene read (``setup("fit")``), the one place a run reads its scene: ``data``
    is a config's ``data`` node (instantiated), a :class:`~b3dgs.types.Scene` already read (served as it is) or a
    data module. ``keep_raw``: keep what was read, for :meth:`~b3dgs.data.datamodule.SceneDataModule.select_train`."""
    from hydra.utils import instantiate

    from b3dgs.data.datamodule import SceneDataModule

    if isinstance(data, Scene):
        return SceneDataModule(scene=data)
    dm = data if isinstance(data, SceneDataModule) else instantiate(data)
    dm.keep_raw = bool(keep_raw)
    dm.setup("fit")
    return dm


def start_run(cfg: DictConfig, data=None, *, seed: Optional[int] = None, threads: bool = True,
              reset_guards: bool = True, init: bool = True, plugins: Optional[dict] = None):
    """The start of every run that trains: :func:`seed_run` (``seed``, default ``cfg.seed``; ``cfg.threads`` unless
    ``threads=False``), the data module (:func:`data_module` of ``data``, default ``cfg.data``) and the model
    (:func:`build_run` on its scene, from ``plugins`` where given; ``init=False``: the caller sets the parameters).
    Returns ``(datamodule, module)``."""
    seed_run(int(cfg.seed if seed is None else seed), cfg.get("threads") if threads else None, reset_guards)
    dm = data_module(cfg.data if data is None else data)
    return dm, build_run(cfg, dm.scene, init=init, plugins=plugins)


# ---------------------------------------------------------------------------------------- the trainer
def resolve_accelerator(requested: Optional[str], renderer) -> str:
    """Lightning's accelerator for ``trainer.accelerator``: ``auto`` follows the renderer's device."""
    want = renderer.device.type
    req = str(requested or "auto")
    if req == "auto":
        return want
    if {"gpu": "cuda"}.get(req, req) != want:
        raise B3dgsError(f"trainer.accelerator={req} does not match renderer={renderer.name}, which runs on {want}",
                         f"trainer.accelerator=auto, or pick a renderer for {req}")
    return req


#: keys of the ``trainer`` node that b3dgs reads itself (its callbacks and final outputs); every other key is an
#: argument of the node's ``_target_`` (``lightning.Trainer``)
RUN_KEYS = ("eval_every", "curve_max_views", "checkpoint_every", "checkpoint_every_s", "keep_checkpoints",
            "save_renders")


def build_callbacks(node) -> list:
    """The configured extra callbacks (``callbacks: {name: {_target_: ...}}``), in their listed order; they run
    after b3dgs's own callbacks (Lightning runs checkpoint callbacks, such as ``last.ckpt``'s, last of all)."""
    from hydra.utils import instantiate

    return [instantiate(n) for n in (node or {}).values() if n is not None]


def build_trainer(tcfg, renderer, callbacks: list, logger=False, final_after_eval: bool = False, **fixed):
    """The ``trainer`` node's ``_target_`` (``lightning.Trainer``) built with its own arguments, the accelerator
    resolved from the renderer (:func:`resolve_accelerator`), ``callbacks``, ``logger``, b3dgs's atomic checkpoint
    IO, and ``fixed`` (what a caller sets whatever the config says, e.g. a round's ``max_steps``). With the progress
    bar on, it is b3dgs's bar over global steps (:class:`b3dgs.callbacks.StepProgressBar`) unless ``callbacks`` has one;
    ``final_after_eval``: its last line waits for the final evaluation (``StepProgressBar.show_final``)."""
    from hydra.utils import instantiate
    from lightning.pytorch.callbacks import ProgressBar

    from b3dgs.callbacks import AtomicCheckpointIO, StepProgressBar

    keys = [str(k) for k in tcfg.keys() if k not in RUN_KEYS and trainer_arg(k) not in fixed]
    # resolved one by one in place (interpolations may point anywhere in the config; fixed ones are never read)
    args = {trainer_arg(k): tcfg[k] for k in keys}
    args = {k: OmegaConf.to_container(v, resolve=True) if OmegaConf.is_config(v) else v for k, v in args.items()}
    args.setdefault("_target_", "lightning.Trainer")
    args["accelerator"] = resolve_accelerator(args.get("accelerator"), renderer)
    args.update(fixed)
    if args.get("enable_progress_bar", True) and not any(isinstance(c, ProgressBar) for c in callbacks):
        callbacks = [*callbacks, StepProgressBar()]
    # objects go in through a partial (instantiate would turn them into configs: hydra#2591)
    trainer = instantiate(args, _partial_=True)(callbacks=callbacks, logger=logger, plugins=[AtomicCheckpointIO()])
    if final_after_eval and isinstance(trainer.progress_bar_callback, StepProgressBar):
        trainer.progress_bar_callback.final_after_eval = True
    return trainer


def checkpoint_every_s(tcfg) -> Optional[float]:
    """``trainer.checkpoint_every_s`` checked: seconds between time-based checkpoints, or ``None``."""
    v = tcfg.get("checkpoint_every_s")
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not v >= 0:
        raise B3dgsError(f"trainer.checkpoint_every_s={v} is invalid: it must be a number of seconds >= 0 or null",
                         "pass trainer.checkpoint_every_s=300, or 0 / null for step-based checkpoints only")
    return float(v)


def fit_on_renderer_device(trainer, module, **fit_kwargs) -> None:
    """``trainer.fit(module, ...)``, then the module back on its renderer's device. Lightning's teardown moves a
    model trained on a GPU to the CPU, and all that follows training (the final evaluation, the posterior pass,
    a study's scoring, exports) renders with the run's renderer: gsplat refuses CPU tensors. On the CPU it is a
    no-op."""
    trainer.fit(module, **fit_kwargs)
    device = module.renderer.device
    if module.device.type != device.type:
        module.to(device)


# ----------------------------------------------------------------------------------------- checkpoints
def read_checkpoint(path, mmap: bool = False) -> dict:
    """A b3dgs checkpoint, on the CPU (with its plugin states and config values: not ``weights_only``)."""
    return torch.load(path, map_location="cpu", weights_only=False, mmap=mmap)


def load_checkpoint(module, ck: dict, new_views: bool = False):
    """Put the model of checkpoint ``ck`` into ``module`` (built by :func:`build_run`) for scoring or evaluation:
    plugin states, parameters and the step it was saved at; returns it in eval mode on its renderer's device.
    ``new_views``: the module's scene may train on views the checkpoint's run did not have (a study's round)."""
    module.allow_new_views = bool(new_views)
    try:
        module.on_load_checkpoint(ck)
    finally:
        module.allow_new_views = False
    module.load_state_dict(ck["state_dict"])
    module._loaded_step = int(ck.get("global_step", 0))
    module.eval()
    module.to(module.renderer.device)
    return module


def check_resume_renderer(cfg: DictConfig, ckpt_path: str) -> None:
    """Refuse to resume with another renderer (backend, device or setting) than the checkpoint's run used: the
    identity of the renderer in the checkpoint, or (checkpoints written before it was recorded) the ``renderer``
    node of its run dir's config.yaml. A damaged checkpoint passes here (:func:`check_resume` names it)."""
    try:
        saved = ((read_checkpoint(ckpt_path, mmap=True).get("b3dgs") or {}).get("identity") or {}).get("renderer")
    except Exception:  # noqa: BLE001
        return
    node = cfg.get("renderer")
    if saved:
        logger = logging.getLogger("b3dgs.render.renderers")
        level = logger.level
        logger.setLevel(logging.WARNING)  # the run builds (and names) its renderer again later
        try:
            current = renderer_identity(build_renderer(node))
        finally:
            logger.setLevel(level)
        bad = renderer_mismatch(saved, current)
    else:
        cfg_path = Path(ckpt_path).resolve().parent.parent / "config.yaml"
        try:
            old = OmegaConf.load(cfg_path).get("renderer") if cfg_path.is_file() else None
        except Exception:  # noqa: BLE001
            old = None
        plain = (lambda n: OmegaConf.to_container(n, resolve=True) if OmegaConf.is_config(n) else n)  # noqa: E731
        bad = renderer_mismatch(plain(old), plain(node), resolved=False)
    if bad is not None:
        problem, want = bad
        raise B3dgsError(f"resume: the checkpoint {ckpt_path} does not match this run: {problem}",
                         f"pass {want}, or start afresh with overwrite=true or another hydra.run.dir (a resume "
                         "continues the same run exactly)")


def check_resume(module, ckpt_path: str) -> None:
    """Refuse to resume a checkpoint of another model, posterior, strategy, scene, schedule or seed, or one whose
    content changed on disk since it was written (:func:`b3dgs.checkpoint.check_sealed`)."""
    try:
        ck = read_checkpoint(ckpt_path, mmap=True)
    except Exception as e:  # noqa: BLE001 - damaged file: say which and how to go on
        raise B3dgsError(f"cannot read the checkpoint {ckpt_path} ({type(e).__name__})",
                         "pass resume=PATH to an intact .ckpt, or overwrite=true to start afresh") from None
    module.check_checkpoint_identity(
        ck, f"resume: the checkpoint {ckpt_path}",
        "start afresh with overwrite=true or another hydra.run.dir (a resume continues the same run exactly)")
    check_sealed(ck, f"resume: the checkpoint {ckpt_path}",  # before the run dir is touched (Lightning checks again)
                 "start afresh with overwrite=true, or pass resume=PATH to an earlier intact checkpoint of this run")


# ------------------------------------------------------------------------------ settings checked at start
def _device_count(v: Any) -> int:
    """How many devices ``trainer.devices`` asks for (-1: all of them, as Lightning reads it)."""
    if isinstance(v, (list, tuple)) or OmegaConf.is_list(v):
        return len(v)
    try:
        return int(str(v))
    except ValueError:
        return 1  # "auto": one device on the CPU


def _show_value(v: Any) -> str:
    if OmegaConf.is_config(v):
        v = OmegaConf.to_container(v)
    return "[" + ",".join(map(str, v)) + "]" if isinstance(v, (list, tuple)) else str(v)


def check_devices(cfg: DictConfig) -> None:
    """Refuse ``trainer.devices`` > 1 (or -1) on the CPU: Lightning would start training processes that fight
    over the run dir."""
    devices = cfg.trainer.get("devices", 1)
    n = _device_count(devices)
    node = cfg.get("renderer")
    target = str(node.get("_target_", "")) if isinstance(node, DictConfig) else str(node or "")
    on_cpu = (not torch.cuda.is_available() or str(cfg.trainer.get("accelerator", "auto")) == "cpu"
              or target.endswith(("CPURenderer", "cpu"))
              or (target.endswith("TorchRenderer") and str(node.get("device_name", "auto")) == "cpu"))
    if on_cpu and (n > 1 or n == -1):
        raise B3dgsError(f"trainer.devices={_show_value(devices)} asks for several training processes on the CPU, "
                         "which b3dgs does not run (they would share one run dir)",
                         "pass trainer.devices=1; threads=N sets how many CPU threads the one process uses")


#: a run the renderer's stated speed puts above this many seconds gets a warning before it starts
SLOW_RUN_S = 600.0


def warn_slow_renderer(cfg: DictConfig) -> Optional[str]:
    """A warning (logged and returned) when the renderer states a CPU cost per step (``cpu_seconds_per_step``, e.g.
    the pure-PyTorch reference's ~1 s) that puts ``trainer.max_steps`` above :data:`SLOW_RUN_S` on the CPU."""
    from b3dgs.schema import locate, value

    node = cfg.get("renderer")
    target = locate(str(node["_target_"])) if isinstance(node, DictConfig) and "_target_" in node else None
    per_step, steps = getattr(target, "cpu_seconds_per_step", None), value(cfg.trainer, "max_steps", "trainer.max_steps")
    device = str(node.get("device_name", "cpu")) if target else ""
    on_cpu = device == "cpu" or (device == "auto" and not torch.cuda.is_available())
    if not (per_step and on_cpu and isinstance(steps, int) and steps > 0 and steps * per_step > SLOW_RUN_S):
        return None
    msg = (f"renderer={getattr(target, 'name', node['_target_'])} trains at about "
           f"{per_step:g} s per step on the CPU: trainer.max_steps={steps} will take about {steps * per_step / 60:.0f} "
           f"min (fix: renderer=cpu, the C++ backend, is ~40x faster; or fewer trainer.max_steps)")
    log.warning(msg)
    return msg


#: the C++ CPU kernels' training cost per pixel per step at ~50k Gaussians on this project's 2-core CPU (fox at
#: 256x144 px, 3000 steps in 163 s: bench/results/train.md); more Gaussians cost more
CPU_SECONDS_PER_PIXEL_STEP = 1.5e-6
#: a CPU run that this rate puts above this many seconds gets a warning with the expected time
LONG_CPU_RUN_S = 3600.0


def warn_long_cpu_run(scene, renderer, max_steps: int) -> Optional[str]:
    """A warning (logged and returned) when training ``max_steps`` steps on ``scene``'s training views with a CPU
    renderer is expected to take over :data:`LONG_CPU_RUN_S` at :data:`CPU_SECONDS_PER_PIXEL_STEP` (a lower bound)."""
    if torch.device(renderer.device).type != "cpu" or not scene.train:
        return None
    pixels = sum(int(c.width) * int(c.height) for c in scene.train) / len(scene.train)
    hours = int(max_steps) * pixels * CPU_SECONDS_PER_PIXEL_STEP / 3600.0
    if hours * 3600.0 <= LONG_CPU_RUN_S:
        return None
    c = scene.train[0]
    msg = (f"trainer.max_steps={int(max_steps)} on {len(scene.train)} training views of about {c.width}x{c.height} px "
           f"on the CPU renderer ({renderer.name}) will take at least ~{hours:.1f} h (about "
           f"{CPU_SECONDS_PER_PIXEL_STEP * 1e6:g} µs per pixel per step on 2 quiet cores at 50k Gaussians, more as they grow) "
           "(fix: train on a CUDA GPU with gsplat, for which experiment=paper is made; experiment=study is the CPU "
           "protocol: 256 px, 3000 steps)")
    log.warning(msg)
    return msg


def warn_cpu_size_on_gpu(scene, renderer, max_side, experiment: Optional[str]) -> Optional[str]:
    """A warning (logged and returned) when a CUDA run trains at the CPU protocol's image size: no ``experiment=``
    chosen (``b3dgs-train data.path=DIR`` on a GPU) and the training views cut to ``data.max_side``;
    ``experiment=paper`` is made for a GPU."""
    if torch.device(renderer.device).type != "cuda" or max_side is None or experiment:
        return None
    if not any(max(int(c.width), int(c.height)) == int(max_side) for c in scene.train):
        return None  # the files are no larger than the cap
    msg = (f"training on a CUDA GPU at data.max_side={max_side} px, the CPU protocol's image size (fix: pass "
           "experiment=paper for the paper's protocol, or data.max_side=null for the files' full size)")
    log.warning(msg)
    return msg


def warn_disabled_options(module) -> None:
    """Warn where one setting silently turns off another (``strategy.max_gaussians`` below the initial count)."""
    cap = getattr(module.strategy, "max_gaussians", None)
    n = int(module.num_gaussians)
    if isinstance(cap, int) and not isinstance(cap, bool) and cap < n:
        log.warning("strategy.max_gaussians=%d is below the %d initial Gaussians: no Gaussian is ever added "
                    "(densification by clone and split is off; only pruning changes the count) (fix: raise "
                    "strategy.max_gaussians above %d, or lower model.init_max_points)", cap, n, n)


# ------------------------------------------------------------------------------------------------ a run
class Run:
    """One run's life, for every command that trains: the config validated once (``app``, e.g. ``"train"``; ``None``
    where a study validated it, giving ``plugins``), seed and build (:meth:`start`), the one trainer (:meth:`fit`), the
    final evaluation and ``metrics.json`` (:meth:`finish`, its one writer; :meth:`amend_metrics`), and a study's
    records of a run it trained (:meth:`record`)."""

    def __init__(self, cfg: Optional[DictConfig] = None, run_dir=None, app: Optional[str] = None,
                 plugins: Optional[dict] = None):
        self.cfg, self.plugins, self.dm, self.module = cfg, plugins or {}, None, None
        self.run_dir = Path(run_dir if run_dir is not None else cfg.trainer.default_root_dir)
        if app is None:
            return
        from b3dgs.validation import validate_config

        try:
            self.plugins = validate_config(cfg, app=app)
            check_devices(cfg)
            warn_slow_renderer(cfg)
        except BaseException:  # also a signal (b3dgs.signals.Interrupted)
            with contextlib.suppress(OSError):
                self.run_dir.rmdir()  # Hydra made it; a refused run leaves nothing
            raise

    def start(self, data=None, **kw):
        """:func:`start_run` of this run's config (``data``, ``kw``), its first model from the validated plugins;
        returns the module."""
        self.dm, self.module = start_run(self.cfg, data, plugins=self.plugins, **kw)
        self.plugins = {}
        return self.module

    def fit(self, callbacks=(), ckpt_path: Optional[str] = None, *, claim=None, logger=False,
            final_after_eval: bool = False, **fixed):
        """The one place a trainer is assembled (:func:`build_trainer` with ``callbacks``, then the config's, and
        ``fixed``) and fit (:func:`fit_on_renderer_device`) on the started model, from ``ckpt_path`` if given;
        ``claim()`` runs once the trainer is built, before anything trains. Returns the trainer."""
        trainer = build_trainer(self.cfg.trainer, self.module.renderer,
                                [*callbacks, *build_callbacks(self.cfg.get("callbacks"))], logger=logger,
                                final_after_eval=final_after_eval, default_root_dir=str(self.run_dir), **fixed)
        if claim is not None:
            claim()
        try:
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message=".*does not have many workers.*")
                warnings.filterwarnings("ignore", message=".*`training_step` returns.*")
                fit_on_renderer_device(trainer, self.module, datamodule=self.dm, ckpt_path=ckpt_path,
                                       weights_only=False)
        except Interrupted as e:  # a signal outside the steps (e.g. once training is done): the step it is at
            if e.step is None and trainer.global_step:
                e.step = int(trainer.global_step)
            raise
        return trainer

    def train(self) -> dict:
        """``b3dgs-train``'s run into the run dir under its lock (:func:`b3dgs.train.train`'s contract)."""
        with interrupt_handlers(), run_dir_lock(self.run_dir):
            return self._train(self.cfg, self.cfg.trainer, self.run_dir)

    def _train(self, cfg: DictConfig, tcfg, run_dir: Path) -> dict:
        from hydra.utils import instantiate
        from lightning.pytorch.loggers import TensorBoardLogger  # noqa: F401 - logger=tensorboard targets it

        from b3dgs.callbacks import CurveCallback, ResumeState, RunCheckpoint, RunFiles
        from b3dgs.validation import hydra_value

        every_s = checkpoint_every_s(tcfg)
        ckpt_path, clear = prepare_run_dir(run_dir, cfg.get("resume"), cfg.get("overwrite", False),
                                           check_checkpoint=lambda path: check_resume_renderer(cfg, path))
        module = self.start()
        scene, renderer = self.dm.scene, module.renderer
        warn_disabled_options(module)
        warn_long_cpu_run(scene, renderer, int(tcfg.max_steps))
        warn_cpu_size_on_gpu(scene, renderer, cfg.data.get("max_side"), hydra_value(cfg, "runtime.choices.experiment", None))
        if ckpt_path is not None:
            check_resume(module, ckpt_path)
        done = None if clear else finished_metrics(run_dir)
        if done is not None:  # resume=auto on a finished run of these settings: nothing to do, nothing rewritten
            psnr = done.get("psnr")
            log.info("%s holds a finished run (step %s, PSNR %s dB): nothing to do, nothing rewritten (overwrite=true "
                     "trains it again)", run_dir, done.get("steps"), "n/a" if psnr is None else f"{psnr:.3f}")
            return done
        curve = CurveCallback(scene.test, eval_every=int(tcfg.eval_every), out_dir=run_dir,
                              max_eval_views=tcfg.get("curve_max_views"))
        ckpt = RunCheckpoint(run_dir / "checkpoints", every_n_steps=int(tcfg.checkpoint_every), every_s=every_s,
                             keep=bool(tcfg.get("keep_checkpoints")))

        def claim() -> None:  # every check has passed: only now is the run dir changed, manifest first
            claim_run_dir(run_dir, cfg, clear)
            log.info("Scene %s: %d train / %d test views, %d initial Gaussians, extent %.3f; renderer %s on %s",
                     scene.name, len(scene.train), len(scene.test), module.num_gaussians, scene.extent, renderer.name,
                     renderer.device)

        trainer = self.fit([curve, ResumeState(), ckpt, RunFiles(run_dir)], ckpt_path, claim=claim,
                           logger=instantiate(cfg.logger, save_dir=str(run_dir)) if cfg.get("logger") else False,
                           final_after_eval=True)
        try:
            return self.finish(trainer, curve, ckpt)
        except Interrupted as e:
            e.step = int(trainer.global_step)
            raise

    def finish(self, trainer, curve, ckpt) -> dict:
        """The final evaluation and outputs of the trained model (also all a resume from the final checkpoint does),
        each written atomically: renders, PLY, curve, then ``metrics.json`` (the done marker)."""
        import time

        from b3dgs.callbacks import StepProgressBar
        from b3dgs.data.scene import scene_transform
        from b3dgs.labels import method_label
        from b3dgs.metrics.lpips import get_lpips
        from b3dgs.metrics.views import evaluate_views
        from b3dgs.ply import frame_comments, write_splats

        cfg, run_dir, module, scene, renderer = self.cfg, self.run_dir, self.module, self.dm.scene, self.module.renderer
        tcfg = cfg.trainer
        final = checkpoint_record(read_checkpoint(ckpt.last_path, mmap=True))
        t_pass = time.perf_counter()
        passed = module.prepare_posterior(scene.train)  # counts from a view pass (posterior.niw.count other than paper)
        posterior_pass_s = time.perf_counter() - t_pass if passed else 0.0
        lpips_model, lpips_reason = get_lpips(cfg.get("lpips_weights"))
        if tcfg.get("save_renders", True):  # listed in the run manifest before they are written
            record_written(run_dir, [f"renders/{Path(c.name).stem}.png" for c in scene.test])
        ev = evaluate_views(module, scene.test, lpips_model=lpips_model,
                            render_dir=run_dir / "renders" if tcfg.get("save_renders", True) else None)
        frame = scene_transform(scene)  # point_cloud.ply in the scene's own (COLMAP / transforms.json) frame
        write_splats(run_dir / "point_cloud.ply", {k: v.data for k, v in module.splats.items()}, frame.inverse(),
                     extra=module.export_extras(), comments=frame_comments(frame))
        curve.write()
        metrics = {
            "method": method_label(cfg), "scene": scene.name, "seed": int(cfg.seed), "steps": int(trainer.global_step),
            "psnr": ev.get("psnr"), "ssim": ev.get("ssim"), "lpips": ev.get("lpips"),
            "lpips_reason": None if lpips_model is not None else lpips_reason,
            "num_gaussians": module.num_gaussians, "train_time_s": round(curve.train_time_s, 3),
            "render_fps": ev["render_fps"], "renderer": renderer.describe(),
            "num_train_views": len(scene.train), "num_test_views": len(scene.test),
            "calib_views": [c.name for c in scene.calib],
            "removed": dict(module.ops.removed) if module.ops else {},
            "added": dict(module.ops.added) if module.ops else {},
            "block_time_s": {k: round(v, 4) for k, v in module.block_time_s.items()},
            "posterior_pass_s": round(posterior_pass_s, 4),  # the blocks' pass over the training views after training
            "schedule": module.schedule.summary(),
            "posterior": {name: blk.summary(state=module.states[name]) for name, blk in module.posterior.items()},
            "numerical_guards": guard_counts(),  # how often each clamp / jitter / floor fired (never silent)
            "checkpoint": final,  # b3dgs-eval refuses a last.ckpt that is not this model
            "scene_transform": frame.to_dict(),  # normalised frame <- the scene's own (point_cloud.ply is in the latter)
            "machine": machine(),  # bits reproduce on the same kind of machine (b3dgs.device.machine)
            "per_view": ev["per_view"],
        }
        self._write_metrics(metrics)
        if isinstance(trainer.progress_bar_callback, StepProgressBar):
            trainer.progress_bar_callback.show_final(metrics)

        def fmt(v, digits):
            return "n/a" if v is None else f"{v:.{digits}f}"

        quality = ("no test views to score (data.test_every=0)" if metrics["psnr"] is None else
                   f"PSNR {fmt(metrics['psnr'], 3)} dB, SSIM {fmt(metrics['ssim'], 4)}, LPIPS {fmt(metrics['lpips'], 4)}")
        log.info("Done: %s, %d Gaussians, %.1f s training -> %s", quality, metrics["num_gaussians"],
                 metrics["train_time_s"], run_dir)
        return metrics

    def amend_metrics(self, update: dict, prog: str = "b3dgs") -> dict:
        """Set ``update``'s keys in the finished run's ``metrics.json`` (e.g. LPIPS filled in later), under the run
        dir's lock, atomically, listed in its manifest (:func:`b3dgs.rundir.record_amended`); returns the metrics."""
        with manifest_lock(self.run_dir, prog):
            metrics = finished_metrics(self.run_dir)
            if metrics is None:
                raise B3dgsError(f"{self.run_dir} holds no finished run to add {', '.join(update)} to",
                                 f"finish it first: b3dgs-train ... hydra.run.dir={self.run_dir} resume=auto")
            metrics.update(update)
            record_amended(self.run_dir, update)
            self._write_metrics(metrics)
        return metrics

    def _write_metrics(self, metrics: dict) -> None:
        write_json(self.run_dir / "metrics.json", metrics)  # the one writer of a run's done marker

    def record(self, name: str, payload: dict, prog: str = "b3dgs-study") -> dict:
        """Write a study's record of this run (a row's ``selection.json`` and ``result.json``, its done marker; phase 1's
        ``phase1.json``; a compression row's ``result.json``) atomically, under the run dir's lock, listed in its
        manifest (made by the first record); returns ``payload``."""
        self.run_dir.mkdir(parents=True, exist_ok=True)
        with manifest_lock(self.run_dir, prog):
            start_manifest(self.run_dir)
            record_written(self.run_dir, [name])
            write_json(self.run_dir / name, payload)
        return payload

    def recorded(self, name: str) -> Optional[dict]:
        """This run's study record ``name`` (:meth:`record`), or None before it is written."""
        path = self.run_dir / name
        return json.loads(path.read_text()) if path.is_file() else None

    @contextlib.contextmanager
    def exclusive(self):
        """This run for one process at a time (parallel seeds of a study share phase-1 models): a lock beside the run
        dir (:mod:`b3dgs.locks`), released when its holder exits, also when it is killed."""
        from b3dgs.locks import process_lock

        self.run_dir.parent.mkdir(parents=True, exist_ok=True)
        with process_lock(self.run_dir.parent / f".{self.run_dir.name}.lock"):
            yield

    def share_training(self, twin) -> dict:
        """This run is the finished run ``twin``'s training (an equal training config: bench's training twins): its
        manifest and config.yaml, ``twin``'s curve, and ``twin``'s metrics with ``training_shared_with`` naming it
        (the done marker, last); no checkpoint. Returns the metrics."""
        import shutil

        twin = Path(twin)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        with run_dir_lock(self.run_dir):
            write_manifest(self.run_dir)
            save_config(self.cfg, self.run_dir / "config.yaml")
            if (twin / "curve.json").exists():
                shutil.copy2(twin / "curve.json", self.run_dir / "curve.json")
            metrics = json.loads((twin / "metrics.json").read_text())
            metrics.update({"method": str(self.cfg.model.name), "training_shared_with": str(twin)})
            self._write_metrics(metrics)
        return metrics
