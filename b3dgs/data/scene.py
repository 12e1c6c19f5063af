"""Shared scene preprocessing and the :func:`load_scene` dispatcher.

Every format loader (COLMAP, ``transforms.json``, LLFF, synthetic) produces a :class:`RawScene`: cameras sorted by
name, intrinsics at the loaded resolution (checked by :func:`check_intrinsics` in :func:`materialize`), OpenCV
world-to-camera poses in the format's own world frame, float32 images, optional initial points. :func:`preprocess`
then applies the steps common to all formats, in this order:

1. **normalisation** (``normalize=True``, :func:`normalize_scene`): the mean camera centre to the origin and the 3DGS
   ``cameras_extent`` (:func:`camera_extent`) to 1, over *all* loaded cameras (train and test, so the world frame does
   not depend on the split), recorded as ``scene.transform`` (:class:`SceneTransform`, the identity with
   ``normalize=False``, which reports the raw extent) so that exports can go back to the format's own frame;
2. the **held-out split** (:func:`split_indices` or :func:`sector_split`), the **calibration split**
   (:func:`split_calibration`), then the **train subset**: ``train_indices`` index into the remaining sorted train list;
3. the **bounds** for random initialisation (:func:`compute_bounds`) and the **near-plane guard**
   (:func:`check_near_plane`).

Before anything is read, :func:`check_scene_settings` checks the settings (:data:`DATA_RULES`), the scene folder and
the format loader's own keywords (its ``validate``); the data module calls it when it is built.
"""
from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import inspect
import logging
import math
import os
import shlex
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import torch

from b3dgs.data.images import IMAGE_EXTENSIONS, image_folders, image_size, load_image
from b3dgs.data.undistort import undistort_image
from b3dgs.errors import B3dgsError, did_you_mean
from b3dgs.schema import RGB_RULE, apply_rules, is_int, positive_rule
from b3dgs.types import Camera, Scene, fit_size

log = logging.getLogger(__name__)

# kind -> "module:function" of its loader (imported on use)
LOADERS = {
    "colmap": "b3dgs.data.colmap:load_colmap",
    "transforms": "b3dgs.data.transforms:load_transforms",
    "llff": "b3dgs.data.llff:load_llff",
    "synthetic": "b3dgs.data.synthetic:load_synthetic",
}
SCENE_KINDS = tuple(LOADERS)
NEAR_PLANE = 0.01  # the renderer's near plane (``b3dgs.render.render.render(near=0.01)``)
NEAR_REFUSE = 3.0  # refuse when the median camera-to-scene distance is below NEAR_REFUSE x NEAR_PLANE
NEAR_WARN = 30.0  # warn below NEAR_WARN x NEAR_PLANE

__all__ = [
    "BLENDER_SPLITS",
    "FORWARD_RESULTANT",
    "LOADERS",
    "NEAR_PLANE",
    "SCENE_KINDS",
    "FrameSpec",
    "RawScene",
    "SceneSettings",
    "SceneTransform",
    "DATA_RULES",
    "check_images_dir",
    "check_intrinsics",
    "check_layout",
    "check_near_plane",
    "check_scene_settings",
    "check_undistort",
    "compute_bounds",
    "fit_to_files",
    "get_loader",
    "guess_kinds",
    "hint_smaller_copies",
    "infer_data_option",
    "infer_data_override",
    "load_scene",
    "look_at_point",
    "materialize",
    "normalize_scene",
    "preprocess",
    "read_scene",
    "scene_frame",
    "scene_transform",
    "select_evenly",
    "split_calibration",
    "split_indices",
    "unit_rows",
]


@dataclass
class FrameSpec:
    """One view before its image is decoded: native-resolution intrinsics and OpenCV w2c pose; ``distortion``: its
    lens (:class:`b3dgs.data.undistort.Distortion`), undistorted by :func:`materialize`, or None (a pinhole view)."""

    name: str
    path: Path
    K: np.ndarray  # (3, 3) float64 at (width, height)
    viewmat: np.ndarray  # (4, 4) float64 world-to-camera, OpenCV
    width: int
    height: int
    distortion: Any = None  # Optional[Distortion]


@dataclass
class RawScene:
    """Loader output: cameras in the format's own world frame, sorted by name."""

    name: str
    cameras: list[Camera]
    points: Optional[np.ndarray] = None  # (M, 3)
    point_colors: Optional[np.ndarray] = None  # (M, 3) in [0, 1]
    extras: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class SceneTransform:
    """The similarity ``x_norm = scale * rotation @ x_scene + translation`` that :func:`load_scene` applied to
    the format's own world frame (COLMAP's, transforms.json's); the identity when nothing was applied."""

    scale: float = 1.0
    rotation: tuple = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    translation: tuple = (0.0, 0.0, 0.0)

    @classmethod
    def from_normalisation(cls, mean: np.ndarray, scale: float) -> "SceneTransform":
        """The transform of :func:`normalize_scene`: ``x' = s (x - m)``."""
        return cls(float(scale), translation=tuple(float(v) for v in -float(scale) * np.asarray(mean, np.float64)))

    def to_dict(self) -> dict:
        return {"scale": self.scale, "rotation": [list(r) for r in self.rotation], "translation": list(self.translation),
                "maps": "x_normalised = scale * rotation @ x_scene + translation"}

    @classmethod
    def from_dict(cls, d: dict) -> "SceneTransform":
        return cls(float(d["scale"]), tuple(tuple(float(v) for v in r) for r in d["rotation"]),
                   tuple(float(v) for v in d["translation"]))

    def inverse(self) -> "SceneTransform":
        """The transform from the normalised frame back to the scene's own."""
        R = np.asarray(self.rotation, np.float64)
        t = -(R.T @ np.asarray(self.translation, np.float64)) / self.scale
        return SceneTransform(1.0 / self.scale, tuple(map(tuple, R.T.tolist())), tuple(t.tolist()))

    def apply(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) points mapped by this transform (float64)."""
        R = np.asarray(self.rotation, np.float64)
        return self.scale * np.asarray(points, np.float64) @ R.T + np.asarray(self.translation, np.float64)


@dataclass(frozen=True)
class SceneSettings:
    """The settings common to every scene format: the ``data.*`` keys of every data config besides ``kind``, ``path``,
    ``name`` and the format loader's own (:func:`load_scene`, :class:`~b3dgs.data.datamodule.SceneDataModule` and
    :func:`preprocess` take them as one). Each default is declared here, once; the ranges are :data:`DATA_RULES`."""

    max_side: Optional[int] = None  # downscale so the longest image side is <= max_side (K scaled); None: full size
    test_every: int = 8  # every test_every-th view in sorted name order is held out; 0: none
    # interleaved: every test_every-th view; sector: a contiguous test_fraction of the cameras, held out along one
    # direction (no training camera sees from there: an OOD split); sector+interleaved: both, from one model
    # (scene.test_groups names each kind)
    test_split: str = "interleaved"
    test_fraction: float = 0.125  # test_split=sector: the share of the views held out
    sector_axis: int = 0  # test_split=sector: which principal direction of the camera centres (0, 1, 2)
    train_indices: Optional[Sequence[int]] = None  # indices into the sorted train list to keep; the rest: candidates
    normalize: bool = True  # centre on the mean camera centre and scale the camera extent to 1
    background: Sequence[float] = (0.0, 0.0, 0.0)  # RGB in [0, 1]: transparent pixels over it, stored on the Scene
    max_images: Optional[int] = None  # keep at most this many views, spread evenly, before splitting; None: all
    images_dir: Optional[str] = None  # image folder in path (colmap, llff, transforms), e.g. images_4; None: images/
    undistort: Optional[bool] = None  # lens distortion (colmap, transforms): True undistorts, False ignores; None: the
    # format's default (b3dgs.data.undistort)
    calib_every: Optional[int] = None  # every calib_every-th train view becomes a calibration view (split_calibration)
    near_plane: float = NEAR_PLANE  # the renderer's near plane, for the guard of check_near_plane
    # keep the initial points >= 2 train views saw (filter_points_to_train); the study sets it (its top-level key),
    # no data config lists it (config: False, see b3dgs.confs.field_defaults)
    init_points_from_train_only: bool = field(default=False, metadata={"config": False})

    @classmethod
    def split(cls, keys: dict, base: Optional["SceneSettings"] = None) -> tuple["SceneSettings", dict]:
        """``(settings, kind_kwargs)`` of flat ``data.*`` keys: the fields of this class over ``base`` (default: the
        defaults), and the rest, the format loader's own; config containers become plain lists and dicts."""
        names = {f.name for f in dataclasses.fields(cls)}
        plain = {k: _plain(v) for k, v in keys.items()}
        settings = dataclasses.replace(base or cls(), **{k: v for k, v in plain.items() if k in names})
        return settings, {k: v for k, v in plain.items() if k not in names}

    def loader_kwargs(self) -> dict:
        """What a format loader gets of these settings: ``max_side``, ``background``, ``max_images``, and
        ``images_dir``/``undistort`` where set."""
        out = dict(max_side=self.max_side, background=tuple(float(x) for x in self.background),
                   max_images=self.max_images)
        return {**out, **{k: getattr(self, k) for k in ("images_dir", "undistort") if getattr(self, k) is not None}}


