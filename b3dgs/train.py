"""``b3dgs-train``: the Hydra app that trains one model and writes its run dir.

``train(cfg)`` does the work and returns the metrics dict; ``main()`` is the console entry point: known
errors print ``b3dgs-train: error: <problem> (fix: <what to do>)`` and exit with code 2 (full traceback
with ``HYDRA_FULL_ERROR=1`` or ``b3dgs.debug=true``).
"""
from __future__ import annotations

import logging
import os
import sys
import time
import warnings
from collections import OrderedDict
from pathlib import Path
from typing import Any, Optional

import hydra
import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from b3dgs.io import write_json

log = logging.getLogger(__name__)

from b3dgs import conf_dir
from b3dgs.errors import B3dgsError
from b3dgs.labels import method_label, register_resolver

CONF_DIR = conf_dir()
register_resolver()  # ${b3dgs.method:} in run dir names (conf/hydra/default.yaml)


def build_plugins(cfg: DictConfig):
    """Instantiate the strategy and the configured posterior blocks (in their listed order)."""
    from hydra.utils import instantiate

    strategy = instantiate(cfg.strategy)
    blocks: "OrderedDict[str, Any]" = OrderedDict()
    post = cfg.get("posterior") or {}
    for name, node in post.items():
        blocks[name] = instantiate(node)
    return strategy, blocks


def build_renderer(node) -> "Renderer":
    """The renderer plugin of a config's ``renderer`` node, checked to run on this machine.

    Run dirs written before renderers were plugins hold ``renderer: {backend: cpu|torch}``.
    """
    from hydra.utils import instantiate

    from b3dgs.render.renderers import make_renderer

    if node is None or isinstance(node, str):
        renderer = make_renderer(node or "auto")
    elif "_target_" in node:
        renderer = instantiate(node)
    else:
        renderer = make_renderer(str(node.get("backend", "auto")))
    renderer.check_available()
    return renderer


def build_module(cfg: DictConfig, strategy, blocks, renderer=None):
    from hydra.utils import instantiate

    from b3dgs.schedule import make_schedule

    return instantiate(cfg.model, _partial_=True)(
        strategy=strategy, posterior=blocks, renderer=renderer if renderer is not None else build_renderer(cfg.get("renderer")),
        max_steps=int(cfg.trainer.max_steps), seed=int(cfg.seed), schedule=make_schedule(cfg.get("schedule")),
    )


def _config_renderer(cfg: DictConfig) -> "Renderer":
    return build_renderer(cfg.get("renderer"))


def build_run(cfg: DictConfig, scene: "Scene", *, renderer=None, init: bool = True):
    """The model of a run, the one build sequence of b3dgs (training, rounds, loading a run, compression):
    :func:`build_plugins` -> :func:`build_renderer` (unless ``renderer`` is given) -> :func:`build_module` ->
    ``init_from_scene(scene)`` (the seeded initial Gaussians and every plugin's state). ``renderer``: a renderer
    plugin, or a function of the config that makes one, in place of :func:`build_renderer`. ``init=False`` only
    attaches ``scene``, for a caller that loads the parameters itself. The renderer is ``module.renderer``."""
    strategy, blocks = build_plugins(cfg)
    if renderer is None or callable(renderer):
        renderer = (renderer or _config_renderer)(cfg)
    module = build_module(cfg, strategy, blocks, renderer)
    if init:
        module.init_from_scene(scene)
    else:
        module.scene = scene
    return module


def resolve_accelerator(requested: Optional[str], renderer) -> str:
    """Lightning's accelerator for ``trainer.accelerator``: ``auto`` follows the renderer's device."""
    want = renderer.device.type
    req = str(requested or "auto")
    if req == "auto":
        return want
    if {"gpu": "cuda"}.get(req, req) != want:
        raise B3dgsError(f"trainer.accelerator={req} does not match renderer={renderer.name}, which runs on {want} "
                         f"(fix: trainer.accelerator=auto, or pick a renderer for {req})")
    return req


