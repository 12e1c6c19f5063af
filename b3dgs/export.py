"""``b3dgs-export``: a trained run's Gaussians in the formats other tools open, from any of its checkpoints.

    b3dgs-export run=outputs/train/RUN format=ply                 # RUN/export/point_cloud.ply (3DGS layout + posterior)
    b3dgs-export run=RUN format=splat                              # RUN/export/scene.splat (web viewers)
    b3dgs-export run=RUN format=3dgs out=/data/model               # the official 3DGS model folder (SIBR viewer)
    b3dgs-export run=RUN format=ply checkpoint=RUN/checkpoints/step1000.ckpt

Every format is in the scene's own frame (COLMAP / transforms.json), as ``point_cloud.ply`` of a run:
- ``ply``: the 3DGS property layout (x y z, normals, f_dc_*, f_rest_*, opacity logit, log-scales, rot) plus the
  posterior blocks' per-Gaussian summaries as extra properties, in the training frame's units (stated in the header);
- ``splat``: the compact 32-byte-per-Gaussian format of the antimatter15 WebGL viewer (and viewers that read it):
  position and linear scale as float32, RGBA and the unit quaternion as uint8, sorted by size × opacity, largest first;
  only the DC colour (view-dependent colour does not fit the format);
- ``3dgs``: ``point_cloud/iteration_<step>/point_cloud.ply`` (the layout alone, no extra properties: SIBR reads a fixed
  record), ``cameras.json`` (every train and test camera: centre, camera-to-world rotation, fx, fy, size) and
  ``cfg_args``, the folder the official scripts and the SIBR viewer read; written whole in a staging folder and renamed
  into place (:func:`write_model_folder`).

It writes only what is its own (:func:`b3dgs.rundir.check_replace`): an existing file that no run's manifest lists is
refused unless ``overwrite=true``, a model folder goes only where none is or over an earlier export, and nothing goes
into a run's ``checkpoints/``.
"""
from __future__ import annotations

import logging
import os
import re
import shutil
import tempfile
from contextlib import nullcontext
from pathlib import Path
from typing import Optional

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from b3dgs.errors import B3dgsError, cli_main, did_you_mean, known_errors
from b3dgs.io import atomic_path, write_json
from b3dgs.ply import frame_comments, transform_gaussians, write_splats
from b3dgs.rundir import (LOCK_NAME, MANIFEST_NAME, _iter_files, _write_manifest, check_replace, manifest_lock,
                          owning_run_dir, read_manifest, record_written, refuse_in_checkpoints, run_files)
from b3dgs.train import CONF_DIR

log = logging.getLogger(__name__)
FORMATS = ("ply", "splat", "3dgs")
SH_C0 = 0.28209479177387814


def _own_frame(run) -> tuple[dict, object, object]:
    """(splats on the CPU, the scene's transform, its inverse)."""
    from b3dgs.data.scene import scene_transform

    frame = scene_transform(run.scene)
    splats = {k: v.detach().float().cpu() for k, v in run.module.splats.items()}
    return splats, frame, frame.inverse()


def export_ply(run, path: Path, extras: bool = True) -> Path:
    """The run's Gaussians as a 3DGS-layout PLY in the scene's frame (with the posterior summaries when ``extras``)."""
    splats, frame, inv = _own_frame(run)
    extra = {k: v.detach().cpu() for k, v in run.module.export_extras().items()} if extras else None
    return write_splats(path, splats, inv, extra=extra or None, comments=frame_comments(frame))


def splat_records(splats: dict, inv) -> np.ndarray:
    """(N, 32) uint8: per Gaussian, position (3 float32), linear scale (3 float32), RGBA (4 uint8), rotation (4 uint8,
    (q / |q|) · 128 + 128), in ``inv``'s frame, sorted by exp(Σ log-scale) · opacity, largest first (ties by index)."""
    means, log_scales, quats = transform_gaussians(splats["means"], splats["scales"], splats["quats"],
                                                   float(inv.scale), np.asarray(inv.rotation), inv.translation)
    means, log_scales, quats = means.double(), log_scales.double(), quats.double()
    alpha = torch.sigmoid(splats["opacities"].double().reshape(-1))
    importance = torch.exp(log_scales.sum(-1)) * alpha
    order = torch.from_numpy(np.lexsort((np.arange(len(importance)), -importance.numpy())))
    rgb = (0.5 + SH_C0 * splats["sh0"].double().reshape(-1, 3)).clamp(0, 1)
    q = torch.nn.functional.normalize(quats, dim=-1)
    n = means.shape[0]
    rec = np.zeros((n, 32), dtype=np.uint8)
    rec[:, 0:12] = means.float().numpy().view(np.uint8).reshape(n, 12)
    rec[:, 12:24] = torch.exp(log_scales).float().numpy().view(np.uint8).reshape(n, 12)
    rec[:, 24:27] = (rgb * 255).round().clamp(0, 255).to(torch.uint8).numpy()
    rec[:, 27] = (alpha * 255).round().clamp(0, 255).to(torch.uint8).numpy()
    rec[:, 28:32] = (q * 128 + 128).round().clamp(0, 255).to(torch.uint8).numpy()
    return rec[order.numpy()]


