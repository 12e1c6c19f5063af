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
  ``cfg_args``, the folder the official scripts and the SIBR viewer read.
"""
from __future__ import annotations

import logging
from contextlib import nullcontext
from pathlib import Path

import hydra
import numpy as np
import torch
from omegaconf import DictConfig

from b3dgs.errors import B3dgsError
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
    from b3dgs.ply import frame_comments, write_splats

    splats, frame, inv = _own_frame(run)
    extra = {k: v.detach().cpu() for k, v in run.module.export_extras().items()} if extras else None
    return write_splats(path, splats, inv, extra=extra or None, comments=frame_comments(frame))


def splat_records(splats: dict, inv) -> np.ndarray:
    """(N, 32) uint8: per Gaussian, position (3 float32), linear scale (3 float32), RGBA (4 uint8), rotation (4 uint8,
    (q / |q|) · 128 + 128), in ``inv``'s frame, sorted by exp(Σ log-scale) · opacity, largest first (ties by index)."""
    from b3dgs.ply import transform_gaussians

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
    from b3dgs.io import atomic_path

    splats, _, inv = _own_frame(run)
    rec = splat_records(splats, inv)
    with atomic_path(path) as tmp:
        tmp.write_bytes(rec.tobytes())
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


def export_3dgs(run, folder: Path, step: int) -> Path:
    from b3dgs.io import atomic_path, write_json

    _, _, inv = _own_frame(run)
    export_ply(run, folder / "point_cloud" / f"iteration_{step}" / "point_cloud.ply", extras=False)
    cams = list(run.scene.train) + list(run.scene.test)
    write_json(folder / "cameras.json", camera_entries(cams, inv))
    bg = [float(v) for v in run.cfg.model.get("background", (0.0, 0.0, 0.0))]
    args = (f"Namespace(data_device='cuda', eval={bool(run.scene.test)}, images='images', "
            f"model_path={str(folder)!r}, resolution=-1, sh_degree={int(run.cfg.model.get('sh_degree', 3))}, "
            f"source_path={str(run.cfg.data.get('path') or '')!r}, white_background={bg == [1.0, 1.0, 1.0]})")
    with atomic_path(folder / "cfg_args") as tmp:
        tmp.write_text(args)
    return folder


def export(cfg: DictConfig) -> dict:
    """Export ``cfg.run`` (at ``cfg.checkpoint``, default its last) as ``cfg.format`` into ``cfg.out``."""
    from b3dgs.runs import load_run

    fmt = str(cfg.get("format"))
    if fmt not in FORMATS:
        from b3dgs.errors import did_you_mean

        raise B3dgsError(f"format={fmt} is not an export format{did_you_mean(fmt, FORMATS)}",
                         f"pass format={'|'.join(FORMATS)}")
    run_dir = Path(str(cfg.run))
    ckpt = cfg.get("checkpoint")
    if ckpt is not None and not Path(str(ckpt)).is_file():
        raise B3dgsError(f"checkpoint={ckpt}: no such file", f"pass one of {run_dir}/checkpoints/*.ckpt, or null (the last)")
    run = load_run(run_dir, checkpoint=None if ckpt is None else str(ckpt))
    step = int(getattr(run.module, "_loaded_step", 0) or 0)
    default = {"ply": run_dir / "export" / "point_cloud.ply", "splat": run_dir / "export" / "scene.splat",
               "3dgs": run_dir / "export" / "3dgs"}[fmt]
    out = Path(str(cfg.out)) if cfg.get("out") else default
    inside = out.resolve().is_relative_to(run_dir.resolve())
    if inside:  # what goes into the run dir joins its manifest: check it before writing
        from b3dgs.rundir import read_manifest

        read_manifest(run_dir, fix="pass out=PATH outside the run dir")
    if fmt == "3dgs" and out.exists() and not out.is_dir():
        raise B3dgsError(f"out={out} is a file; format=3dgs writes a folder", "pass out= a folder path")
    if fmt != "3dgs" and out.is_dir():
        raise B3dgsError(f"out={out} is a folder; format={fmt} writes one file", f"pass out=PATH/NAME.{fmt}")
    names = []
    if inside:  # listed in the run's manifest, under its lock, before it is written
        rel = out.resolve().relative_to(run_dir.resolve()).as_posix()
        pre = "" if rel == "." else f"{rel}/"
        names = [rel] if fmt != "3dgs" else [f"{pre}cameras.json", f"{pre}cfg_args",
                                              f"{pre}point_cloud/iteration_{step}/point_cloud.ply"]
    from b3dgs.rundir import manifest_lock, record_written

    with manifest_lock(run_dir, "b3dgs-export") if inside else nullcontext():
        if names:
            record_written(run_dir, names)
        if fmt == "3dgs":
            export_3dgs(run, out, step)
        else:
            (export_ply if fmt == "ply" else export_splat)(run, out)
    n = run.module.num_gaussians
    log.info("%s: %d Gaussians at step %d as %s -> %s", run_dir, n, step, fmt, out)
    return {"format": fmt, "out": str(out), "step": step, "num_gaussians": n}


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="export")
def hydra_main(cfg: DictConfig) -> None:
    from b3dgs.errors import known_errors, quiet_known_noise

    with known_errors("b3dgs-export", cfg):
        quiet_known_noise()
        w = export(cfg)
        print(f"b3dgs-export: {w['num_gaussians']} Gaussians (step {w['step']}) as {w['format']} -> {w['out']}",
              flush=True)


def main() -> None:
    """``b3dgs-export``: one-line errors with exit code 2 (see :mod:`b3dgs.errors`)."""
    from b3dgs.errors import run_cli

    run_cli("b3dgs-export", hydra_main, config="export")


if __name__ == "__main__":
    main()