#: keys of the ``trainer`` node that b3dgs reads itself (its callbacks and final outputs); every other key is an
#: argument of the node's ``_target_`` (``lightning.Trainer``)
RUN_KEYS = ("eval_every", "curve_max_views", "checkpoint_every", "checkpoint_every_s", "keep_checkpoints",
            "save_renders")
#: trainer keys of run dirs written before the trainer node was a ``lightning.Trainer`` target
_OLD_TRAINER_KEYS = {"progress_bar": "enable_progress_bar", "log_every": "log_every_n_steps"}


def build_callbacks(node) -> list:
    """The configured extra callbacks (``callbacks: {name: {_target_: ...}}``), in their listed order; they run
    after b3dgs's own callbacks (Lightning runs checkpoint callbacks, such as ``last.ckpt``'s, last of all)."""
    from hydra.utils import instantiate

    return [instantiate(n) for n in (node or {}).values() if n is not None]


def build_trainer(tcfg, renderer, callbacks: list, logger=False, **fixed):
    """The ``trainer`` node's ``_target_`` (``lightning.Trainer``) built with its own arguments, the accelerator
    resolved from the renderer (:func:`resolve_accelerator`), ``callbacks``, ``logger``, b3dgs's atomic checkpoint
    IO, and ``fixed`` (what a caller sets whatever the config says, e.g. a round's ``max_steps``). With the progress
    bar on, it is b3dgs's bar over global steps (:class:`b3dgs.callbacks.StepProgressBar`) unless ``callbacks`` has one."""
    from hydra.utils import instantiate
    from lightning.pytorch.callbacks import ProgressBar

    from b3dgs.callbacks import AtomicCheckpointIO, StepProgressBar

    keys = [str(k) for k in tcfg.keys() if k not in RUN_KEYS and _OLD_TRAINER_KEYS.get(k, k) not in fixed]
    # resolved one by one in place (interpolations may point anywhere in the config; fixed ones are never read)
    args = {_OLD_TRAINER_KEYS.get(k, k): tcfg[k] for k in keys}
    args = {k: OmegaConf.to_container(v, resolve=True) if OmegaConf.is_config(v) else v for k, v in args.items()}
    args.setdefault("_target_", "lightning.Trainer")
    args["accelerator"] = resolve_accelerator(args.get("accelerator"), renderer)
    args.update(fixed)
    if args.get("enable_progress_bar", True) and not any(isinstance(c, ProgressBar) for c in callbacks):
        callbacks = [*callbacks, StepProgressBar()]
    # objects go in through a partial (instantiate would turn them into configs: hydra#2591)
    return instantiate(args, _partial_=True)(callbacks=callbacks, logger=logger, plugins=[AtomicCheckpointIO()])


def save_config(cfg: DictConfig, path: Path) -> None:
    """The composed config (without Hydra's own node), resolved, ``data.path`` made absolute (``b3dgs-eval``
    works from any folder), written atomically."""
    from b3dgs.io import atomic_path

    c = cfg.copy()
    with open_dict(c):
        c.pop("hydra", None)
    plain = OmegaConf.to_container(c, resolve=True)
    data = plain.get("data")
    if isinstance(data, dict) and data.get("path"):
        data["path"] = str(Path(str(data["path"])).expanduser().resolve())
    with atomic_path(path) as tmp:
        tmp.write_text(OmegaConf.to_yaml(OmegaConf.create(plain)))


def resolve_resume(cfg: DictConfig, run_dir: Path) -> Optional[str]:
    resume = cfg.get("resume")
    if resume in (None, False, "null", ""):
        return None
    if resume in ("auto", True):
        last = run_dir / "checkpoints" / "last.ckpt"
        return str(last) if last.exists() else None
    p = Path(str(resume))
    if not p.exists():
        raise FileNotFoundError(f"resume={resume}: no such checkpoint; pass a .ckpt path, 'auto' or null")
    return str(p)


#: what marks a b3dgs run dir (one with a run manifest, :mod:`b3dgs.rundir`) as holding a run
RUN_MARKERS = ("config.yaml", "checkpoints/last.ckpt", "metrics.json")
#: what ``overwrite=true`` leaves of the replaced run: the new run rewrites Hydra's ``.hydra/`` and its job log
RUN_OUTPUTS_KEPT = (".hydra/*", "*.log")


