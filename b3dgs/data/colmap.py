"""COLMAP scenes (``images/`` + ``sparse/0``), read with pycolmap.

Only undistorted pinhole models (PINHOLE, SIMPLE_PINHOLE) are accepted; anything with lens
distortion must be undistorted first (``colmap image_undistorter`` or ``pycolmap.undistort_images``),
as the 3DGS preprocessing does.

pycolmap is imported lazily, inside :func:`read_colmap`, and only after PIL (see
:mod:`b3dgs.data.images` for why).
"""
from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from b3dgs.data.images import import_pycolmap  # imports PIL first
from b3dgs.data.scene import FrameSpec, RawScene, materialize, select_evenly

log = logging.getLogger(__name__)

PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")

__all__ = ["find_sparse_dir", "load_colmap", "read_colmap"]


def _has_model(d: Path) -> bool:
    return all((d / f"{n}.bin").is_file() for n in ("cameras", "images", "points3D")) or all(
        (d / f"{n}.txt").is_file() for n in ("cameras", "images", "points3D")
    )


def find_sparse_dir(root: Path, sparse_dir: Optional[str] = None) -> Path:
    """The model folder: ``root/sparse_dir`` if given, else the first of ``sparse/0``, ``sparse``, ``root``."""
    if sparse_dir is not None:
        cand = [root / sparse_dir]
    else:
        cand = [root / "sparse" / "0", root / "sparse", root]
    for d in cand:
        if d.is_dir() and _has_model(d):
            return d
    raise FileNotFoundError(
        f"No COLMAP model (cameras/images/points3D .bin or .txt) found in "
        f"{', '.join(str(c) for c in cand)}"
    )


def _intrinsics(cam: Any, image_name: str) -> np.ndarray:
    model = cam.model.name if hasattr(cam.model, "name") else str(cam.model)
    p = np.asarray(cam.params, dtype=np.float64)
    if model == "PINHOLE":
        fx, fy, cx, cy = p[:4]
    elif model == "SIMPLE_PINHOLE":
        fx, cx, cy = p[:3]
        fy = fx
    else:
        raise ValueError(
            f"COLMAP camera {cam.camera_id} (used by image {image_name!r}) has the distorted model "
            f"{model}; only {' / '.join(PINHOLE_MODELS)} are supported. Undistort the images first, e.g. "
            f"`colmap image_undistorter --image_path images --input_path sparse/0 --output_path undistorted` "
            f"or `pycolmap.undistort_images(output_path, input_path, image_path)`, and load the result."
        )
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def read_colmap(
    path: str | os.PathLike,
    images_dir: str = "images",
    sparse_dir: Optional[str] = None,
) -> tuple[list[FrameSpec], Optional[np.ndarray], Optional[np.ndarray]]:
    """Parse a COLMAP model: (frames sorted by image name, points xyz (M, 3), colours (M, 3) in [0, 1])."""
    root = Path(path)
    if not root.is_dir():
        raise FileNotFoundError(f"COLMAP scene folder not found: {root}")
    img_root = root / images_dir
    if not img_root.is_dir():
        raise FileNotFoundError(f"COLMAP image folder not found: {img_root}")
    model_dir = find_sparse_dir(root, sparse_dir)
    pycolmap = import_pycolmap()
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as e:  # pycolmap raises plain RuntimeError/ValueError on bad files
        raise ValueError(f"Cannot read COLMAP model in {model_dir}: {e}") from e

    frames = []
    skipped = []
    for im in rec.images.values():
        if hasattr(im, "has_pose") and not im.has_pose:
            skipped.append(im.name)
            continue
        cam = rec.cameras[im.camera_id]
        K = _intrinsics(cam, im.name)
        viewmat = np.eye(4)
        viewmat[:3, :4] = np.asarray(im.cam_from_world().matrix(), dtype=np.float64)
        frames.append(FrameSpec(im.name, img_root / im.name, K, viewmat, int(cam.width), int(cam.height)))
    if skipped:
        log.warning("COLMAP: %d unregistered images skipped (%s...)", len(skipped), ", ".join(skipped[:3]))
    if not frames:
        raise ValueError(f"COLMAP model in {model_dir} has no registered images")
    frames.sort(key=lambda f: f.name)

    points = colors = None
    if len(rec.points3D) > 0:
        pts = list(rec.points3D.values())
        points = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
        colors = np.array([p.color for p in pts], dtype=np.float32).reshape(-1, 3) / 255.0
    return frames, points, colors


def load_colmap(
    path: str | os.PathLike,
    max_side: Optional[int] = None,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    max_images: Optional[int] = None,
    images_dir: str = "images",
    sparse_dir: Optional[str] = None,
) -> RawScene:
    """Load a COLMAP scene: cameras (K at the loaded size, OpenCV w2c), images, SfM points.

    Raises ``ValueError`` for distorted camera models (undistort first), size mismatches between
    an image file and its camera, unreadable images; ``FileNotFoundError`` for missing folders/files.
    """
    frames, points, colors = read_colmap(path, images_dir=images_dir, sparse_dir=sparse_dir)
    frames = [frames[i] for i in select_evenly(len(frames), max_images)]
    cams = materialize(frames, max_side=max_side, background=background)
    return RawScene(name=Path(path).resolve().name, cameras=cams, points=points, point_colors=colors)
