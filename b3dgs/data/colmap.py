"""COLMAP scenes (``images/`` + ``sparse/0``), read with pycolmap.

Pinhole models (PINHOLE, SIMPLE_PINHOLE) are loaded as they are. A camera with lens distortion (SIMPLE_RADIAL,
COLMAP's default, RADIAL, OPENCV, FULL_OPENCV, OPENCV_FISHEYE, SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE,
THIN_PRISM_FISHEYE) is undistorted on load (``data.undistort`` null, the default, or true): each image is resampled,
at the loaded size, into a pinhole view of the same size whose focal lengths are scaled so that no border is blank
(:mod:`b3dgs.data.undistort`). ``data.undistort=false`` uses such cameras as their pinhole part (fx, fy, cx, cy),
with one warning listing the distortion ignored. Other models (FOV, the division models, equirectangular, ...) are
refused with a one-line error: undistort those with ``colmap image_undistorter`` (or b3dgs-process) first.

pycolmap is imported lazily, inside :func:`read_colmap`, and only after PIL (see
:mod:`b3dgs.data.images` for why).

Before pycolmap sees a binary model, :func:`check_colmap_binary` walks ``cameras.bin``, ``images.bin``
and ``points3D.bin`` record by record (counts, record sizes, the exact file size): pycolmap trusts the
counts in the headers, so a truncated ``points3D.bin`` once made it reserve memory without bound, and a
short ``images.bin`` loaded silently. ``rigs.bin`` / ``frames.bin`` (COLMAP 3.12+) get a header check.
"""
from __future__ import annotations

import logging
import mmap
import os
import struct
from dataclasses import replace
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from b3dgs.data.images import image_folders, image_size, import_pycolmap  # imports PIL first
from b3dgs.data.scene import FrameSpec, RawScene, materialize, scale_intrinsics, select_evenly
from b3dgs.data.undistort import MODELS, Distortion, describe
from b3dgs.errors import B3dgsError

log = logging.getLogger(__name__)

PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")

__all__ = ["check_colmap_binary", "find_sparse_dir", "load_colmap", "read_colmap"]


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
    raise B3dgsError(f"no COLMAP model (cameras/images/points3D .bin or .txt) found in "
                     f"{', '.join(str(c) for c in cand)}",
                     "pass data.path=PATH to the scene folder that holds sparse/0 (or data.sparse_dir=FOLDER of the "
                     "model inside it)")


def _camera_param_counts() -> dict[int, int]:
    """COLMAP camera model id -> number of parameters, from pycolmap's own model table."""
    pycolmap = import_pycolmap()
    out = {}
    for name, mid in pycolmap.CameraModelId.__members__.items():
        if name == "INVALID" or int(mid) < 0:  # pycolmap 4.0 logs a failed check for it on stderr
            continue
        try:
            out[int(mid)] = len(pycolmap.Camera.create_from_model_name(1, name, 1.0, 2, 2).params)
        except Exception:  # INVALID and models pycolmap cannot build
            continue
    return out


class _Reader:
    """Bounds-checked little-endian reads from a memory-mapped file (no read past its end)."""

    def __init__(self, path: Path, buf):
        self.path, self.buf, self.pos = path, buf, 0

    def remaining(self) -> int:
        return len(self.buf) - self.pos

    def bad(self, what: str) -> B3dgsError:
        return B3dgsError(
            f"COLMAP file {self.path} is damaged: {what} (at byte {self.pos} of {len(self.buf)})",
            "re-export the model (e.g. `colmap model_converter --output_type BIN`) or restore the file")

    def skip(self, n: int, what: str) -> None:
        if n < 0 or n > self.remaining():
            raise self.bad(f"truncated inside {what}")
        self.pos += n

    def unpack(self, fmt: str, what: str) -> tuple:
        n = struct.calcsize(fmt)
        if n > self.remaining():
            raise self.bad(f"truncated inside {what}")
        out = struct.unpack_from(fmt, self.buf, self.pos)
        self.pos += n
        return out

    def count(self, min_record: int, what: str) -> int:
        (n,) = self.unpack("<Q", f"the {what} count")
        if n * min_record > self.remaining():
            raise self.bad(f"header says {n} {what} but only {self.remaining()} bytes follow "
                           f"(at least {min_record} per record): truncated")
        return n

    def name(self, what: str) -> None:
        end = self.buf.find(b"\0", self.pos)
        if end < 0:
            raise self.bad(f"unterminated name in {what}")
        self.pos = end + 1

    def done(self) -> None:
        if self.remaining():
            raise self.bad(f"{self.remaining()} unexpected bytes after the last record")