def _remove_outputs(run_dir: Path, names=None) -> None:
    """Remove ``names`` (files of the run dir), or by default every file the previous run wrote: exactly what its
    manifest lists (:func:`b3dgs.rundir.remove_run_files`), never a file b3dgs did not write."""
    from b3dgs.rundir import remove_run_files

    if names is None:
        remove_run_files(run_dir, keep=RUN_OUTPUTS_KEPT)
        return
    for name in names:
        p = run_dir / name
        if p.is_file() or p.is_symlink():
            p.unlink()


def _foreign_dir_error(run_dir: Path):
    from b3dgs.errors import B3dgsError
    from b3dgs.rundir import foreign_files

    files = foreign_files(run_dir, limit=5)
    shown = ", ".join(files[:4]) + (" and more" if len(files) > 4 else "")
    return B3dgsError(f"{run_dir} is not empty and holds no b3dgs run ({shown})",
                      "pass hydra.run.dir=PATH to a new or empty folder; b3dgs writes only there or into its own run "
                      "dirs, and overwrite=true removes only files a b3dgs run wrote")


def prepare_run_dir(cfg: DictConfig, run_dir: Path) -> tuple[Optional[str], bool]:
    """``(checkpoint to resume from or None, whether to remove the old run's outputs first)``.

    A b3dgs run dir carries the run manifest ``.b3dgs-run.json`` (:mod:`b3dgs.rundir`). One that already holds a
    run (config.yaml, checkpoints/last.ckpt or metrics.json) is refused unless ``resume=auto`` (or ``resume=`` one
    of its own checkpoints) continues it or ``overwrite=true`` replaces it (removing only what its manifest lists).
    A non-empty folder without a manifest is someone else's: refused, naming its files, whatever the flags.
    Run dirs written before manifests (a b3dgs config.yaml with metrics.json or checkpoints/last.ckpt, e.g. the
    archived ``bench/results/runs/*``) count as runs: ``resume=auto`` continues them, ``overwrite=true`` removes
    only the outputs a manifest would list (:func:`b3dgs.rundir.run_files`), and the run's start writes their
    manifest. A resume with another renderer is refused (:func:`check_resume_renderer`). Nothing is removed
    here (the caller removes after every other check has passed).
    """
    from b3dgs.rundir import run_dir_kind

    overwrite = cfg.get("overwrite", False)
    if not isinstance(overwrite, bool):
        raise B3dgsError(f"overwrite={overwrite} is invalid: it must be true or false "
                         "(fix: pass overwrite=true to replace the run in the run dir, or leave it out)")
    resume = cfg.get("resume")
    resuming = resume not in (None, False, "null", "")
    if overwrite and resuming:
        raise B3dgsError(f"resume={resume} and overwrite=true contradict each other (fix: pass resume=auto to "
                         "continue the run in the run dir, or overwrite=true to replace it, not both)")
    kind = run_dir_kind(run_dir)
    if kind == "foreign":
        raise _foreign_dir_error(run_dir)
    held = [n for n in RUN_MARKERS if (run_dir / n).exists()]
    if overwrite:
        return None, kind != "empty"
    ckpt = resolve_resume(cfg, run_dir)
    if ckpt is not None:
        check_resume_renderer(cfg, ckpt)
    if not held:
        return ckpt, False
    if resume in ("auto", True):
        if finished_metrics(run_dir) is not None:
            return ckpt, False  # finished: the caller checks its identity, says so and rewrites nothing
        if ckpt is None and (run_dir / "metrics.json").exists():
            raise B3dgsError(f"{run_dir} holds a finished run but no checkpoints/last.ckpt to resume from "
                             "(fix: pass overwrite=true to train it again, or another hydra.run.dir)")
        return ckpt, False
    own = (run_dir / "checkpoints").resolve()
    if ckpt is not None and Path(ckpt).resolve().parent == own:
        return ckpt, False
    raise B3dgsError(f"{run_dir} already holds a run ({', '.join(held)}) (fix: pass resume=auto to continue it, "
                     "overwrite=true to replace it, or another hydra.run.dir)")