def _plain(v: Any) -> Any:
    """A ``data.*`` value as plain Python: config containers as lists and dicts, tuples as lists, numpy scalars as
    Python numbers (without importing omegaconf eagerly)."""
    if "omegaconf" in sys.modules:
        from omegaconf import DictConfig, ListConfig, OmegaConf

        if isinstance(v, (DictConfig, ListConfig)):
            v = OmegaConf.to_container(v, resolve=True)
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v.item() if isinstance(v, np.generic) else v


class IndicesOutOfRange(B3dgsError, IndexError):
    """``data.train_indices`` names a view the scene does not have (an ``IndexError`` too)."""


def scene_transform(scene: Scene) -> SceneTransform:
    """The normalisation ``load_scene`` applied to ``scene`` (the identity for a scene built another way)."""
    t = getattr(scene, "transform", None)
    return t if isinstance(t, SceneTransform) else SceneTransform()


# ----------------------------------------------------------------------------------------------
# helpers used by the loaders
# ----------------------------------------------------------------------------------------------


def select_evenly(n: int, max_images: Optional[int]) -> list[int]:
    """Indices of ``max_images`` views spread evenly over ``n`` (all of them if ``None``)."""
    if max_images is None or max_images >= n:
        return list(range(n))
    if max_images <= 0:
        raise B3dgsError(f"max_images must be positive, got {max_images}",
                         fix="pass data.max_images as a positive count, or null for every image")
    return sorted(set(np.linspace(0, n - 1, max_images).round().astype(int).tolist()))


def check_pose(name: str, viewmat: np.ndarray, tol: float = 1e-2) -> np.ndarray:
    """Validate a 4x4 world-to-camera matrix; return it with an exactly orthonormal rotation."""
    v = np.asarray(viewmat, dtype=np.float64)
    if v.shape != (4, 4):
        raise B3dgsError(f"Pose of {name!r} must be 4x4, got {v.shape}",
                         fix="pass the world-to-camera pose as a 4x4 matrix (append the row [0, 0, 0, 1] to a 3x4 "
                             "[R|t])")
    if not np.isfinite(v).all():
        raise B3dgsError(f"Pose of {name!r} contains NaN/Inf",
                         fix="repair that camera's pose in the scene's poses file (finite numbers only), or drop the "
                             "image")
    R = v[:3, :3]
    err = np.abs(R.T @ R - np.eye(3)).max()
    det = np.linalg.det(R)
    if err > tol or det <= 0:
        raise B3dgsError(
            f"Pose of {name!r} is not a rigid transform (|R^T R - I|max = {err:.3g}, det(R) = {det:.3g})",
            fix="repair that camera's pose in the scene's poses file: its rotation must be orthonormal with det +1 (no "
                "scaling or mirroring)")
    u, _, vt = np.linalg.svd(R)
    out = v.copy()
    out[:3, :3] = u @ vt
    out[3] = (0, 0, 0, 1)
    return out


