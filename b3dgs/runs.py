"""Load a finished run dir (config.yaml + checkpoints/last.ckpt) back into a SplatModule."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from omegaconf import DictConfig, OmegaConf

from b3dgs.errors import B3dgsError
from b3dgs.lifecycle import build_renderer, build_run, data_module, load_checkpoint, read_checkpoint
from b3dgs.rundir import not_a_run_dir
from b3dgs.types import Scene

log = logging.getLogger(__name__)


def _run_renderer(cfg: DictConfig):
    """The run's own renderer when it runs on this machine, else ``renderer=auto`` (said in the log)."""
    from b3dgs.render.renderers import RendererUnavailable, auto_renderer

    try:
        return build_renderer(cfg.get("renderer"))
    except RendererUnavailable as e:
        log.warning("%s; scoring with renderer=auto instead", e)
        return auto_renderer()


@dataclass
class LoadedRun:
    path: Path
    cfg: DictConfig
    module: "object"  # SplatModule
    scene: Scene
    metrics: Optional[dict]


def load_run(run_dir: str | Path, scene: Optional[Scene] = None, checkpoint: Optional[str | Path] = None,
             renderer=None, data_path: Optional[str | Path] = None) -> LoadedRun:
    """Rebuild the model of ``run_dir`` from its config and last checkpoint.

    ``scene`` may be passed to share one loaded scene between several runs (ensembles). ``renderer``
    (a renderer plugin) overrides the run's own, e.g. to score a CPU-trained run with gsplat; the module
    is moved to the renderer's device. ``data_path`` is the run's scene folder on this machine where it is not the
    recorded one (:func:`locate_scene`).
    """
    import json

    from b3dgs.upgrade import upgrade_targets

    run_dir = Path(run_dir)
    cfg_path = run_dir / "config.yaml"
    if not cfg_path.exists():
        raise not_a_run_dir(run_dir)
    ckpt_path = Path(checkpoint) if checkpoint else run_dir / "checkpoints" / "last.ckpt"
    if not ckpt_path.exists():
        raise B3dgsError(f"no checkpoint at {ckpt_path}; the run may not have finished",
                         f"finish it with `b3dgs-train ... hydra.run.dir={run_dir} resume=auto`")
    try:
        cfg = OmegaConf.create(upgrade_targets(OmegaConf.to_container(OmegaConf.load(cfg_path), resolve=False)))
        bad = None if isinstance(cfg, DictConfig) and "data" in cfg and "model" in cfg else "no data / model node"
    except Exception as e:  # noqa: BLE001 - damaged or foreign file: say which and how to go on
        bad = " ".join(str(e).split())[:120]
    if bad is not None:
        raise B3dgsError(f"{cfg_path} is damaged or not a b3dgs run config ({bad})",
                         f"train the run again with `b3dgs-train ... hydra.run.dir={run_dir} overwrite=true`")
    metrics = None
    if (run_dir / "metrics.json").exists():
        try:
            metrics = json.loads((run_dir / "metrics.json").read_text())
        except ValueError as e:
            raise B3dgsError(f"{run_dir / 'metrics.json'} is damaged ({e})",
                             f"finish the run again with `b3dgs-train ... hydra.run.dir={run_dir} resume=auto`") from None
    moved = locate_scene(cfg, cfg_path, data_path) if scene is None else None
    if scene is None:
        scene = data_module(cfg.data).scene
    if moved is not None:
        check_same_scene(run_dir, scene, moved, metrics)
    module = build_run(cfg, scene, renderer=renderer if renderer is not None else _run_renderer, init=False)
    try:
        ck = read_checkpoint(ckpt_path)
    except Exception as e:  # noqa: BLE001 - corrupt or truncated file
        raise B3dgsError(f"cannot read the checkpoint {ckpt_path} ({' '.join(str(e).split())[:120]})",
                         f"pass another checkpoint, or train the run again with `b3dgs-train ... "
                         f"hydra.run.dir={run_dir} overwrite=true`") from e
    if checkpoint is None:  # the run's own last.ckpt must be the model its metrics.json describes
        check_run_checkpoint(run_dir, ck, metrics)
    # the commands that load a run take no training options: the fix names none (no model=, seed=)
    module.check_checkpoint_identity(
        ck, f"{ckpt_path}", f"pass checkpoint= one of {run_dir}/checkpoints/*.ckpt, or run= the run dir that "
        f"checkpoint came from" if checkpoint else f"keep each run dir's config.yaml and checkpoints from one "
        f"b3dgs-train run (train it again with `b3dgs-train ... hydra.run.dir={run_dir} overwrite=true`)",
        suggest=False)
    return LoadedRun(run_dir, cfg, load_checkpoint(module, ck), scene, metrics)