def check_resume_renderer(cfg: DictConfig, ckpt_path: str) -> None:
    """Refuse to resume with another renderer (backend, device or setting) than the checkpoint's run used: the
    identity of the renderer in the checkpoint, or (checkpoints written before it was recorded) the ``renderer``
    node of its run dir's config.yaml. A damaged checkpoint passes here (:func:`check_resume` names it)."""
    from b3dgs.checkpoint import renderer_identity, renderer_mismatch
    from b3dgs.errors import B3dgsError

    try:
        ck = torch.load(ckpt_path, map_location="cpu", weights_only=False, mmap=True)
        saved = ((ck.get("b3dgs") or {}).get("identity") or {}).get("renderer")
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
    """Refuse to resume a checkpoint of another model, posterior, strategy, scene, schedule or seed."""
    try:
        ck = torch.load(ckpt_path, map_location="cpu", weights_only=False, mmap=True)
    except Exception as e:  # noqa: BLE001 - damaged file: say which and how to go on
        raise B3dgsError(f"cannot read the checkpoint {ckpt_path} ({type(e).__name__}) (fix: pass resume=PATH to an "
                         "intact .ckpt, or overwrite=true to start afresh)") from None
    module.check_checkpoint_identity(
        ck, f"resume: the checkpoint {ckpt_path}",
        "start afresh with overwrite=true or another hydra.run.dir (a resume continues the same run exactly)")


def _checkpoint_every_s(tcfg) -> Optional[float]:
    v = tcfg.get("checkpoint_every_s")
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not v >= 0:
        raise B3dgsError(f"trainer.checkpoint_every_s={v} is invalid: it must be a number of seconds >= 0 or null "
                         "(fix: pass trainer.checkpoint_every_s=300, or 0 / null for step-based checkpoints only)")
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


def _device_count(v: Any) -> int:
    """How many devices ``trainer.devices`` asks for (-1: all of them, as Lightning reads it)."""
    if isinstance(v, (list, tuple)) or OmegaConf.is_list(v):
        return len(v)
    try:
        return int(str(v))
    except ValueError:
        return 1  # "auto": one device on the CPU


def check_devices(cfg: DictConfig) -> None:
    """Refuse ``trainer.devices`` > 1 (or -1) on the CPU: Lightning would start training processes that fight
    over the run dir."""
    from b3dgs.errors import B3dgsError

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


def _show_value(v: Any) -> str:
    if OmegaConf.is_config(v):
        v = OmegaConf.to_container(v)
    return "[" + ",".join(map(str, v)) + "]" if isinstance(v, (list, tuple)) else str(v)


def warn_disabled_options(module) -> None:
    """Warn where one setting silently turns off another (``strategy.max_gaussians`` below the initial count)."""
    cap = getattr(module.strategy, "max_gaussians", None)
    n = int(module.num_gaussians)
    if isinstance(cap, int) and not isinstance(cap, bool) and cap < n:
        log.warning("strategy.max_gaussians=%d is below the %d initial Gaussians: no Gaussian is ever added "
                    "(densification by clone and split is off; only pruning changes the count) (fix: raise "
                    "strategy.max_gaussians above %d, or lower model.init_max_points)", cap, n, n)


def _rmdir_if_empty(path: Path) -> None:
    try:
        path.rmdir()
    except OSError:
        pass


def finished_metrics(run_dir: Path) -> Optional[dict]:
    """The complete ``metrics.json`` of a finished run in ``run_dir``, else ``None``."""
    import json

    try:
        m = json.loads((run_dir / "metrics.json").read_text())
    except (OSError, ValueError):
        return None
    return m if isinstance(m, dict) and "checkpoint" in m else None