def check_intrinsics(name: str, K: np.ndarray, width: int, height: int) -> None:
    """Refuse a view whose focal lengths are not positive and finite or whose principal point lies
    outside its ``width`` x ``height`` image (both at the same resolution)."""
    K = np.asarray(K, dtype=np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    fix = ("correct the intrinsics of this view in the scene files: focal lengths in pixels (> 0) and the "
           "principal point inside the image, given for the image size they were measured at")
    if not (width >= 1 and height >= 1):
        raise B3dgsError(f"view {name!r} has the image size {width}x{height}", fix)
    if not (np.isfinite([fx, fy]).all() and fx > 0 and fy > 0):
        raise B3dgsError(f"view {name!r} has the focal lengths fx={fx:.6g}, fy={fy:.6g}; they must be positive "
                         f"and finite", fix)
    if not (np.isfinite([cx, cy]).all() and 0.0 <= cx <= width and 0.0 <= cy <= height):
        raise B3dgsError(f"view {name!r} has its principal point ({cx:.6g}, {cy:.6g}) outside its "
                         f"{width}x{height} image", fix)


def check_near_plane(name: str, viewmats: np.ndarray, lo: np.ndarray, hi: np.ndarray, normalize: bool,
                     near: float = NEAR_PLANE) -> float:
    """Median distance from the cameras to the centre of the initialisation box; refuse the scene if
    it is below ``NEAR_REFUSE`` x ``near`` (the renderer would drop nearly everything), warn below
    ``NEAR_WARN`` x ``near``."""
    centres, _ = _centres_dirs(viewmats)
    depth = float(np.median(np.linalg.norm(centres - 0.5 * (lo + hi), axis=1)))
    fix = ("data.normalize=true (scales the scene so its camera extent is 1)" if not normalize else
           "rescale the scene: its cameras are closer to their subject than the renderer can draw")
    if depth < NEAR_REFUSE * near:
        raise B3dgsError(f"scene {name!r}: the cameras are {depth:.3g} from the scene, inside the renderer's "
                         f"near plane ({near:g}); every render would be nearly black", fix)
    if depth < NEAR_WARN * near:
        log.warning("Scene %r: the cameras are %.3g from the scene, close to the renderer's near plane (%g); "
                    "Gaussians nearer than it are not drawn (fix: %s)", name, depth, near, fix)
    return depth


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """K for an image resized by (sx, sy) per axis (pixel-centre-at-0.5 convention: exact)."""
    K = np.array(K, dtype=np.float64)
    K[0, :] *= sx
    K[1, :] *= sy
    K[2] = (0, 0, 1)
    return K


def fit_to_files(frames: Sequence[FrameSpec], where: str) -> list[FrameSpec]:
    """``frames`` at the size of their image files where a file is a uniform downscale of its camera (Mip-NeRF 360's
    ``images_4``, or images shrunk after the poses were computed): ``K`` scaled by the per-axis ratio, one log line
    naming ``where`` (the image folder or file). Any other size is left for :func:`b3dgs.data.images.load_image` to
    refuse, naming the file; the official 3DGS code reads images of any size."""
    out, shrunk = [], []
    for f in frames:
        w, h = image_size(f.path) if Path(f.path).is_file() else (f.width, f.height)  # load_image names a missing one
        s = w / f.width
        if (w, h) == (f.width, f.height) or s > 1.0 or abs(f.height * s - h) > 1.0:
            out.append(f)
            continue
        out.append(replace(f, K=scale_intrinsics(f.K, w / f.width, h / f.height), width=w, height=h))
        shrunk.append((f, out[-1]))
    if shrunk:
        f, g = shrunk[0]
        log.info("%d of %d images in %s are smaller than their cameras (e.g. %s: %dx%d, camera %dx%d): intrinsics "
                 "scaled to the files", len(shrunk), len(frames), where, f.name, g.width, g.height, f.width, f.height)
    return out


def hint_smaller_copies(folder: Path, frames: Sequence[FrameSpec], max_side: Optional[int]) -> Optional[str]:
    """Log (and return) a hint when ``data.max_side`` shrinks the files of ``folder`` to half or less and a sibling
    copy ``<name>_<k>`` (Mip-NeRF 360's ``images_4``, LLFF's ``images_8``) is still at least ``max_side``: decoding
    the smaller copy is faster. Not applied by itself: another resampling changes a run's pixels."""
    if not max_side or not frames or _POSES_ONLY.get():
        return None
    folder = Path(folder)
    base, _, factor = folder.name.rpartition("_")
    base, now = (base, int(factor)) if base and factor.isdigit() and int(factor) > 0 else (folder.name, 1)
    side = max(max(f.width, f.height) for f in frames)
    if side < 2 * max_side:
        return None
    f = frames[0]

    def uniform_copy(k: int) -> bool:  # its first image is the first frame's at 1/k (LLFF's copies rename the files)
        d = folder.parent / f"{base}_{k}"
        first = d / Path(f.path).name
        if not first.is_file():
            first = next(iter(sorted(p for p in d.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)), None)
        if first is None:
            return False
        w, h = image_size(first)
        return abs(w - f.width * now / k) <= 1 and abs(h - f.height * now / k) <= 1

    suffixes = (d.name[len(base) + 1:] for d in folder.parent.glob(f"{base}_*") if d.is_dir())
    ks = sorted((int(s) for s in suffixes if s.isdigit()), reverse=True)
    k = next((k for k in ks if k > now and side * now / k >= max_side and uniform_copy(k)), None)
    if k is None:
        return None
    hint = (f"data.max_side={max_side} shrinks {side}-px images from {folder.name}/; {base}_{k}/ holds copies "
            f"{k // now if k % now == 0 else k / now:g}x smaller: data.images_dir={base}_{k} loads them faster (its "
            "resampling differs, so the pixels do too)")
    log.info(hint)
    return hint


_POSES_ONLY = contextvars.ContextVar("b3dgs_poses_only", default=False)


@contextlib.contextmanager
def poses_only():
    """Within it, scenes are read without decoding a pixel: each camera's pose, size and name as a full read gives
    them, its ``image`` None and its ``K`` before any undistortion. For what needs the cameras' geometry only (camera
    centres, the extent, the test split): decoding a scene's images is most of the time of reading it."""
    token = _POSES_ONLY.set(True)
    try:
        yield
    finally:
        _POSES_ONLY.reset(token)


def materialize(
    frames: Sequence[FrameSpec],
    max_side: Optional[int] = None,
    background: Sequence[float] = (0.0, 0.0, 0.0),
) -> list[Camera]:
    """Decode each frame's image once, at the target size (the file's native size must be the frame's), into a
    :class:`Camera` with ``K`` scaled by the per-axis ratio; a frame with a ``distortion`` is then undistorted at that
    size (:func:`b3dgs.data.undistort.undistort_image`), frames sharing a lens, ``K`` and size sharing one sampling
    grid. The frames are not changed. Within :func:`poses_only` no file is read."""
    cams, grids, pixels, smaller = [], {}, not _POSES_ONLY.get(), []
    for f in frames:
        check_intrinsics(f.name, f.K, f.width, f.height)
        w2, h2 = fit_size(f.width, f.height, max_side)
        if (w2, h2) != (f.width, f.height):
            smaller.append(f"{f.width}x{f.height} -> {w2}x{h2}")
        img = load_image(f.path, size=(w2, h2), expected_size=(f.width, f.height), background=background) \
            if pixels else None
        K = scale_intrinsics(f.K, w2 / f.width, h2 / f.height)
        if f.distortion is not None and pixels:
            img, K = undistort_image(img, K, f.distortion, cache=grids)
        cams.append(Camera(f.name, torch.tensor(K, dtype=torch.float32),
                           torch.tensor(check_pose(f.name, f.viewmat), dtype=torch.float32), w2, h2,
                           None if img is None else torch.from_numpy(img)))
    if smaller and pixels:
        log.info("images downscaled to a longest side of %d px (data.max_side; null trains at the files' size): %d of "
                 "%d, e.g. %s", max_side, len(smaller), len(frames), smaller[0])
    return cams


# ----------------------------------------------------------------------------------------------
# shared preprocessing
# ----------------------------------------------------------------------------------------------


def _centres_dirs(viewmats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    R = viewmats[:, :3, :3]
    t = viewmats[:, :3, 3]
    centres = -np.einsum("nji,nj->ni", R, t)  # -R^T t
    dirs = R[:, 2, :]  # optical axis (camera +z) in world coordinates
    return centres, dirs


def camera_extent(viewmats: np.ndarray) -> tuple[np.ndarray, float]:
    """(mean camera centre, 1.1 x max distance of the centres from it)."""
    centres, _ = _centres_dirs(viewmats)
    mean = centres.mean(axis=0)
    return mean, 1.1 * float(np.linalg.norm(centres - mean, axis=1).max())


def check_camera_spread(name: str, viewmats: np.ndarray, rel_tol: float = 1e-6) -> None:
    """Refuse cameras that make a scene meaningless: two or more views whose centres all lie at one point (the same
    pose repeated, or a rotation-only panorama). They have no parallax, so nothing can be triangulated, and the scene's
    extent is 0, which scales the centres' learning rate and the densification thresholds to nothing."""
    if len(viewmats) < 2:
        return
    centres, _ = _centres_dirs(viewmats)
    spread = float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max())
    if not spread > rel_tol * max(1.0, float(np.abs(centres).max())):
        raise B3dgsError(f"Scene {name!r}: all {len(viewmats)} cameras are at one point (their centres lie within "
                         f"{spread:.3g} of their mean), so the views have no parallax and the scene's extent is 0",
                         "use views taken from different positions; a rotation-only panorama or one pose repeated "
                         "cannot be reconstructed in 3D")


def normalize_scene(
    viewmats: np.ndarray, points: Optional[np.ndarray]
) -> tuple[np.ndarray, Optional[np.ndarray], float, np.ndarray, float]:
    """Apply x' = s (x - m) to all poses and points: (viewmats', points', extent', m, s), m the mean camera centre,
    s = 1 / raw extent (1 when all cameras coincide), so the new extent is 1 (0 for coincident cameras). A
    world-to-camera [R | t] becomes [R | s (R m + t)], which keeps the camera frame metric consistent with the world."""
    mean, extent = camera_extent(viewmats)
    s = 1.0 / extent if extent > 1e-12 else 1.0
    out = viewmats.copy()
    R = out[:, :3, :3]
    out[:, :3, 3] = s * (np.einsum("nij,j->ni", R, mean) + out[:, :3, 3])
    pts = None if points is None else (s * (points - mean))
    return out, pts, extent * s, mean, s


def look_at_point(viewmats: np.ndarray, fallback_depth: Optional[float] = None) -> tuple[np.ndarray, bool]:
    """Least-squares point closest to all optical axes: argmin_p sum_i |(I - d_i d_i^T)(p - c_i)|^2.

    Returns (point, well_posed). It is not well posed when the axes are (nearly) parallel (smallest eigenvalue of the
    mean projector < 1e-3) or when the solution lies behind most cameras (diverging axes of a forward-facing capture);
    then the point is the mean centre moved along the mean viewing direction by ``fallback_depth`` if given (e.g.
    LLFF's focus depth from its near/far bounds), else by the rig's radius (1 if all centres coincide)."""
    centres, dirs = _centres_dirs(viewmats)
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(centres, dirs):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    n = len(centres)
    if n >= 2 and np.linalg.eigvalsh(A / n).min() > 1e-3:
        p = np.linalg.solve(A, b)
        if np.median(np.einsum("ni,ni->n", p[None] - centres, dirs)) > 0:
            return p, True
    mean = centres.mean(axis=0)
    d = dirs.mean(axis=0)
    d = d / max(np.linalg.norm(d), 1e-12)
    if fallback_depth is not None and fallback_depth > 0:
        return mean + d * float(fallback_depth), False
    r = float(np.linalg.norm(centres - mean, axis=1).max())
    return mean + d * (r if r > 1e-12 else 1.0), False


def compute_bounds(
    viewmats: np.ndarray,
    points: Optional[np.ndarray] = None,
    percentiles: tuple[float, float] = (1.0, 99.0),
    margin: float = 0.1,
    camera_box_scale: float = 0.5,
    fallback_depth: Optional[float] = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box for random initialisation: with >= 10 points, their per-axis ``percentiles`` widened on each
    side by ``margin`` x their span (SfM outliers ignored); without, a cube centred on the :func:`look_at_point` ``p``
    of the optical axes (``fallback_depth``: see there) of half-size ``camera_box_scale`` x median_i |c_i - p|, half
    the typical viewing distance: the subject the cameras look at lies inside, the cameras outside."""
    if points is not None and len(points) >= 10:
        lo = np.percentile(points, percentiles[0], axis=0)
        hi = np.percentile(points, percentiles[1], axis=0)
        span = np.maximum(hi - lo, 1e-6)
        return lo - margin * span, hi + margin * span
    p, _ = look_at_point(viewmats, fallback_depth)
    centres, _ = _centres_dirs(viewmats)
    half = camera_box_scale * float(np.median(np.linalg.norm(centres - p, axis=1)))
    if not half > 1e-9:
        half = 1.0
    return p - half, p + half


def split_indices(n: int, test_every: int) -> tuple[list[int], list[int]]:
    """(train, test) indices into a name-sorted list: ``i % test_every == 0`` is test; 0 means no test
    (``test_every >= 0``: :data:`DATA_RULES`)."""
    if test_every == 0:
        return list(range(n)), []
    return [i for i in range(n) if i % test_every != 0], list(range(0, n, test_every))


def split_calibration(train: Sequence[Camera], calib_every: Optional[int]) -> tuple[list[Camera], list[Camera]]:
    """(train, calib): every ``calib_every``-th view of the sorted train list (positions ``j`` with
    ``(j + 1) % calib_every == 0``) is a calibration view; ``None`` or 0 holds none out (else ``calib_every >= 2``:
    :data:`DATA_RULES`). Only train views are ever taken, so a calibration view is never a test view."""
    if not calib_every:
        return list(train), []
    calib = [c for j, c in enumerate(train) if (j + 1) % calib_every == 0]
    return [c for j, c in enumerate(train) if (j + 1) % calib_every != 0], calib


TEST_SPLITS = ("interleaved", "sector", "sector+interleaved")


def sector_split(centres: np.ndarray, fraction: float, axis: int = 0) -> tuple[list[int], list[int]]:
    """(train, test) indices: the test views are the ``ceil(fraction · n)`` cameras farthest along one direction, the
    ``axis``-th principal direction of the camera centres (sign: its largest component positive), so they form one
    contiguous sector that no training camera sees from (an arc of a 360° capture, one edge of a forward-facing one).
    Ties go to the earlier index. ``0 < fraction < 1`` and ``axis`` in 0, 1, 2: :data:`DATA_RULES`."""
    c = np.asarray(centres, np.float64).reshape(-1, 3)
    n = len(c)
    u = np.linalg.svd(c - c.mean(0), full_matrices=False)[2][int(axis)]
    u = u if u[np.argmax(np.abs(u))] > 0 else -u
    proj = (c - c.mean(0)) @ u
    k = min(max(1, math.ceil(float(fraction) * n)), n - 1)
    order = sorted(range(n), key=lambda i: (-proj[i], i))
    test = sorted(order[:k])
    return [i for i in range(n) if i not in set(test)], test


def preprocess(raw: RawScene, settings: Optional[SceneSettings] = None) -> Scene:
    """Normalise, split and bound a :class:`RawScene` with ``settings`` (default: :class:`SceneSettings`'s, whose
    fields say what each does; see the module docstring); ``sector+interleaved`` names the test views of each kind in
    ``scene.test_groups``. With ``train_indices``, the other train views become ``scene.candidates``: cameras without
    images, whose images go to a :class:`CandidateStore` that :func:`take_candidate_store` hands to the study driver.
    The settings' ranges are :func:`check_scene_settings`'s (checked before the scene is read), not checked here."""
    s = settings or SceneSettings()
    cams = sorted(raw.cameras, key=lambda c: c.name)
    if not cams:
        raise B3dgsError(f"Scene {raw.name!r} has no cameras",
                         fix="point data.path at a scene with registered cameras (COLMAP sparse/0, transforms.json "
                             "or poses_bounds.npy)")
    names = [c.name for c in cams]
    if len(set(names)) != len(names):
        raise B3dgsError(f"Scene {raw.name!r} has duplicate image names",
                         fix="rename the duplicate images so that each camera's image name is unique")
    viewmats = np.stack([c.viewmat.double().numpy() for c in cams])
    check_camera_spread(raw.name, viewmats)
    points = None if raw.points is None else np.asarray(raw.points, dtype=np.float64).reshape(-1, 3)
    colors = None if raw.point_colors is None else np.asarray(raw.point_colors, dtype=np.float32).reshape(-1, 3)
    if points is not None and colors is not None and len(points) != len(colors):
        raise B3dgsError(f"{len(points)} points but {len(colors)} point colours",
                         fix="pass one colour per point (RawScene.points and point_colors of equal length), or "
                             "point_colors=None")
    if points is not None and len(points) == 0:
        points, colors = None, None
    if points is not None and not np.isfinite(points).all():
        keep = np.isfinite(points).all(axis=1)
        log.warning("Dropping %d non-finite initial points", int((~keep).sum()))
        points = points[keep]
        colors = None if colors is None else colors[keep]

    focus = raw.extras.get("focus_depth")
    transform = SceneTransform()
    if s.normalize:
        viewmats, points, extent, mean, scale = normalize_scene(viewmats, points)
        transform = SceneTransform.from_normalisation(mean, scale)
        focus = None if focus is None else focus * scale
        cams = [
            Camera(c.name, c.K, torch.tensor(v, dtype=torch.float32), c.width, c.height, c.image)
            for c, v in zip(cams, viewmats)
        ]
    else:
        _, extent = camera_extent(viewmats)

    test_groups = None
    if s.test_split.startswith("sector"):
        centres = np.stack([-v[:3, :3].T @ v[:3, 3] for v in viewmats])
        train_idx, test_idx = sector_split(centres, s.test_fraction, s.sector_axis)
        if s.test_split == "sector+interleaved":  # both kinds held out from one model: OOD (sector) against ID views
            sector = set(test_idx)
            between = [i for i in split_indices(len(cams), s.test_every)[1] if i not in sector]
            test_idx = sorted(sector | set(between))
            train_idx = [i for i in range(len(cams)) if i not in set(test_idx)]
            test_groups = {"sector": [cams[i].name for i in sorted(sector)],
                           "interleaved": [cams[i].name for i in between]}
    else:
        train_idx, test_idx = split_indices(len(cams), s.test_every)
    train = [cams[i] for i in train_idx]
    test = [cams[i] for i in test_idx]
    train, calib = split_calibration(train, s.calib_every)
    candidates = []
    if s.train_indices is not None:
        sel = [int(i) for i in s.train_indices]
        bad = [i for i in sel if not 0 <= i < len(train)]
        if bad:
            raise IndicesOutOfRange(f"train_indices {bad} out of range for {len(train)} train views",
                                    f"pass data.train_indices with indices below {len(train)}")
        pool, train = train, [train[i] for i in sel]
        candidates = [c for i, c in enumerate(pool) if i not in set(sel)]
    point_filter = None
    if s.init_points_from_train_only and points is not None:
        points, colors, point_filter = filter_points_to_train(raw, points, colors, train)
    if not train:
        raise B3dgsError(f"Scene {raw.name!r}: no train views (n={len(cams)}, test_every={s.test_every})",
                         fix="leave views to train on: pass a non-empty data.train_indices, or a larger "
                             "data.test_every (0 holds none out), or add images")

    lo, hi = compute_bounds(viewmats, points, fallback_depth=focus)
    check_near_plane(raw.name, viewmats, lo, hi, s.normalize, s.near_plane)
    if colors is None and points is not None:
        colors = np.full_like(points, 0.5, dtype=np.float32)
    scene = Scene(
        name=raw.name,
        train=train,
        test=test,
        points=None if points is None else torch.tensor(points, dtype=torch.float32),
        point_colors=None if colors is None else torch.tensor(np.clip(colors, 0, 1), dtype=torch.float32),
        extent=float(extent),
        bounds_min=torch.tensor(lo, dtype=torch.float32),
        bounds_max=torch.tensor(hi, dtype=torch.float32),
        background=tuple(float(x) for x in s.background),
    )
    scene.calib = list(calib)  # calibration views (data.calib_every); [] when off
    scene.transform = transform  # normalised frame <- the format's own (exports go back through its inverse)
    scene.test_groups = test_groups  # sector+interleaved: the test view names of each kind; else None
    if candidates:  # active-view pool: cameras only; the images go to the driver's store
        scene.candidates = [c.with_image(None) for c in candidates]
        scene._candidate_store = CandidateStore({c.name: c.image for c in candidates})
    if point_filter is not None:
        scene._candidate_store = getattr(scene, "_candidate_store", None) or CandidateStore({})
        scene._candidate_store.point_filter = point_filter
    return scene


class CandidateStore:
    """The images of the candidate views of an active-view study, by view name. Only the study driver holds it
    (:func:`take_candidate_store` removes it from the scene before any model or policy sees the scene): it reads an
    image when a view is acquired, and for the analysis-only ``oracle``. ``reads`` counts every access (leak test)."""

    def __init__(self, images: dict):
        self._images = dict(images)
        self.reads: list[str] = []
        self.point_filter: Optional[dict] = None  # what init_points_from_train_only kept

    def __contains__(self, name: str) -> bool:
        return name in self._images

    def image(self, name: str) -> torch.Tensor:
        self.reads.append(name)
        return self._images[name]

    def acquire(self, camera: Camera) -> Camera:
        """``camera`` with its ground-truth image: the view joins the training set."""
        return camera.with_image(self.image(camera.name))


def take_candidate_store(scene: Scene) -> CandidateStore:
    """Remove the candidates' image store from ``scene`` and return it (an empty one if there is none)."""
    store = scene.__dict__.pop("_candidate_store", None)
    return store if store is not None else CandidateStore({})


def filter_points_to_train(raw: RawScene, points: np.ndarray, colors: Optional[np.ndarray], train: Sequence[Camera]):
    """Keep the initial points observed by at least two of the ``train`` views, so that a sparse start does not inherit
    geometry only the candidate views saw: by the tracks of a COLMAP scene (``raw.extras["point_views"]``: the image
    names of each point's track), else by visibility (a point projecting inside the image in front of the camera; no
    occlusion test, so this keeps slightly more). Returns (points, colors, report)."""
    names = {c.name for c in train}
    total = len(points)
    tracks = raw.extras.get("point_views")
    if tracks is not None:
        finite = np.isfinite(np.asarray(raw.points, dtype=np.float64).reshape(-1, 3)).all(axis=1)
        tracks = [t for t, f in zip(tracks, finite) if f]  # aligned with the finite points kept above
        seen = np.array([sum(1 for n in t if n in names) for t in tracks], dtype=np.int64)
        method = "sfm_tracks"
    else:
        seen = np.zeros(total, dtype=np.int64)
        P = torch.tensor(points, dtype=torch.float64)
        for c in train:
            v, K = c.viewmat.double(), c.K.double()
            x = P @ v[:3, :3].T + v[:3, 3]
            z = x[:, 2]
            uv = (x[:, :2] / z.clamp_min(1e-9)[:, None]) @ K[:2, :2].T + K[:2, 2]
            ok = (z > NEAR_PLANE) & (uv[:, 0] >= 0) & (uv[:, 0] < c.width) & (uv[:, 1] >= 0) & (uv[:, 1] < c.height)
            seen += ok.numpy().astype(np.int64)
        method = "frustum_visibility"
    keep = seen >= 2
    report = {"method": method, "total": int(total), "kept": int(keep.sum()), "train_views": len(names)}
    log.info("init_points_from_train_only: kept %d of %d initial points (seen by >= 2 of %d train views, %s)",
             report["kept"], total, len(names), method)
    if not keep.any():
        return None, None, report  # random initialisation in the bounds
    return points[keep], None if colors is None else colors[keep], report


# kind -> (what its folder must hold, test on the folder); "transforms" also accepts a .json file as the path
_MARKERS = {
    "colmap": ("COLMAP model (cameras, images, points3D .bin/.txt in sparse/0/, sparse/ or the folder)",
               lambda d: any(all((m / f"{n}.{e}").is_file() for n in ("cameras", "images", "points3D"))
                             for m in (d / "sparse" / "0", d / "sparse", d) for e in ("bin", "txt"))),
    "transforms": ("transforms.json or Blender's transforms_{train,val,test}.json",
                   lambda d: (d / "transforms.json").is_file() or any(d.glob("transforms_*.json"))),
    "llff": ("poses_bounds.npy", lambda d: (d / "poses_bounds.npy").is_file()),
}


def guess_kinds(path: str | os.PathLike) -> list[str]:
    """The scene formats whose files a folder holds (a ``.json`` file: ``transforms``)."""
    p = Path(path)
    if p.is_file():
        return ["transforms"] if p.suffix.lower() == ".json" else []
    return [k for k, (_, test) in _MARKERS.items() if p.is_dir() and test(p)]


#: Blender's (NeRF-synthetic) split files are transforms_<split>.json
BLENDER_SPLITS = ("train", "val", "test")

#: the length of the training cameras' mean unit direction from the centre from which a capture with every camera within
#: 90° of that mean is forward-facing (LLFF ≈ 0.99, a half circle 2/π ≈ 0.64, a hemisphere ≈ 0.6; a ring 20° above the
#: equator ≈ 0.34: not)
FORWARD_RESULTANT = 0.5


def unit_rows(v: np.ndarray) -> np.ndarray:
    """``v`` (..., 3) with each row scaled to unit length (rows of length ~0 left as they are)."""
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 1e-12, n, 1.0)


def scene_frame(train: Sequence[Camera], margin_deg: float = 10.0) -> dict:
    """The training cameras' centre (the point they look at, :func:`b3dgs.data.scene.look_at_point`; their mean centre
    when that is not well posed), up (their mean −y), basis ``a``, ``b`` of the plane orthogonal to it, their
    distances and elevations from the centre, and whether they are forward-facing: all within 90° of their mean
    direction from the centre (``axis``) and that mean's length at least :data:`FORWARD_RESULTANT` (a low orbit all
    around is not); ``cos_limit``: a candidate direction d is frontal when d · axis >= it."""
    if not train:
        raise B3dgsError("the run's scene has no training cameras", "pass run=DIR of a run trained on a scene")
    vms = np.stack([c.viewmat.double().cpu().numpy() for c in train])
    c2w = np.stack([c.camtoworld.double().cpu().numpy() for c in train])
    centres = c2w[:, :3, 3]
    if len(train) >= 2:
        target, ok = look_at_point(vms)
        centre = target if ok else centres.mean(0)
    else:  # one camera: the point one rig radius in front of it
        centre = centres[0] + c2w[0, :3, 2]
    up = -c2w[:, :3, 1].mean(0)
    up = unit_rows(up) if np.linalg.norm(up) > 1e-9 else np.array([0.0, 0.0, 1.0])
    a = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 1.0, 0.0])
    a = unit_rows(a)
    b = np.cross(up, a)
    rel = centres - centre
    dist = np.linalg.norm(rel, axis=1)
    dirs = unit_rows(rel)
    elev = np.arcsin(np.clip(dirs @ up, -1.0, 1.0))
    mean = dirs.mean(0)
    axis = unit_rows(mean) if np.linalg.norm(mean) > 1e-6 else up
    forward = bool(np.linalg.norm(mean) >= FORWARD_RESULTANT and (dirs @ axis).min() > 0.0)
    return {"centre": centre, "up": up, "a": a, "b": b, "dist": dist, "elev": elev, "axis": axis,
            "forward": forward, "cos_limit": -math.sin(math.radians(float(margin_deg))) if forward else -1.0 - 1e-9}


