"""instant-ngp / nerfstudio / Blender-synthetic ``transforms.json`` scenes.

* Intrinsics: ``fl_x, fl_y, cx, cy, w, h`` (instant-ngp, nerfstudio) or Blender's ``camera_angle_x`` (``fx = w / 2 /
  tan(camera_angle_x / 2)``; ``fy`` from ``camera_angle_y``, else ``fx``), top-level and overridden per frame; the
  principal point defaults to the image centre, missing ``w``/``h`` are read from the image header. Top-level
  ``fl_x``/``cx``... without ``w``/``h`` over images of *different* sizes are taken for the size whose centre is
  nearest ``(cx, cy)`` and scaled to each other size of the same aspect ratio (with a warning); any other mix is
  refused (add ``w`` and ``h``). :func:`b3dgs.data.scene.check_intrinsics` then checks them.
* Poses: ``transform_matrix`` is an OpenGL/NeRF camera-to-world (x right, y up, z backwards), made OpenCV by flipping
  the camera's y and z axes (``c2w[:3, 1:3] *= -1``), then inverted. ``file_path`` is relative to the JSON file's
  folder, with or without an extension.
* **Lens distortion** (``data.undistort``, :mod:`b3dgs.data.undistort`): ``camera_model`` OPENCV (the default;
  ``k1..k4`` radial on r^2..r^8, ``p1, p2`` tangential) or OPENCV_FISHEYE (equidistant, ``k1..k4`` on theta); FISHEYE,
  EQUIRECTANGULAR and FISHEYE624 are refused. ``undistort=None`` (the default) *ignores* OPENCV coefficients as before
  this option existed (archived runs on fox reproduce bit for bit), with one warning naming their largest magnitudes,
  and undistorts OPENCV_FISHEYE; ``True`` undistorts every frame into a pinhole view of the same size (focal lengths
  scaled, no blank border); ``False`` ignores all distortion, with the warning.
* RGBA images are composited over the scene ``background`` (before undistortion, which commutes with it). An optional
  ``ply_file_path`` (nerfstudio) gives initial points (xyz, and colours if present).
* A folder without ``transforms.json`` but with Blender's ``transforms_{train,val,test}.json``: their frames are merged
  (the held-out split is then re-made by :func:`b3dgs.data.load_scene`).
* ``images_dir`` (``data.images_dir=images_2``): each frame's image is that folder's file of the same name, as
  nerfstudio's ``--downscale-factor`` reads ``images_N/``; the intrinsics, which name the full-size images, are scaled
  to the files (:func:`b3dgs.data.scene.fit_to_files`).
"""
from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from b3dgs.data.images import image_size
from b3dgs.data.scene import (BLENDER_SPLITS, FrameSpec, RawScene, fit_to_files, materialize, scale_intrinsics,
                              select_evenly)
from b3dgs.data.undistort import FISHEYE, MODELS, Distortion
from b3dgs.errors import B3dgsError

log = logging.getLogger(__name__)

DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
NUMBER_KEYS = ("w", "h", "fl_x", "fl_y", "cx", "cy", "camera_angle_x", "camera_angle_y") + DISTORTION_KEYS


def _is_number(v) -> bool:
    try:
        float(v)
    except (TypeError, ValueError):
        return False
    return not isinstance(v, (bool, list, dict))


def _check_numbers(jf: Path, meta: dict) -> None:
    """Refuse a non-numeric camera value of ``transforms.json``, naming the file, frame and key."""
    for where, d in [("", meta)] + [(f"frame {i} ", fr) for i, fr in enumerate(meta["frames"])]:
        if not isinstance(d, dict):
            raise B3dgsError(f"{jf}: {where or 'the top level '}is not a JSON object",
                             f"write {where or 'the top level '}of {jf.name} as a JSON object ({{...}})")
        for k in NUMBER_KEYS:
            if d.get(k) is not None and not _is_number(d[k]):
                raise B3dgsError(f"{jf}: {where}{k}={d[k]!r} is not a number", f"write a number for {k} in that file")
        m = d.get("transform_matrix")
        if m is not None and not (isinstance(m, list) and all(isinstance(r, list) and all(_is_number(x) for x in r)
                                                             for r in m)):
            raise B3dgsError(f"{jf}: {where}transform_matrix holds a value that is not a number",
                             "write a 4x4 (or 3x4) list of numbers in that file")


_UNSUPPORTED_MODELS = ("FISHEYE", "EQUIRECTANGULAR", "FISHEYE624")
_EXTS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG", ".exr", ".webp")

