"""COLMAP scenes (``images/`` + ``sparse/0``).

Pinhole models (PINHOLE, SIMPLE_PINHOLE) are loaded as they are. A camera with lens distortion (SIMPLE_RADIAL,
COLMAP's default, and the other COLMAP models of :data:`b3dgs.data.undistort.MODELS`) is undistorted on load
(``data.undistort`` null, the default, or true) into a pinhole view of the same size at the loaded size, with no blank
border; ``data.undistort=false`` uses such cameras as their pinhole part (fx, fy, cx, cy), with one warning listing
the distortion ignored. Other models (FOV, the division models, equirectangular, ...) are refused with a one-line
error: undistort those with ``colmap image_undistorter`` (or b3dgs-process) first.

The model (``.bin`` or ``.txt``) is read and checked by :mod:`b3dgs.data.colmap_model` (NumPy, no pycolmap: only
``b3dgs-process`` imports it), which names a truncated or inconsistent file in one line. The loaded scene is the one
pycolmap gave: the same frames, bit for bit the same poses (:func:`~b3dgs.data.colmap_model.qvec_to_rotmat`) and the
3D points in the same order (:func:`~b3dgs.data.colmap_model.unordered_map_order`).
"""
from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from b3dgs.data.colmap_model import ColmapCamera, model_format, read_model, unordered_map_order
from b3dgs.data.images import image_folders
from b3dgs.data.scene import FrameSpec, RawScene, fit_to_files, hint_smaller_copies, materialize, select_evenly
from b3dgs.data.undistort import MODELS, Distortion, describe
from b3dgs.errors import B3dgsError

log = logging.getLogger(__name__)

PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")

__all__ = ["check_colmap_binary", "find_sparse_dir", "load_colmap", "read_colmap"]


def find_sparse_dir(root: Path, sparse_dir: Optional[str] = None) -> Path:
    """The model folder: ``root/sparse_dir`` if given, else the first of ``sparse/0``, ``sparse``, ``root``."""
    cand = [root / sparse_dir] if sparse_dir is not None else [root / "sparse" / "0", root / "sparse", root]
    for d in cand:
        if d.is_dir() and model_format(d) is not None:
            return d
    raise B3dgsError(f"no COLMAP model (cameras/images/points3D .bin or .txt) found in "
                     f"{', '.join(str(c) for c in cand)}",
                     "pass data.path=PATH to the scene folder that holds sparse/0 (or data.sparse_dir=FOLDER of the "
                     "model inside it)")


def check_colmap_binary(model_dir: str | os.PathLike) -> None:
    """Parse the binary model of ``model_dir`` and raise :class:`B3dgsError` naming a damaged or inconsistent file:
    every record of cameras/images/points3D.bin is bounds-checked and each file must end right after its last record
    (:func:`~b3dgs.data.colmap_model.read_model`). A text model is checked the same way when it is read."""
    read_model(model_dir, ".bin")


def _intrinsics(cam: ColmapCamera, image_name: str, undistort: Optional[bool] = None) -> tuple[np.ndarray, Any]:
    """(K of the camera's pinhole part, its lens: a :class:`Distortion`, None for a pinhole model, or with
    ``undistort=False`` the description of the distortion ignored)."""
    model = cam.model
    p = np.asarray(cam.params, dtype=np.float64)
    lens = None
    if model == "PINHOLE":
        fx, fy, cx, cy = p[:4]
    elif model == "SIMPLE_PINHOLE":
        fx, cx, cy = p[:3]
        fy = fx
    elif model in MODELS and model != "NERFSTUDIO_OPENCV":
        n = len(p) - len(MODELS[model])  # 3: f, cx, cy; 4: fx, fy, cx, cy
        fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if n == 3 else p[:4]
        coeffs = tuple(float(c) for c in p[n:])
        lens = f"camera {cam.id} {model} {describe(model, coeffs)}" if undistort is False else \
            Distortion(model, coeffs, where=f"COLMAP camera {cam.id} (image {image_name!r})")
    else:
        raise B3dgsError(
            f"COLMAP camera {cam.id} (used by image {image_name!r}) has the model {model}, which b3dgs cannot "
            f"undistort (it reads {' / '.join(PINHOLE_MODELS)} and undistorts "
            f"{', '.join(m for m in MODELS if m != 'NERFSTUDIO_OPENCV')})",
            fix="undistort the images first, e.g. `colmap image_undistorter --image_path images --input_path "
                "sparse/0 --output_path undistorted` or `pycolmap.undistort_images(output_path, input_path, "
                "image_path)`, and point data.path at the result",
        )
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), lens