def infer_data_option(path: str | os.PathLike, key: str = "data.path") -> tuple[str, str]:
    """The ``data=`` option of a scene folder given alone as ``data.path`` (no ``data=``), and what decided it:
    a COLMAP model (``sparse/0``, ``sparse/`` or the folder) -> ``colmap``; ``transforms.json`` -> ``transforms``;
    only Blender's ``transforms_{train,val,test}.json`` -> ``blender`` (NeRF-synthetic: alpha on white);
    ``poses_bounds.npy`` -> ``llff``. Raises :class:`B3dgsError` for a missing folder, a folder of photos only
    (naming ``b3dgs-process``) and a folder of no known format; its words name the option ``key`` that gave the
    folder (``candidates`` for b3dgs-suggest)."""
    p = Path(path).expanduser()
    if not p.exists():
        raise B3dgsError(f"{key}={path} does not exist", missing_scene_fix(p, key))
    _refuse_inside_a_scene(p, key)
    kinds = guess_kinds(p)
    if "colmap" in kinds:
        return "colmap", "a COLMAP model"
    if "transforms" in kinds:
        blender_split = p.is_file() and p.name.lower() in {f"transforms_{s}.json" for s in BLENDER_SPLITS}
        if (p.is_file() and not blender_split) or (p / "transforms.json").is_file():
            return "transforms", "a transforms.json"
        if blender_split and (p.parent / "transforms.json").is_file():
            return "transforms", "a transforms file"
        return "blender", "Blender's transforms_*.json (NeRF-synthetic: alpha on white)"
    if "llff" in kinds:
        return "llff", "an LLFF poses_bounds.npy"
    _refuse_photos_only(p, key)
    scenes = sorted(d.name for d in p.iterdir() if d.is_dir() and guess_kinds(d)) if p.is_dir() else []
    if scenes:
        listed = ", ".join(scenes[:6]) + (", ..." if len(scenes) > 6 else "")
        raise B3dgsError(f"{key}={path} holds {len(scenes)} scene folder{'s' * (len(scenes) > 1)} ({listed}), not "
                         "a scene", f"pass one of them, e.g. {key}={shlex.quote(str(p / scenes[0]))}")
    named = ", or name its format with data=colmap|transforms|llff" if key == "data.path" else ""
    raise B3dgsError(f"{key}={path} holds no scene: no COLMAP model (sparse/0), transforms*.json or "
                     "poses_bounds.npy", f"pass {key}=PATH to a scene folder{named}")