# OpenGL (x right, y up, z back) -> OpenCV (x right, y down, z forward) on the camera side.
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])

__all__ = ["GL_TO_CV", "load_transforms", "read_transforms"]


def _resolve_json(path: Path) -> list[Path]:
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise B3dgsError(f"transforms scene {path} does not exist",
                         "pass data.path=PATH to an existing scene folder (or its transforms*.json file)")
    if (path / "transforms.json").is_file():
        return [path / "transforms.json"]
    split = [p for p in (path / f"transforms_{s}.json" for s in BLENDER_SPLITS) if p.is_file()]
    if split:
        return split
    raise B3dgsError(f"{path} has no transforms.json (nor transforms_train.json)",
                     "pass data.path=PATH to the folder that holds transforms.json, or to the .json file itself")


def _resolve_image(root: Path, file_path: str) -> Path:
    p = root / file_path
    if p.is_file():
        return p
    if p.suffix.lower() not in _EXTS:
        found: list[Path] = []
        for q in (p.with_name(p.name + ext) for ext in _EXTS):
            if q.is_file() and not any(os.path.samefile(q, f) for f in found):  # .png and .PNG on a case-blind disk
                found.append(q)
        if len(found) > 1:  # which one was meant cannot be told: never load one of them silently
            raise B3dgsError(f"file_path {file_path!r} has no extension and two files have that name: "
                             f"{found[0].name} and {found[1].name}",
                             f"write file_path with its extension ({Path(file_path).name}{found[0].suffix} or "
                             f"{Path(file_path).name}{found[1].suffix}) in the transforms file, or remove the other file")
        if found:
            return found[0]
    raise B3dgsError(f"the image of file_path {file_path!r} does not exist (looked for {p} with and without an "
                     "extension)", "restore the image, or correct file_path in the transforms file")


def _read_ply(path: Path) -> tuple[np.ndarray, Optional[np.ndarray]]:
    from plyfile import PlyData  # a dependency of b3dgs

    try:
        v = PlyData.read(str(path))["vertex"]
    except Exception as e:
        raise B3dgsError(f"Cannot read point cloud {path}: {e}",
                         fix="check ply_file_path in the transforms file: it must name a readable PLY with a "
                             "'vertex' element (x, y, z), or remove the key to start from random points") from e
    names = v.data.dtype.names
    xyz = np.stack([np.asarray(v[k], dtype=np.float64) for k in ("x", "y", "z")], axis=1)
    rgb = None
    if all(k in names for k in ("red", "green", "blue")):
        rgb = np.stack([np.asarray(v[k], dtype=np.float32) for k in ("red", "green", "blue")], axis=1)
        if np.asarray(v["red"]).dtype == np.uint8 or rgb.max() > 1.0:
            rgb = rgb / 255.0
    return xyz, rgb


def _rescale_shared_intrinsics(jf: Path, meta: dict, frames: list[FrameSpec], unsized: list[int]) -> None:
    """Frames ``unsized`` use top-level pixel intrinsics without ``w``/``h``; if their images differ in
    size, scale K from the size the intrinsics fit (image centre nearest the principal point) to each."""
    sizes = sorted({(frames[i].width, frames[i].height) for i in unsized})
    if len(sizes) < 2:
        return
    fix = f"add \"w\" and \"h\" (the image size the intrinsics refer to) to {jf.name}, or per-frame intrinsics"
    if "cx" not in meta or "cy" not in meta:
        raise B3dgsError(f"{jf}: images of sizes {', '.join(f'{w}x{h}' for w, h in sizes)} share one focal length "
                         f"but the file gives no w/h or principal point to tell which size it belongs to", fix)
    cx, cy = float(meta["cx"]), float(meta["cy"])
    ref_w, ref_h = min(sizes, key=lambda s: abs(cx - s[0] / 2) + abs(cy - s[1] / 2))
    for i in unsized:
        f = frames[i]
        if (f.width, f.height) == (ref_w, ref_h):
            continue
        sx, sy = f.width / ref_w, f.height / ref_h
        if abs(sx / sy - 1.0) > 0.01:
            raise B3dgsError(f"{jf}: image {f.name} is {f.width}x{f.height}, not a rescaled {ref_w}x{ref_h} (the "
                             f"size the shared intrinsics fit), and the file has no w/h", fix)
        f.K = scale_intrinsics(f.K, sx, sy)
    log.warning("%s has no w/h and images of sizes %s: shared intrinsics taken for %dx%d and scaled to the others",
                jf, ", ".join(f"{w}x{h}" for w, h in sizes), ref_w, ref_h)