def train(cfg: DictConfig) -> dict:
    """Train one model into its run dir; returns the metrics dict.

    Run dir contract: the run dir's lock (:func:`b3dgs.rundir.run_dir_lock`) first; once every check has
    passed ``config.yaml``, ``.hydra/`` and the job log, ``checkpoints/last.ckpt`` (never ``last-v1.ckpt``)
    every ``trainer.checkpoint_every`` steps and ``trainer.checkpoint_every_s`` seconds and at the end,
    then the renders, ``point_cloud.ply`` and the curve files, and ``metrics.json`` last, as the "done"
    marker (it records the final checkpoint's step, Gaussian count and parameter digest). A finished run
    is never rewritten: ``resume=auto`` on it says so and returns its metrics (``overwrite=true`` trains it
    again). A resume (``resume=auto``) is exact: it continues bit for bit as the uninterrupted run would
    (RNGs, view sampler, guard counters and plugin states are in the checkpoint), also when the kill came
    after the last checkpoint (then only the final evaluation runs), and is refused for another model,
    posterior, strategy, scene, ``trainer.max_steps`` or seed. SIGINT / SIGTERM save a checkpoint and raise
    :class:`b3dgs.rundir.Interrupted`.
    """
    from b3dgs.rundir import interrupt_handlers, run_dir_lock
    from b3dgs.validation import validate_config

    run_dir = Path(cfg.trainer.default_root_dir)
    try:
        validate_config(cfg, app="train")
        check_devices(cfg)
        warn_slow_renderer(cfg)
    except Exception:
        _rmdir_if_empty(run_dir)  # Hydra made it; a refused run leaves nothing
        raise
    with interrupt_handlers(), run_dir_lock(run_dir):
        return _train_locked(cfg, run_dir)


def _train_locked(cfg: DictConfig, run_dir: Path) -> dict:
    import lightning as L
    from lightning.pytorch.loggers import TensorBoardLogger  # noqa: F401 - logger=tensorboard targets it

    from b3dgs.callbacks import CurveCallback, ResumeState, RunCheckpoint, RunFiles
    from b3dgs.numerics import reset_guards
    from b3dgs.rundir import Interrupted, arm_run_log, remove_stale_staging, remove_stale_tmp, write_hydra_files

    tcfg = cfg.trainer
    every_s = _checkpoint_every_s(tcfg)
    ckpt_path, clear = prepare_run_dir(cfg, run_dir)
    seed = int(cfg.seed)
    # reset the global seed in every job: PL_GLOBAL_SEED survives between multirun jobs
    os.environ.pop("PL_GLOBAL_SEED", None)
    L.seed_everything(seed, workers=True, verbose=False)
    reset_guards()
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))

    from hydra.utils import instantiate

    dm = instantiate(cfg.data)
    dm.setup("fit")
    scene = dm.scene
    module = build_run(cfg, scene)
    renderer = module.renderer
    warn_disabled_options(module)
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
    logger = instantiate(cfg.logger, save_dir=str(run_dir)) if cfg.get("logger") else False
    trainer = build_trainer(tcfg, renderer, [curve, ResumeState(), ckpt, RunFiles(run_dir),
                                             *build_callbacks(cfg.get("callbacks"))],
                            logger=logger, default_root_dir=str(run_dir))
    # every check has passed: only now is the run dir changed
    arm_run_log(fresh=clear)
    if clear:
        log.warning("overwrite=true: removing the previous run's outputs from %s", run_dir)
        _remove_outputs(run_dir)
    else:
        _remove_outputs(run_dir, ("metrics.json",))  # a damaged done marker comes back when this run finishes
    for p in remove_stale_tmp(run_dir):
        log.info("removed %s, a temp file left by an interrupted run", p.relative_to(run_dir))
    for p in remove_stale_staging(run_dir, owned=clear):
        log.info("removed %s, the staging folder of an interrupted b3dgs-eval", p.name)
    write_hydra_files(run_dir, cfg)
    save_config(cfg, run_dir / "config.yaml")
    log.info("Scene %s: %d train / %d test views, %d initial Gaussians, extent %.3f; renderer %s on %s",
             scene.name, len(scene.train), len(scene.test), module.num_gaussians, scene.extent, renderer.name,
             renderer.device)

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*does not have many workers.*")
        warnings.filterwarnings("ignore", message=".*`training_step` returns.*")
        try:
            # our own checkpoints hold plugin states and config values, not only tensors
            fit_on_renderer_device(trainer, module, datamodule=dm, ckpt_path=ckpt_path, weights_only=False)
        except Interrupted as e:  # a signal outside the steps (e.g. once training is done): the step it is at
            if e.step is None and trainer.global_step:
                e.step = int(trainer.global_step)
            raise
    try:
        return _finish(cfg, run_dir, module, scene, renderer, trainer, curve, ckpt)
    except Interrupted as e:
        e.step = int(trainer.global_step)
        raise