def infer_data_override(prog: str, argv: list[str]) -> list[str]:
    """``argv`` with ``data=<format>`` added when it sets ``data.path=DIR`` without ``data=`` or ``scene=``: the
    folder's format (:func:`b3dgs.data.scene.infer_data_option`), so that a path is never silently ignored for the
    default scene. One line on stderr says which format was read; a sweep over folders of different formats, a
    missing folder or a folder of photos only is a :class:`B3dgsError`. Overrides Hydra cannot parse are left to it."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser, groups, at, override = OverridesParser.create(), set(), None, None
    for i, arg in enumerate(argv):
        if arg.startswith("-") or "=" not in arg:
            continue
        try:
            parsed = parser.parse_overrides([arg])[0]
        except Exception:  # noqa: BLE001 - Hydra reports a bad override in its own words
            return argv
        groups.add(parsed.key_or_group)
        if parsed.key_or_group == "data.path":
            at, override = i, parsed
    if at is None or groups & {"data", "scene"}:
        return argv
    if override.is_sweep_override() and not {"-m", "--multirun"} & set(argv):
        return argv  # data.path=a,b without -m: Hydra's words (a sweep, a list or a string, e.g. a folder "scan,1")
    values = list(override.sweep_string_iterator()) if override.is_sweep_override() else [override.value()]
    if not all(isinstance(v, str) and v and "${" not in v for v in values):
        return argv  # null or an interpolation: the data module checks what it resolves to
    found = {v: infer_data_option(v) for v in values}
    options = sorted({option for option, _ in found.values()})
    if len(options) > 1:
        raise B3dgsError("data.path sweeps folders of different formats ("
                         + ", ".join(f"{v}: {option}" for v, (option, _) in found.items()) + ")",
                         "sweep the folders of each format in their own command, each with its data=FORMAT")
    option, what = found[values[0]]
    shown = argv[at].partition("=")[2]
    sys.stderr.write(f"{prog}: data.path={shown} holds {what}: reading it with data={option} "
                     f"(pass data=FORMAT to choose another)\n")
    sys.stderr.flush()
    return [*argv[:at], f"data={option}", *argv[at:]]


def missing_scene_fix(path: str | os.PathLike, key: str = "data.path") -> str:
    """The fix for a scene folder that does not exist: ``b3dgs-data get NAME`` where the folder is a registry scene's
    place in this machine's data root (``scene=fox`` on a fresh clone), else an existing folder."""
    from b3dgs import data_root
    from b3dgs.datasets import load_registry

    p = Path(str(path)).expanduser()
    try:
        named = p.name in load_registry()
    except B3dgsError:  # an unreadable $B3DGS_DATA_REGISTRY: the plain fix
        named = False
    if named and p.parent.resolve() == Path(data_root()).expanduser().resolve():
        return f"fetch it: b3dgs-data get {p.name} (into {p.parent}), or set B3DGS_DATA to a folder that holds {p.name}"
    return f"pass {key}=PATH to an existing scene folder"