def export_splat(run, path: Path) -> Path:
    splats, _, inv = _own_frame(run)
    with atomic_path(path) as tmp:
        tmp.write_bytes(splat_records(splats, inv).tobytes())
    return path


def camera_entries(cameras, inv) -> list[dict]:
    """The official 3DGS ``cameras.json`` entries of ``cameras`` in ``inv``'s frame: centre and camera-to-world
    rotation (OpenCV axes), fx, fy in pixels at the cameras' size."""
    R = np.asarray(inv.rotation, np.float64)
    out = []
    for i, c in enumerate(cameras):
        vm = c.viewmat.double().cpu().numpy()
        c2w_rot = R @ vm[:3, :3].T  # a rotation of the world frame turns the camera's axes with it
        centre = inv.scale * R @ (-vm[:3, :3].T @ vm[:3, 3]) + np.asarray(inv.translation, np.float64)
        K = c.K.double().cpu().numpy()
        out.append({"id": i, "img_name": Path(c.name).stem, "width": int(c.width), "height": int(c.height),
                    "position": centre.tolist(), "rotation": c2w_rot.tolist(), "fy": float(K[1, 1]),
                    "fx": float(K[0, 0])})
    return out


def export_3dgs(run, folder: Path, step: int, model_path: Optional[Path] = None) -> Path:
    """The official 3DGS model folder of ``run`` at ``step`` in ``folder`` (``cfg_args`` names ``model_path``, default
    ``folder``: the folder it will have once staged into place)."""
    _, _, inv = _own_frame(run)
    export_ply(run, folder / "point_cloud" / f"iteration_{step}" / "point_cloud.ply", extras=False)
    cams = list(run.scene.train) + list(run.scene.test)
    write_json(folder / "cameras.json", camera_entries(cams, inv))
    bg = [float(v) for v in run.cfg.model.get("background", (0.0, 0.0, 0.0))]
    args = (f"Namespace(data_device='cuda', eval={bool(run.scene.test)}, images='images', "
            f"model_path={str(model_path or folder)!r}, resolution=-1, sh_degree={int(run.cfg.model.get('sh_degree', 3))}, "
            f"source_path={str(run.cfg.data.get('path') or '')!r}, white_background={bg == [1.0, 1.0, 1.0]})")
    with atomic_path(folder / "cfg_args") as tmp:
        tmp.write_text(args)
    return folder


#: the files of a model folder (``format=3dgs``) besides ``point_cloud/iteration_<step>/point_cloud.ply``
MODEL_FILES = ("cameras.json", "cfg_args", ".b3dgs-run.json")
_MODEL_PLY = re.compile(r"point_cloud/iteration_\d+/point_cloud\.ply")


def _not_ours(folder: Path) -> list[str]:
    """The files of ``folder`` that are not part of a model folder b3dgs-export wrote: those its own manifest does not
    list (a folder exported before it carried one: unless it has the layout alone, in a run dir whose manifest lists
    every file); every file for a folder without such a manifest."""
    files = [f for f in _iter_files(folder) if f != LOCK_NAME]
    try:
        m = read_manifest(folder)
    except B3dgsError:
        return files
    if m is not None:
        listed = set(m.get("files", [])) | {MANIFEST_NAME}
        return [f for f in files if f not in listed] if m.get("writer") == "b3dgs-export" else files
    owner = owning_run_dir(folder)
    if owner is None or not all(f in MODEL_FILES or _MODEL_PLY.fullmatch(f) for f in files):
        return files
    pre = Path(folder).resolve().relative_to(owner).as_posix()
    return [] if {f"{pre}/{f}" for f in files} <= set(run_files(owner)) else files


def _check_folder(out: Path) -> Optional[Path]:
    """Whether a model folder may be written at ``out`` (new, empty, or one b3dgs-export wrote: replaced whole); the run
    dir whose manifest lists it, or ``None``. A folder that holds anything else (a user's model, its other iterations)
    is refused: a model folder is never merged into one."""
    refuse_in_checkpoints(out, "b3dgs-export")
    files = _not_ours(out) if out.is_dir() else []
    if files:
        raise B3dgsError(f"out={out} holds files b3dgs-export did not write ({', '.join(files[:3])}"
                         f"{' and more' if len(files) > 3 else ''}); a model folder is written whole, never into "
                         "another", "pass another out= (a new or empty folder)")
    owner = owning_run_dir(out)
    if owner is not None:
        read_manifest(owner, fix="pass out=PATH outside the run dir")
    return owner