def _walk(path: Path, walker) -> None:
    size = path.stat().st_size
    if size < 8:
        raise B3dgsError(f"COLMAP file {path} is damaged: {size} bytes, shorter than its 8-byte header",
                         "re-export the model (e.g. `colmap model_converter --output_type BIN`) or restore the file")
    with open(path, "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as buf:
        r = _Reader(path, buf)
        walker(r)


def _walk_cameras(r: _Reader) -> None:
    nparams = _camera_param_counts()
    for i in range(r.count(24, "cameras")):
        _, model_id, w, h = r.unpack("<iiQQ", f"camera {i}")
        if model_id not in nparams:
            raise r.bad(f"camera {i} has the unknown model id {model_id}")
        if not (0 < w < 2**20 and 0 < h < 2**20):
            raise r.bad(f"camera {i} has the size {w}x{h}")
        r.skip(8 * nparams[model_id], f"the parameters of camera {i}")
    r.done()


def _walk_images(r: _Reader) -> None:
    for i in range(r.count(73, "images")):
        r.skip(64, f"the pose of image {i}")
        r.name(f"image {i}")
        (n2d,) = r.unpack("<Q", f"the point count of image {i}")
        r.skip(24 * n2d, f"the 2D points of image {i}")
    r.done()


def _walk_points(r: _Reader) -> None:
    for i in range(r.count(51, "3D points")):
        r.skip(43, f"3D point {i}")
        (track,) = r.unpack("<Q", f"the track length of 3D point {i}")
        r.skip(8 * track, f"the track of 3D point {i}")
    r.done()


def _walk_header(r: _Reader) -> None:
    r.count(8, "records")


def check_colmap_binary(model_dir: str | os.PathLike) -> None:
    """Walk the binary model files of ``model_dir`` and raise :class:`B3dgsError` naming a damaged one.

    Every record of cameras/images/points3D.bin is bounds-checked and the files must end exactly after
    their last record; rigs.bin / frames.bin (if present) must have a plausible record count.
    A text model (``.txt``) is left to pycolmap.
    """
    d = Path(model_dir)
    walkers = {"cameras": _walk_cameras, "images": _walk_images, "points3D": _walk_points,
               "rigs": _walk_header, "frames": _walk_header}
    for stem, walker in walkers.items():
        p = d / f"{stem}.bin"
        if p.is_file():
            _walk(p, walker)


def _intrinsics(cam: Any, image_name: str, undistort: Optional[bool] = None) -> tuple[np.ndarray, Any]:
    """(K of the camera's pinhole part, its lens: a :class:`Distortion`, None for a pinhole model, or with
    ``undistort=False`` the description of the distortion ignored)."""
    model = cam.model.name if hasattr(cam.model, "name") else str(cam.model)
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
        lens = f"camera {cam.camera_id} {model} {describe(model, coeffs)}" if undistort is False else \
            Distortion(model, coeffs, where=f"COLMAP camera {cam.camera_id} (image {image_name!r})")
    else:
        raise B3dgsError(
            f"COLMAP camera {cam.camera_id} (used by image {image_name!r}) has the model {model}, which b3dgs cannot "
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
    check_colmap_binary(model_dir)
    pycolmap = import_pycolmap()
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as e:  # pycolmap raises plain RuntimeError/ValueError on bad files
        raise B3dgsError(f"Cannot read COLMAP model in {model_dir}: {e}",
                         fix="point data.path at a scene folder whose sparse/0 holds a complete COLMAP model "
                             "(cameras, images, points3D), or rebuild it with b3dgs-process") from e

    frames = []
    skipped = []
    ignored: dict[int, str] = {}  # camera id -> its distortion, when undistort=False
    for im in rec.images.values():
        if hasattr(im, "has_pose") and not im.has_pose:
            skipped.append(im.name)
            continue
        cam = rec.cameras[im.camera_id]
        K, lens = _intrinsics(cam, im.name, undistort)
        if isinstance(lens, str):  # undistort=False
            ignored[cam.camera_id], lens = lens, None
        viewmat = np.eye(4)
        viewmat[:3, :4] = np.asarray(im.cam_from_world().matrix(), dtype=np.float64)
        frames.append(FrameSpec(im.name, img_root / im.name, K, viewmat, int(cam.width), int(cam.height), lens))
    if ignored:
        log.warning("COLMAP: lens distortion IGNORED (data.undistort=false: images used as their pinhole part, not "
                    "undistorted): %s%s", "; ".join(ignored[k] for k in sorted(ignored)[:3]),
                    f" (+{len(ignored) - 3} more cameras)" if len(ignored) > 3 else "")
    if skipped:
        log.warning("COLMAP: %d unregistered images skipped (%s...)", len(skipped), ", ".join(skipped[:3]))
    if not frames:
        raise B3dgsError(f"COLMAP model in {model_dir} has no registered images",
                         fix="rerun COLMAP's mapper (or b3dgs-process) until images register, and point data.path at "
                             "that model")
    frames.sort(key=lambda f: f.name)
    if images_dir != "images":  # e.g. Mip-NeRF 360's images_4: a uniform downscale of the model's cameras
        frames = [_at_file_size(f) for f in frames]

    points = colors = None
    if len(rec.points3D) > 0:
        pts = list(rec.points3D.values())
        points = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
        colors = np.array([p.color for p in pts], dtype=np.float32).reshape(-1, 3) / 255.0
    if point_tracks:  # the image names that observed each point (init_points_from_train_only)
        names = {i: im.name for i, im in rec.images.items()}
        tracks = [sorted({names[e.image_id] for e in p.track.elements if e.image_id in names}) for p in pts] \
            if points is not None else None
        return frames, points, colors, tracks
    return frames, points, colors


def _at_file_size(f: FrameSpec) -> FrameSpec:
    """``f`` at the size of its image file when that file is a uniform downscale of the camera (a folder such as
    ``images_4``: K scaled by the per-axis ratio, as :func:`b3dgs.data.scene.materialize` scales it); any other size
    is left for :func:`b3dgs.data.images.load_image` to refuse, naming the file."""
    if not Path(f.path).is_file():
        return f  # load_image names the missing file
    w, h = image_size(f.path)
    s = w / f.width
    if (w, h) == (f.width, f.height) or s > 1.0 or abs(f.height * s - h) > 1.0:
        return f
    return replace(f, K=scale_intrinsics(f.K, w / f.width, h / f.height), width=w, height=h)


def load_colmap(
    path: str | os.PathLike,
    max_side: Optional[int] = None,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    max_images: Optional[int] = None,
    images_dir: str = "images",
    sparse_dir: Optional[str] = None,
    point_tracks: bool = False,
    undistort: Optional[bool] = None,
) -> RawScene:
    """Load a COLMAP scene: cameras (K at the loaded size, OpenCV w2c), images, SfM points.

    ``undistort``: None or True undistort distorted cameras, False uses their pinhole part (module docstring).
    Raises :class:`B3dgsError` for camera models it cannot undistort, size mismatches between an image file and its
    camera, unreadable images, missing folders/files.
    """
    out = read_colmap(path, images_dir=images_dir, sparse_dir=sparse_dir, point_tracks=point_tracks,
                      undistort=undistort)
    frames, points, colors = out[:3]
    frames = [frames[i] for i in select_evenly(len(frames), max_images)]
    cams = materialize(frames, max_side=max_side, background=background)
    extras = {"point_views": out[3]} if point_tracks and out[3] is not None else {}
    return RawScene(name=Path(path).resolve().name, cameras=cams, points=points, point_colors=colors, extras=extras)