def _refuse_inside_a_scene(p: Path, key: str = "data.path") -> None:
    """Refuse a path inside a scene folder, naming the scene folder to pass instead: a file other than a ``.json``
    (``poses_bounds.npy``, ``sparse/0/cameras.bin``, an image), a COLMAP model folder (``sparse/0``, ``sparse``)
    without images beside it, or a folder holding no scene of its own (``images/``)."""
    own = guess_kinds(p) if p.is_dir() else []
    model = p.is_dir() and p.name in ("0", "sparse") and not image_folders(p)
    if (p.is_file() and p.suffix.lower() == ".json") or (own and not model):
        return
    start = p if own else p.parent
    scene = next((a for a in [start, *start.parents][:3] if guess_kinds(a)), None)
    if scene is None:
        return
    if scene.name == "0" and scene.parent.name == "sparse":  # a COLMAP model's folder -> the scene folder
        scene = scene.parent
    if scene.name == "sparse":
        scene = scene.parent
    if scene == p:
        return
    what = "a file" if p.is_file() else "the COLMAP model" if model else "a folder"
    raise B3dgsError(f"{key}={p} is {what} inside the scene folder {scene}",
                     f"pass the folder: {key}={shlex.quote(str(scene))}")


def _refuse_photos_only(p: Path, key: str = "data.path") -> None:
    """Refuse a folder that holds photos (directly or in image folders) and no camera poses: b3dgs-process makes a
    scene of it."""
    if p.is_dir() and (image_folders(p) or any(f.suffix in IMAGE_EXTENSIONS for f in p.iterdir() if f.is_file())):
        raise B3dgsError(f"{key}={p} holds photos but no camera poses (no COLMAP model, transforms*.json or "
                         "poses_bounds.npy)",
                         f"run `b3dgs-process images={shlex.quote(str(p))} out=SCENE` (structure from motion), then pass {key}=SCENE")