def read_transforms(
    path: str | os.PathLike,
    undistort: Optional[bool] = None,
    images_dir: Optional[str] = None,
) -> tuple[list[FrameSpec], Optional[np.ndarray], Optional[np.ndarray], dict[str, float]]:
    """Parse transforms JSON file(s): (frames sorted by name, points, colours, max |coefficient| per key of the
    distortion left ignored). Frames to undistort (``undistort``, see the module docstring) carry their lens;
    ``images_dir``: the folder whose files of the frames' names are read (module docstring)."""
    path = Path(path)
    files = _resolve_json(path)
    frames: list[FrameSpec] = []
    distortion: dict[str, float] = {}  # max |coefficient| ignored on frames used as pinhole (not undistorted)
    dropped: dict[str, float] = {}  # ... and on undistorted frames whose lens model lacks it (OPENCV_FISHEYE's p1, p2)
    points = colors = None
    for jf in files:
        try:
            meta = json.loads(jf.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise B3dgsError(f"Cannot parse {jf}: {e}",
                             fix=f"repair the JSON syntax of {jf.name} (python -m json.tool {jf} shows "
                                 "where), or restore the file") from e
        root = jf.parent
        if "frames" not in meta or not meta["frames"]:
            raise B3dgsError(f"{jf} has no frames",
                             fix=f'list the views in {jf.name} under "frames", each with file_path and '
                                 "transform_matrix")
        first = len(frames)
        unsized: list[int] = []  # frames with top-level pixel intrinsics but no w/h
        _check_numbers(jf, meta)
        for i, fr in enumerate(meta["frames"]):
            g = {**meta, **fr}  # per-frame keys override global ones
            if "file_path" not in fr or "transform_matrix" not in fr:
                raise B3dgsError(f"{jf}: frame {i} lacks file_path or transform_matrix",
                                 fix=f"give frame {i} of {jf.name} both file_path (the image) and transform_matrix "
                                     "(its 4x4 camera-to-world pose)")
            model = str(g.get("camera_model", "OPENCV")).upper()
            if model in _UNSUPPORTED_MODELS:
                raise B3dgsError(f"{jf}: camera_model {model} cannot be undistorted (b3dgs undistorts OPENCV and "
                                 "OPENCV_FISHEYE)",
                                 fix="undistort the images to a pinhole model first (e.g. nerfstudio's "
                                     "ns-process-data or COLMAP's image_undistorter) and write camera_model PINHOLE "
                                     "or OPENCV with zero distortion")
            if images_dir is None:
                img_path = full = _resolve_image(root, fr["file_path"])
            else:  # the intrinsics name the full-size image: its size comes from w/h, else from that image
                img_path = _resolve_image(root / images_dir, Path(fr["file_path"]).name)
                try:
                    full = None if "w" in g and "h" in g else _resolve_image(root, fr["file_path"])
                except B3dgsError:
                    raise B3dgsError(f"{jf}: data.images_dir={images_dir} scales the intrinsics from the full-size "
                                     f"image of {fr['file_path']!r}, which is missing, and the file gives no w and h",
                                     f"add \"w\" and \"h\" (the full image size) to {jf.name}, or restore the "
                                     "full-size images") from None
            name = Path(os.path.relpath(img_path, path if path.is_dir() else root)).as_posix()
            lens, vals = None, {k: float(g[k]) for k in DISTORTION_KEYS if g.get(k) is not None and float(g[k]) != 0.0}
            lens_model = "OPENCV_FISHEYE" if model == "OPENCV_FISHEYE" else "NERFSTUDIO_OPENCV"
            if undistort or (undistort is None and lens_model in FISHEYE):  # null: OPENCV ignored, as it always was
                if vals or lens_model in FISHEYE:
                    lens = Distortion(lens_model, tuple(vals.get(k, 0.0) for k in MODELS[lens_model]),
                                      where=f"{jf.name} frame {fr['file_path']!r}")
                vals = {k: v for k, v in vals.items() if k not in MODELS[lens_model]}
            for k, v in vals.items():  # undistorted frames: the lens model has no such coefficient
                into = dropped if lens is not None else distortion
                into[k] = max(into.get(k, 0.0), abs(v))
            if "w" in g and "h" in g:
                w, h = int(round(float(g["w"]))), int(round(float(g["h"])))
            else:  # the full-size image's (with images_dir, the intrinsics still name it)
                w, h = image_size(full)
                if not any(k in fr for k in ("fl_x", "fl_y", "cx", "cy", "camera_angle_x")) and (
                        "fl_x" in meta or "fl_y" in meta):
                    unsized.append(len(frames) - first)
            if "fl_x" in g or "fl_y" in g:
                fx = float(g.get("fl_x", g.get("fl_y")))
                fy = float(g.get("fl_y", fx))
            elif "camera_angle_x" in g:
                fx = 0.5 * w / math.tan(0.5 * float(g["camera_angle_x"]))
                fy = 0.5 * h / math.tan(0.5 * float(g["camera_angle_y"])) if "camera_angle_y" in g else fx
            else:
                raise B3dgsError(f"{jf}: frame {fr['file_path']!r} has no focal length (fl_x/fl_y or camera_angle_x)",
                                 fix=f"add fl_x (and fl_y) in pixels, or camera_angle_x in radians, to {jf.name} "
                                     "(globally or in this frame)")
            cx = float(g.get("cx", w / 2.0))
            cy = float(g.get("cy", h / 2.0))
            K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
            c2w = np.asarray(fr["transform_matrix"], dtype=np.float64)
            if c2w.shape == (3, 4):
                c2w = np.vstack([c2w, [0, 0, 0, 1]])
            if c2w.shape != (4, 4):
                raise B3dgsError(f"{jf}: transform_matrix of {fr['file_path']!r} has shape {c2w.shape}",
                                 fix=f"write transform_matrix of {fr['file_path']!r} as a 4x4 (or 3x4) "
                                     "camera-to-world matrix")
            if not np.isfinite(c2w).all():
                raise B3dgsError(f"{jf}: transform_matrix of {fr['file_path']!r} contains NaN/Inf",
                                 fix=f"write finite numbers in transform_matrix of {fr['file_path']!r}, or drop that "
                                     f"frame from {jf.name}")
            c2w_cv = c2w @ GL_TO_CV
            try:
                viewmat = np.linalg.inv(c2w_cv)
            except np.linalg.LinAlgError as e:
                raise B3dgsError(f"{jf}: transform_matrix of {fr['file_path']!r} is singular",
                                 fix="write a rigid camera-to-world pose (an invertible 4x4) for "
                                     f"{fr['file_path']!r}, or drop that frame") from e
            frames.append(FrameSpec(name, img_path, K, viewmat, w, h, lens))
        _rescale_shared_intrinsics(jf, meta, frames[first:], unsized)
        if meta.get("ply_file_path") and points is None:
            ply = root / meta["ply_file_path"]
            if not ply.is_file():
                raise B3dgsError(f"ply_file_path {ply} of {jf} does not exist",
                                 "restore that file, or drop ply_file_path from the transforms file (random points "
                                 "are used then)")
            points, colors = _read_ply(ply)
    if dropped:  # the images were undistorted; only these coefficients, which their model lacks, were not applied
        log.warning("transforms.json: frames undistorted with their %s lens (k1..k4); %s, which that model does not "
                    "have, ignored", ", ".join(sorted({f.distortion.model for f in frames if f.distortion})),
                    ", ".join(f"{k}={v:.3g}" for k, v in dropped.items()))
    frames.sort(key=lambda f: f.name)
    return fit_to_files(frames, str(path)), points, colors, distortion


def load_transforms(path: str | os.PathLike, max_side: Optional[int] = None,
                    background: Sequence[float] = (0.0, 0.0, 0.0), max_images: Optional[int] = None,
                    undistort: Optional[bool] = None, images_dir: Optional[str] = None) -> RawScene:
    """Load a ``transforms.json`` scene (see the module docstring: ``undistort`` None ignores OPENCV distortion with a
    warning and undistorts OPENCV_FISHEYE, True undistorts every frame, False ignores all distortion; ``images_dir``
    reads a downscaled copy such as nerfstudio's ``images_2``)."""
    frames, points, colors, distortion = read_transforms(path, undistort=undistort, images_dir=images_dir)
    if distortion:
        log.warning(
            "transforms.json: lens distortion is IGNORED (images used as pinhole, not undistorted); "
            "max |coefficient|: %s; %s",
            ", ".join(f"{k}={v:.3g}" for k, v in distortion.items()),
            "as data.undistort=false asks" if undistort is False else "data.undistort=true undistorts them",
        )
    frames = [frames[i] for i in select_evenly(len(frames), max_images)]
    cams = materialize(frames, max_side=max_side, background=background)
    p = Path(path).resolve()
    name = p.name if p.is_dir() else p.parent.name
    return RawScene(name=name, cameras=cams, points=points, point_colors=colors, extras={"distortion": distortion})