def write_model_folder(run, out: Path, step: int, owner: Optional[Path]) -> Path:
    """The model folder of ``run`` at ``step`` (:func:`export_3dgs`) written whole into a staging folder beside ``out``
    and renamed into place (a previous export there, checked by :func:`_check_folder`, goes as a whole), so that ``out``
    holds one export or none; its files are listed in its own manifest (``writer: b3dgs-export``) and in ``owner``'s
    (the run dir it lies in), before they are moved in."""
    out.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.b3dgs-stage-", dir=out.parent))
    old = None
    try:
        export_3dgs(run, stage, step, model_path=out.resolve())
        files = list(_iter_files(stage))
        _write_manifest(stage, files, None, None, writer="b3dgs-export")
        if owner is not None:
            pre = out.resolve().relative_to(owner).as_posix()
            gone = [f for f in run_files(owner) if f.startswith(f"{pre}/")]
            record_written(owner, [f"{pre}/{f}" for f in [*files, MANIFEST_NAME]], forget=gone)
        if out.is_dir():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.b3dgs-old-", dir=out.parent))
            os.replace(out, old / "model")
        os.replace(stage, out)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    return out


def export(cfg: DictConfig) -> dict:
    """Export ``cfg.run`` (at ``cfg.checkpoint``, default its last) as ``cfg.format`` into ``cfg.out``."""
    from b3dgs.runs import load_run
    from b3dgs.validation import validate_config

    fmt = str(cfg.get("format"))
    if fmt not in FORMATS:
        raise B3dgsError(f"format={fmt} is not an export format{did_you_mean(fmt, FORMATS)}",
                         f"pass format={'|'.join(FORMATS)}")
    validate_config(cfg, app="export")
    overwrite = cfg.get("overwrite", False)
    run_dir = Path(str(cfg.run))
    ckpt = cfg.get("checkpoint")
    if ckpt is not None and not Path(str(ckpt)).is_file():
        raise B3dgsError(f"checkpoint={ckpt}: no such file", f"pass one of {run_dir}/checkpoints/*.ckpt, or null (the last)")
    default = {"ply": run_dir / "export" / "point_cloud.ply", "splat": run_dir / "export" / "scene.splat",
               "3dgs": run_dir / "export" / "3dgs"}[fmt]
    out = Path(str(cfg.out)) if cfg.get("out") else default
    if fmt == "3dgs" and out.exists() and not out.is_dir():
        raise B3dgsError(f"out={out} is a file; format=3dgs writes a folder", "pass out= a folder path")
    if fmt != "3dgs" and (out.is_dir() or not out.suffix):  # out= a folder, as for b3dgs-render, -eval, -suggest
        out = out / default.name
    # what may be written there is settled before the (slow) load: nothing of a user's is replaced unasked
    owner = _check_folder(out) if fmt == "3dgs" else check_replace(
        out, "b3dgs-export", overwrite, "pass overwrite=true to replace it, or another out=")
    if fmt != "3dgs" and out.suffix.lower() != f".{fmt}":
        raise B3dgsError(f"out={out} ends in {out.suffix}, but format={fmt} writes a .{fmt} file",
                         f"pass out={out.with_suffix('.' + fmt)}, or the format its name says")
    run = load_run(run_dir, checkpoint=None if ckpt is None else str(ckpt), data_path=OmegaConf.select(cfg, "data.path"))
    step = int(getattr(run.module, "_loaded_step", 0) or 0)
    with manifest_lock(owner, "b3dgs-export") if owner is not None else nullcontext():
        if fmt == "3dgs":
            write_model_folder(run, out, step, owner)
        else:
            if owner is not None:  # listed in the run's manifest, under its lock, before it is written
                record_written(owner, [out.resolve().relative_to(owner).as_posix()])
            (export_ply if fmt == "ply" else export_splat)(run, out)
    n = run.module.num_gaussians
    log.info("%s: %d Gaussians at step %d as %s -> %s", run_dir, n, step, fmt, out)
    return {"format": fmt, "out": str(out), "step": step, "num_gaussians": n}


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="export")
def hydra_main(cfg: DictConfig) -> None:
    with known_errors("b3dgs-export", cfg, quiet=True):
        w = export(cfg)
        print(f"b3dgs-export: {w['num_gaussians']} Gaussians (step {w['step']}) as {w['format']} -> {w['out']}",
              flush=True)


main = cli_main("b3dgs-export", hydra_main, "export")


if __name__ == "__main__":
    main()