def check_layout(kind: str, path: str | os.PathLike) -> None:
    """Refuse a scene folder without the files of ``kind`` that holds another format's, naming that format
    (a folder holding no known format is left to the loader, whose :class:`B3dgsError` names the missing file)."""
    if kind not in _MARKERS or not Path(path).is_dir() or _MARKERS[kind][1](Path(path)):
        return
    others = [k for k in guess_kinds(path) if k != kind]
    if not others:
        return _refuse_photos_only(Path(path))
    blender = " (data=blender for a NeRF-synthetic one: alpha on white)" if others[0] == "transforms" else ""
    raise B3dgsError(f"data={kind}: {path} has no {_MARKERS[kind][0]} but holds a {others[0]} scene",
                     f"pass data={others[0]}{blender}")


def get_loader(kind: str):
    """The format loader of scene ``kind``: one of :data:`SCENE_KINDS` (b3dgs's own formats), or any loader
    function named ``"package.module:function"`` (or ``"package.module.function"``), e.g. an installed
    package's. The contract (docs/extending.md): ``loader([path,] *, max_side, background, max_images,
    **kind_kwargs) -> RawScene``; a loader that reads files takes ``path`` as its first parameter, and one that
    can say which images observed each point accepts ``point_tracks`` (``init_points_from_train_only``)."""
    import importlib

    spec = LOADERS.get(kind, kind)
    module, sep, func = spec.partition(":") if ":" in spec else spec.rpartition(".")
    if not sep or not module or not func:
        raise B3dgsError(f"data.kind={kind} is not a scene format{did_you_mean(kind, LOADERS)}",
                         f"pick data={'|'.join(LOADERS)}, or name a loader function as data.kind=package.module:function")
    try:
        loader = getattr(importlib.import_module(module), func)
    except (ImportError, AttributeError) as e:
        raise B3dgsError(f"data.kind={kind}: the loader {spec} cannot be imported ({type(e).__name__}: {e})",
                         "install the package that provides it, or correct data.kind") from None
    if not callable(loader):
        raise B3dgsError(f"data.kind={kind}: {spec} is not a function", "name a loader function")
    return loader


def loader_params(loader) -> dict[str, Any]:
    """The keyword parameters of a format loader, name -> default (``inspect.Parameter.empty`` if none)."""
    return {n: p.default for n, p in inspect.signature(loader).parameters.items()
            if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}


def loader_reads_files(loader) -> bool:
    """Whether a format loader takes a scene ``path`` (its first parameter); the procedural scene does not."""
    return next(iter(loader_params(loader)), None) == "path"


#: the ranges of the data settings (the data module's and :func:`load_scene`'s keywords), checked by
#: :func:`check_scene_settings` in this order, in the form of :data:`b3dgs.schema.RULES`; a format loader's own keywords
#: are its ``validate``'s (e.g. :func:`b3dgs.data.synthetic.validate_synthetic`).
DATA_RULES = {
    "data.max_side?": (lambda v: is_int(v, 1), "an integer >= 1 or null",
                       "pass data.max_side=256 (longest image side in pixels) or null for full resolution"),
    "data.test_every": (lambda v: is_int(v, 0), "an integer >= 0",
                        f"pass data.test_every={SceneSettings.test_every} (every n-th view held out) or 0"),
    "data.test_split": (lambda v: v in TEST_SPLITS, f"one of {'|'.join(TEST_SPLITS)}",
                        "pass data.test_split=interleaved (every test_every-th view), sector (a contiguous sector) or "
                        "sector+interleaved (both, from one model)"),
    "data.test_fraction": (lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v < 1,
                           "a fraction in (0, 1)", f"pass data.test_fraction={SceneSettings.test_fraction}"),
    "data.sector_axis": (lambda v: v in (0, 1, 2) and not isinstance(v, bool), "0, 1 or 2",
                         f"pass data.sector_axis={SceneSettings.sector_axis} (0: the cameras' first principal direction)"),
    "data.max_images?": (lambda v: is_int(v, 1), "an integer >= 1 or null", "pass data.max_images=N or null for all views"),
    "data.train_indices?": (lambda v: isinstance(v, list) and all(is_int(i, 0) for i in v) and len(set(v)) == len(v),
                            "null or a list of distinct indices >= 0", "pass data.train_indices=[0,3,5] or null"),
    "data.background": (*RGB_RULE, "pass data.background=[0,0,0] (black) or data.background=[1,1,1] (white)"),
    "data.near_plane": positive_rule(" (the renderer's near plane)",
                                     "pass renderer.near=0.01 (data.near_plane follows it unless set apart), and "
                                     "data.normalize=true so that the scene's extent is 1"),
    "data.calib_every?": (lambda v: v == 0 or is_int(v, 2), "null, 0 or an integer >= 2 (every n-th training view "
                          "becomes a calibration view)", "pass data.calib_every=16, or null for no calibration views"),
}