def _finish(cfg: DictConfig, run_dir: Path, module, scene, renderer, trainer, curve, ckpt) -> dict:
    """The final evaluation and outputs of a trained model (also all a resume from the final checkpoint does)."""
    from b3dgs.checkpoint import checkpoint_record
    from b3dgs.metrics.lpips import get_lpips
    from b3dgs.metrics.views import evaluate_views
    from b3dgs.numerics import guard_counts
    from b3dgs.rundir import record_written
    tcfg, seed = cfg.trainer, int(cfg.seed)
    # ------------------------------------------------------------ final evaluation and outputs
    # written in this order, each atomically: renders, PLY, curve, then metrics.json (the done marker)
    final = checkpoint_record(torch.load(ckpt.last_path, map_location="cpu", weights_only=False, mmap=True))
    t_pass = time.perf_counter()
    passed = module.prepare_posterior(scene.train)  # counts from a view pass (posterior.niw.count other than paper)
    posterior_pass_s = time.perf_counter() - t_pass if passed else 0.0
    lpips_model, lpips_reason = get_lpips(cfg.get("lpips_weights"))
    if tcfg.get("save_renders", True):  # listed in the run manifest before they are written
        record_written(run_dir, [f"renders/{Path(c.name).stem}.png" for c in scene.test])
    ev = evaluate_views(module, scene.test, lpips_model=lpips_model,
                        render_dir=run_dir / "renders" if tcfg.get("save_renders", True) else None)
    from b3dgs.data.scene import scene_transform
    from b3dgs.ply import frame_comments, write_splats

    frame = scene_transform(scene)  # point_cloud.ply in the scene's own (COLMAP / transforms.json) frame
    write_splats(run_dir / "point_cloud.ply", {k: v.data for k, v in module.splats.items()}, frame.inverse(),
                 extra=module.export_extras(), comments=frame_comments(frame))
    curve.write()
    metrics = {
        "method": method_label(cfg), "scene": scene.name, "seed": seed, "steps": int(trainer.global_step),
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
        "per_view": ev["per_view"],
    }
    write_json(run_dir / "metrics.json", metrics)
    def fmt(v, digits):
        return "n/a" if v is None else f"{v:.{digits}f}"

    log.info("Done: PSNR %s dB, SSIM %s, LPIPS %s, %d Gaussians, %.1f s training -> %s", fmt(metrics["psnr"], 3),
             fmt(metrics["ssim"], 4), fmt(metrics["lpips"], 4), metrics["num_gaussians"], metrics["train_time_s"], run_dir)
    return metrics


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="train")
def hydra_main(cfg: DictConfig) -> Optional[float]:
    from b3dgs.errors import known_errors, quiet_known_noise

    from b3dgs.rundir import Interrupted

    with known_errors("b3dgs-train", cfg):
        quiet_known_noise()
        try:
            metrics = train(cfg)
        except Interrupted as e:
            at = "before training started" if e.step is None else f"at step {e.step}"
            sys.stderr.write(f"b3dgs-train: {e} {at}; resume with resume=auto\n")
            sys.stderr.flush()
            sys.exit(e.exit_code)
    return metrics.get("psnr")


def main() -> None:
    """``b3dgs-train``: one-line errors with exit code 2 (see :mod:`b3dgs.errors`)."""
    from b3dgs.errors import run_cli

    run_cli("b3dgs-train", hydra_main, config="train")


if __name__ == "__main__":
    # through the importable module, so that the joblib launcher can pickle the task (not __main__'s copy)
    from b3dgs.train import main as _main

    _main()