def locate_scene(cfg: DictConfig, cfg_path: Path, data_path: Optional[str | Path] = None) -> Optional[str]:
    """Point ``cfg.data.path`` at the run's scene folder on this machine: ``data_path`` where given (``data.path=DIR``
    of the command reading the run); else the recorded folder where it exists; else, for a run dir read on another
    machine, the folder of the same name under this machine's data root (:func:`b3dgs.data_root`), said in the log.
    Returns the folder read where it is not the recorded one (to be checked by :func:`check_same_scene`)."""
    from b3dgs import data_root_and_origin

    recorded = cfg.data.get("path")
    if data_path is not None:
        here = Path(str(data_path)).expanduser().resolve()
        if not here.exists():
            raise B3dgsError(f"data.path={data_path} does not exist", "pass data.path=DIR, the folder of the scene the "
                             "run was trained on as it lies on this machine")
        cfg.data.path = str(here)
        return None if str(here) == str(recorded) else str(here)
    if not recorded or Path(str(recorded)).exists():
        return None
    if not Path(str(recorded)).is_absolute():  # runs trained before data.path was stored absolute
        raise B3dgsError(f"{cfg_path} has data.path={recorded}, relative to the folder the run was trained in, and "
                         f"it is not below {Path.cwd()}",
                         "run from that folder, or pass data.path=DIR, the scene's folder")
    root, origin = data_root_and_origin()
    rec = Path(str(recorded))
    here = Path(root) / rec.parent.name / rec.name if rec.suffix.lower() == ".json" else Path(root) / rec.name
    if not here.exists():
        raise B3dgsError(f"the run's scene folder {recorded} is not on this machine, nor is {here} (its name under "
                         f"the data root, {origin})", "pass data.path=DIR, the scene's folder on this machine")
    log.warning("the run's scene folder %s is not on this machine: reading %s (its name under the data root, %s)",
                recorded, here, origin)
    cfg.data.path = str(here)
    return str(here)


def check_same_scene(run_dir: Path, scene: Scene, folder: str, m: Optional[dict]) -> None:
    """Refuse a scene read from another folder than the run's (:func:`locate_scene`) whose normalisation or view
    counts differ from what the run's ``metrics.json`` (``m``) recorded: it is not the scene the run was trained on."""
    import numpy as np

    from b3dgs.data.scene import SceneTransform, scene_transform

    if m is None:
        return  # an unfinished run: load_run refuses it with its own reason
    want = None if m.get("scene_transform") is None else SceneTransform.from_dict(m["scene_transform"])
    have = scene_transform(scene)
    same = want is None or (np.allclose(have.scale, want.scale, rtol=1e-6)
                            and np.allclose(have.translation, want.translation, atol=1e-6))
    same = same and all(m.get(k) in (None, n) for k, n in (("num_train_views", len(scene.train)),
                                                             ("num_test_views", len(scene.test))))
    if not same:
        raise B3dgsError(f"{folder} is not the scene {run_dir} was trained on: its cameras or views differ from the "
                         "run's metrics.json", "pass data.path=DIR, the folder of the scene the run was trained on")


def check_run_checkpoint(run_dir: Path, ck: dict, metrics: Optional[dict]) -> None:
    """Refuse a run dir whose ``checkpoints/last.ckpt`` is not the model its ``metrics.json`` describes
    (global step, Gaussian count and, where recorded, the parameter digest), or that has no
    ``metrics.json`` (an unfinished run: ``metrics.json`` is written last)."""
    from b3dgs.checkpoint import checkpoint_record

    ckpt_path = run_dir / "checkpoints" / "last.ckpt"
    if metrics is None:
        raise B3dgsError(f"{run_dir} holds an unfinished run: no metrics.json",
                         f"finish it with `b3dgs-train ... hydra.run.dir={run_dir} resume=auto`, or pass its "
                         "checkpoint explicitly")
    have = checkpoint_record(ck)
    want = metrics.get("checkpoint") or {"global_step": metrics.get("steps"), "num_gaussians": metrics.get("num_gaussians")}
    for key in ("global_step", "num_gaussians", "params_sha256"):
        if want.get(key) is not None and want[key] != have[key]:
            raise B3dgsError(f"{ckpt_path} is not the model of {run_dir / 'metrics.json'}: {key} {have[key]} in the "
                             f"checkpoint, {want[key]} in metrics.json",
                             f"train the run again with `b3dgs-train ... hydra.run.dir={run_dir} overwrite=true`, or "
                             "remove the stray checkpoint")