def read_colmap(
    path: str | os.PathLike,
    images_dir: str = "images",
    sparse_dir: Optional[str] = None,
    point_tracks: bool = False,
    undistort: Optional[bool] = None,
) -> tuple[list[FrameSpec], Optional[np.ndarray], Optional[np.ndarray]]:
    """Parse a COLMAP model: (frames sorted by image name, points xyz (M, 3), colours (M, 3) in [0, 1]).
    A distorted camera's frames carry its lens (undistorted by :func:`b3dgs.data.scene.materialize`); with
    ``undistort=False`` they do not, and one warning lists the distortion ignored."""
    root = Path(path)
    if not root.is_dir():
        raise B3dgsError(f"COLMAP scene folder {root} does not exist", "pass data.path=PATH to an existing scene folder")
    img_root = root / images_dir
    if not img_root.is_dir():
        there = image_folders(root)
        raise B3dgsError(f"COLMAP image folder {img_root} does not exist",
                         f"pass data.images_dir=FOLDER, the folder of {root} that holds the images"
                         + (f" ({', '.join(there)})" if there else ""))
    model_dir = find_sparse_dir(root, sparse_dir)
    model = read_model(model_dir)

    frames = []
    ignored: dict[int, str] = {}  # camera id -> its distortion, when undistort=False
    for im in model.images.values():
        cam = model.cameras[im.camera_id]
        K, lens = _intrinsics(cam, im.name, undistort)
        if isinstance(lens, str):  # undistort=False
            ignored[cam.id], lens = lens, None
        frames.append(FrameSpec(im.name, img_root / im.name, K, im.viewmat(), cam.width, cam.height, lens))
    if ignored:
        log.warning("COLMAP: lens distortion IGNORED (data.undistort=false: images used as their pinhole part, not "
                    "undistorted): %s%s", "; ".join(ignored[k] for k in sorted(ignored)[:3]),
                    f" (+{len(ignored) - 3} more cameras)" if len(ignored) > 3 else "")
    if not frames:
        raise B3dgsError(f"COLMAP model in {model_dir} has no registered images",
                         fix="rerun COLMAP's mapper (or b3dgs-process) until images register, and point data.path at "
                             "that model")
    frames.sort(key=lambda f: f.name)
    frames = fit_to_files(frames, str(img_root))  # images_4, or images/ shrunk after COLMAP ran: K scaled

    points = colors = tracks = None
    if len(model.point_ids) > 0:
        order = unordered_map_order(model.point_ids)  # pycolmap's order: runs keep their bits
        points = model.xyz[order]
        colors = model.rgb[order].astype(np.float32) / 255.0
        if point_tracks:  # the image names that observed each point (init_points_from_train_only)
            names = {i: im.name for i, im in model.images.items()}
            ids, s = model.track["image_id"].tolist(), model.track_start
            tracks = [sorted({names[k] for k in ids[s[i]:s[i + 1]]}) for i in order.tolist()]
    return (frames, points, colors, tracks) if point_tracks else (frames, points, colors)


def load_colmap(path: str | os.PathLike, max_side: Optional[int] = None, background: Sequence[float] = (0.0, 0.0, 0.0),
                max_images: Optional[int] = None, images_dir: str = "images", sparse_dir: Optional[str] = None,
                point_tracks: bool = False, undistort: Optional[bool] = None) -> RawScene:
    """Load a COLMAP scene: cameras (K at the loaded size, OpenCV w2c), images, SfM points. ``undistort``: None or
    True undistort distorted cameras, False uses their pinhole part (module docstring)."""
    out = read_colmap(path, images_dir=images_dir, sparse_dir=sparse_dir, point_tracks=point_tracks,
                      undistort=undistort)
    frames, points, colors = out[:3]
    frames = [frames[i] for i in select_evenly(len(frames), max_images)]
    hint_smaller_copies(Path(path) / images_dir, frames, max_side)
    cams = materialize(frames, max_side=max_side, background=background)
    extras = {"point_views": out[3]} if point_tracks and out[3] is not None else {}
    return RawScene(name=Path(path).resolve().name, cameras=cams, points=points, point_colors=colors, extras=extras)
