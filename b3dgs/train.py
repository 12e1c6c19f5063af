"""``b3dgs-train``: the Hydra app that trains one model and writes its run dir.

``train(cfg)`` does the work and returns the metrics dict; ``main()`` is the console entry point: known
errors print ``b3dgs-train: error: <problem> (fix: <what to do>)`` and exit with code 2 (full traceback
with ``HYDRA_FULL_ERROR=1`` or ``b3dgs.debug=true``).
"""
from __future__ import annotations

import logging
import sys
import time
from pathlib import Path
from typing import Optional

import hydra
from omegaconf import DictConfig

from b3dgs import conf_dir
from b3dgs.io import write_json
from b3dgs.labels import method_label, register_resolver

log = logging.getLogger(__name__)

CONF_DIR = conf_dir()
register_resolver()  # ${b3dgs.method:} in run dir names (conf/hydra/default.yaml)


def train(cfg: DictConfig) -> dict:
    """Train one model into its run dir; returns the metrics dict.

    Run dir contract: the run dir's lock (:func:`b3dgs.rundir.run_dir_lock`) first; once every check has
    passed the run manifest, then the job log, ``.hydra/`` and ``config.yaml`` (:func:`b3dgs.rundir.claim_run_dir`),
    ``checkpoints/last.ckpt`` (never ``last-v1.ckpt``)
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
    from b3dgs.lifecycle import check_devices, warn_slow_renderer
    from b3dgs.rundir import interrupt_handlers, run_dir_lock
    from b3dgs.validation import validate_config

    run_dir = Path(cfg.trainer.default_root_dir)
    try:
        validate_config(cfg, app="train")
        check_devices(cfg)
        warn_slow_renderer(cfg)
    except Exception:
        try:
            run_dir.rmdir()  # Hydra made it; a refused run leaves nothing
        except OSError:
            pass
        raise
    with interrupt_handlers(), run_dir_lock(run_dir):
        return _train_locked(cfg, run_dir)


def _train_locked(cfg: DictConfig, run_dir: Path) -> dict:
    from hydra.utils import instantiate
    from lightning.pytorch.loggers import TensorBoardLogger  # noqa: F401 - logger=tensorboard targets it

    from b3dgs.callbacks import CurveCallback, ResumeState, RunCheckpoint, RunFiles
    from b3dgs.lifecycle import (build_callbacks, build_trainer, check_resume, check_resume_renderer,
                                 checkpoint_every_s, fit, start_run, warn_settings)
    from b3dgs.rundir import Interrupted, claim_run_dir, finished_metrics, prepare_run_dir

    tcfg = cfg.trainer
    every_s = checkpoint_every_s(tcfg)
    ckpt_path, clear = prepare_run_dir(run_dir, cfg.get("resume"), cfg.get("overwrite", False),
                                       check_checkpoint=lambda path: check_resume_renderer(cfg, path))
    dm, module = start_run(cfg)
    scene, renderer = dm.scene, module.renderer
    warn_settings(module, scene, int(tcfg.max_steps))
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
                            logger=logger, default_root_dir=str(run_dir), final_after_eval=True)
    claim_run_dir(run_dir, cfg, clear)  # every check has passed: only now is the run dir changed, manifest first
    log.info("Scene %s: %d train / %d test views, %d initial Gaussians, extent %.3f; renderer %s on %s",
             scene.name, len(scene.train), len(scene.test), module.num_gaussians, scene.extent, renderer.name,
             renderer.device)
    try:
        fit(trainer, module, dm, ckpt_path)
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
    from b3dgs.callbacks import StepProgressBar
    from b3dgs.checkpoint import checkpoint_record
    from b3dgs.data.scene import scene_transform
    from b3dgs.lifecycle import read_checkpoint
    from b3dgs.metrics.lpips import get_lpips
    from b3dgs.metrics.views import evaluate_views
    from b3dgs.numerics import guard_counts
    from b3dgs.ply import frame_comments, write_splats
    from b3dgs.rundir import record_written

    tcfg, seed = cfg.trainer, int(cfg.seed)
    # written in this order, each atomically: renders, PLY, curve, then metrics.json (the done marker)
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
    if isinstance(trainer.progress_bar_callback, StepProgressBar):
        trainer.progress_bar_callback.show_final(metrics)

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

    from b3dgs.data.scene import infer_data_override

    run_cli("b3dgs-train", hydra_main, config="train", prepare_argv=infer_data_override)


if __name__ == "__main__":
    # through the importable module, so that the joblib launcher can pickle the task (not __main__'s copy)
    from b3dgs.train import main as _main

    _main()
