"""``b3dgs-train``: the Hydra app that trains one model and writes its run dir.

``train(cfg)`` does the work and returns the metrics dict; ``main()`` is the console entry point: known
errors print ``b3dgs-train: error: <problem> (fix: <what to do>)`` and exit with code 2 (full traceback
with ``HYDRA_FULL_ERROR=1`` or ``b3dgs.debug=true``).
"""
from __future__ import annotations

import logging
import os
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

CONF_DIR = str(Path(__file__).resolve().parent.parent / "conf")


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

    return instantiate(cfg.model, _partial_=True)(
        strategy=strategy, posterior=blocks, renderer=renderer if renderer is not None else build_renderer(cfg.get("renderer")),
        max_steps=int(cfg.trainer.max_steps), seed=int(cfg.seed),
    )


def resolve_accelerator(requested: Optional[str], renderer) -> str:
    """Lightning's accelerator for ``trainer.accelerator``: ``auto`` follows the renderer's device."""
    want = renderer.device.type
    req = str(requested or "auto")
    if req == "auto":
        return want
    if {"gpu": "cuda"}.get(req, req) != want:
        raise ValueError(f"trainer.accelerator={req} does not match renderer={renderer.name}, which runs on {want} "
                         f"(fix: trainer.accelerator=auto, or pick a renderer for {req})")
    return req


def save_config(cfg: DictConfig, path: Path) -> None:
    """The composed config (without Hydra's own node), resolved, written atomically."""
    from b3dgs.io import atomic_path

    c = cfg.copy()
    with open_dict(c):
        c.pop("hydra", None)
    plain = OmegaConf.to_container(c, resolve=True)
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


def train(cfg: DictConfig) -> dict:
    import lightning as L
    from lightning.pytorch.callbacks import ModelCheckpoint
    from lightning.pytorch.loggers import TensorBoardLogger

    from b3dgs.callbacks import AtomicCheckpointIO, CurveCallback
    from b3dgs.evaluate import evaluate_views
    from b3dgs.metrics.lpips import get_lpips
    from b3dgs.posterior.guards import guard_counts, reset_guards
    from b3dgs.validation import validate_config

    validate_config(cfg, app="train")
    run_dir = Path(cfg.trainer.default_root_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    save_config(cfg, run_dir / "config.yaml")
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
    strategy, blocks = build_plugins(cfg)
    renderer = build_renderer(cfg.get("renderer"))
    module = build_module(cfg, strategy, blocks, renderer)
    module.init_from_scene(scene)
    accelerator = resolve_accelerator(cfg.trainer.get("accelerator"), renderer)
    log.info("Scene %s: %d train / %d test views, %d initial Gaussians, extent %.3f; renderer %s on %s",
             scene.name, len(scene.train), len(scene.test), module.num_gaussians, scene.extent, renderer.name,
             renderer.device)

    tcfg = cfg.trainer
    curve = CurveCallback(scene.test, eval_every=int(tcfg.eval_every), out_dir=run_dir,
                          max_eval_views=tcfg.get("curve_max_views"))
    ckpt = ModelCheckpoint(dirpath=run_dir / "checkpoints", filename="step{step}", auto_insert_metric_name=False,
                           every_n_train_steps=int(tcfg.checkpoint_every), save_last=True, save_top_k=0 if not tcfg.get("keep_checkpoints") else -1)
    logger = instantiate(cfg.logger, save_dir=str(run_dir)) if cfg.get("logger") else False
    trainer = L.Trainer(
        max_steps=int(tcfg.max_steps), accelerator=accelerator, devices=1, logger=logger,
        callbacks=[curve, ckpt], default_root_dir=str(run_dir), limit_val_batches=0, num_sanity_val_steps=0,
        enable_progress_bar=bool(tcfg.progress_bar), log_every_n_steps=int(tcfg.log_every),
        plugins=[AtomicCheckpointIO()], enable_model_summary=False, deterministic=False,
    )
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*does not have many workers.*")
        warnings.filterwarnings("ignore", message=".*`training_step` returns.*")
        # our own checkpoints hold plugin states and config values, not only tensors
        trainer.fit(module, datamodule=dm, ckpt_path=resolve_resume(cfg, run_dir), weights_only=False)

    # ------------------------------------------------------------ final evaluation and outputs
    lpips_model, lpips_reason = get_lpips()
    ev = evaluate_views(module, scene.test, lpips_model=lpips_model,
                        render_dir=run_dir / "renders" if tcfg.get("save_renders", True) else None)
    metrics = {
        "method": cfg.model.get("name", "custom"), "scene": scene.name, "seed": seed, "steps": int(trainer.global_step),
        "psnr": ev.get("psnr"), "ssim": ev.get("ssim"), "lpips": ev.get("lpips"),
        "lpips_reason": None if lpips_model is not None else lpips_reason,
        "num_gaussians": module.num_gaussians, "train_time_s": round(curve.train_time_s, 3),
        "render_fps": ev["render_fps"], "renderer": renderer.describe(),
        "num_train_views": len(scene.train), "num_test_views": len(scene.test),
        "removed": dict(module.ops.removed) if module.ops else {},
        "added": dict(module.ops.added) if module.ops else {},
        "block_time_s": {k: round(v, 4) for k, v in module.block_time_s.items()},
        "posterior": {name: blk.summary(state=module.states[name]) for name, blk in module.posterior.items()},
        "numerical_guards": guard_counts(),  # how often each clamp / jitter / floor fired (never silent)
        "per_view": ev["per_view"],
    }
    write_json(run_dir / "metrics.json", metrics)
    from b3dgs.ply import write_ply

    sp = module.splats
    write_ply(run_dir / "point_cloud.ply", sp["means"].data, sp["scales"].data, sp["quats"].data, sp["opacities"].data,
              sp["sh0"].data[:, 0], sp["shN"].data, extra=module.export_extras())
    curve.write()
    log.info("Done: PSNR %s dB, SSIM %s, LPIPS %s, %d Gaussians, %.1f s training -> %s",
             "n/a" if metrics["psnr"] is None else f"{metrics['psnr']:.3f}", metrics["ssim"], metrics["lpips"], metrics["num_gaussians"], metrics["train_time_s"], run_dir)
    return metrics


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="train")
def hydra_main(cfg: DictConfig) -> Optional[float]:
    from b3dgs.errors import known_errors, quiet_known_noise

    with known_errors("b3dgs-train", cfg):
        quiet_known_noise()
        metrics = train(cfg)
    return metrics.get("psnr")


def main() -> None:
    """``b3dgs-train``: one-line errors with exit code 2 (see :mod:`b3dgs.errors`)."""
    from b3dgs.errors import run_cli

    run_cli("b3dgs-train", hydra_main)


if __name__ == "__main__":
    main()