def check_scene_settings(kind: str, path: str | os.PathLike | None, settings: SceneSettings, kind_kwargs: dict):
    """Check the settings of a scene load before anything is read, and return the format loader of ``kind``.

    ``settings``: checked against :data:`DATA_RULES`; ``kind_kwargs``: the format loader's own keywords (a key it does
    not take is refused, naming the valid ones), checked by its ``validate`` when it has one. A loader that reads files
    needs ``path`` to exist (and to hold its format, :func:`check_layout`). Raises :class:`B3dgsError` naming the
    ``data.*`` key and the fix; the data module calls it when it is built."""
    kind = str(kind) if str(kind).lower() not in LOADERS else str(kind).lower()
    apply_rules({f"data.{k}": _plain(v) for k, v in vars(settings).items()}, DATA_RULES)
    loader = get_loader(kind)
    unknown = [k for k in kind_kwargs if k not in loader_params(loader)]
    if unknown and not any(p.kind == p.VAR_KEYWORD for p in inspect.signature(loader).parameters.values()):
        valid = sorted({"kind", "path", "name", *vars(settings), *loader_params(loader)} - {"point_tracks"})
        raise B3dgsError(f"data.{unknown[0]} is not a setting of data={kind}{did_you_mean(unknown[0], valid)}",
                         f"remove it or correct its spelling (keys of data: {', '.join(valid)})")
    if not loader_reads_files(loader) and path not in (None, ""):
        try:
            fix = f"drop data={kind}: data.path alone picks the folder's format (here data={infer_data_option(path)[0]})"
        except B3dgsError:
            fix = "drop data.path, or pass data=colmap|transforms|llff for the folder's format"
        raise B3dgsError(f"data={kind} is a scene generated in code and reads no folder, but data.path={path} is set",
                         fix)
    if loader_reads_files(loader):
        if path is None or str(path) == "":
            raise B3dgsError(f"data={kind} reads a scene folder, and data.path is not set", "pass data.path=PATH")
        if not Path(path).exists():
            raise B3dgsError(f"data.path={path} does not exist", missing_scene_fix(path))
        if kind_kwargs.get("sparse_dir") is None:  # a custom model folder is the loader's to find
            check_layout(kind, path)
    if settings.images_dir is not None:
        check_images_dir(kind, loader, path, settings.images_dir)
    if settings.undistort is not None:
        check_undistort(kind, loader, settings.undistort)
    check = getattr(loader, "validate", None)
    if callable(check):
        check(**kind_kwargs)
    return loader


def check_images_dir(kind: str, loader, path: str | os.PathLike | None, folder: Any) -> None:
    """Refuse a ``data.images_dir`` that is no folder name, that the format ``loader`` does not take (its images are
    named in its own files), or that ``path`` does not hold (naming the image folders it does hold)."""
    if not isinstance(folder, str) or not folder.strip() or Path(folder).is_absolute() or ".." in Path(folder).parts:
        raise B3dgsError(f"data.images_dir={folder} is invalid: it must be the name of a folder inside data.path, or null",
                         "pass data.images_dir=images_4 (a folder of the scene), or null for the format's own images/")
    if "images_dir" not in loader_params(loader):
        raise B3dgsError(f"data.images_dir={folder}: data={kind} has no image folder setting (its files name the images)",
                         "pass data.images_dir=null")
    if path is not None and Path(path).is_dir() and not (Path(path) / folder).is_dir():
        there = image_folders(path)
        raise B3dgsError(f"data.images_dir={folder}: {path} has no folder {folder}",
                         f"pass data.images_dir= one of its image folders ({', '.join(there)})" if there else
                         f"{path} holds no image folder: pass data.path=PATH to the scene folder")


def check_undistort(kind: str, loader, value: Any) -> None:
    """Refuse a ``data.undistort`` that is not null/true/false, or that the format ``loader`` does not take (a format
    without lens distortion)."""
    if not isinstance(value, bool):
        raise B3dgsError(f"data.undistort={value} is invalid: it must be true, false or null",
                         "pass data.undistort=true (undistort), false (ignore distortion) or null (the format's default)")
    if "undistort" not in loader_params(loader):
        raise B3dgsError(f"data.undistort={str(value).lower()}: data={kind} has no lens distortion setting",
                         "pass data.undistort=null")


def read_raw(loader, path: str | os.PathLike | None, settings: SceneSettings, kind_kwargs: dict,
             point_tracks: bool = False) -> RawScene:
    """A scene as its format ``loader`` (from :func:`check_scene_settings`, which checked the settings) reads it,
    before :func:`preprocess`. ``point_tracks``: also which images observed each initial point, where the format
    records it (``init_points_from_train_only``)."""
    if point_tracks and "point_tracks" in loader_params(loader):
        kind_kwargs = {**kind_kwargs, "point_tracks": True}  # which images observed each SfM point
    common = settings.loader_kwargs()
    return loader(path, **common, **kind_kwargs) if loader_reads_files(loader) else loader(**common, **kind_kwargs)


def read_scene(loader, kind: str, path: str | os.PathLike | None, settings: SceneSettings, kind_kwargs: dict,
               raw: Optional[RawScene] = None) -> Scene:
    """Read a scene with ``loader`` (:func:`read_raw`; ``raw``: what it read before, read again otherwise) and
    preprocess it with ``settings``."""
    if raw is None:
        raw = read_raw(loader, path, settings, kind_kwargs, point_tracks=settings.init_points_from_train_only)
    scene = preprocess(raw, settings)
    log.info(
        "Loaded %s scene %r: %d train / %d test%s views, %s points, extent %.4g",
        kind, scene.name, len(scene.train), len(scene.test),
        f" / {len(scene.calib)} calibration" if scene.calib else "",
        0 if scene.points is None else len(scene.points), scene.extent,
    )
    return scene


def load_scene(kind: str, path: str | os.PathLike | None, settings: Optional[SceneSettings] = None,
               raw: Optional[RawScene] = None, **keys: Any) -> Scene:
    """Load a scene of ``kind`` (``colmap``, ``transforms``, ``llff``, ``synthetic`` or a loader function
    ``package.module:function``, see :func:`get_loader`) from ``path`` (a folder or ``transforms*.json`` file; None for
    a loader that reads no files) and preprocess it: :func:`check_scene_settings`, then :func:`read_scene`.
    ``keys``: fields of :class:`SceneSettings` over ``settings`` (default its defaults), e.g. ``max_side=256``, and the
    format loader's own keywords (``n_views`` for "synthetic", ``sparse_dir`` for "colmap"). ``raw``: the scene as
    :func:`read_raw` read it with these settings (nothing is read again; its point tracks serve
    ``init_points_from_train_only``)."""
    settings, kind_kwargs = SceneSettings.split(keys, settings)
    path = None if path is None else os.path.expanduser(path)
    loader = check_scene_settings(kind, path, settings, kind_kwargs)
    return read_scene(loader, kind, path, settings, kind_kwargs, raw=raw)
