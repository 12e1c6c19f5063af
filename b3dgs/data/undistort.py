"""Lens undistortion of the views a format loader reads (``data.undistort``): the distorted image is resampled into a
pinhole view of the same size. Not with a library: OpenCV is no dependency of b3dgs, and pycolmap's undistorter works
on files (model and image folders, written anew) while the loaders hold decoded images in memory; the math is small, a
closed-form forward distortion per output pixel and one bilinear ``grid_sample``, on the CPU, once per load.

The map, for a frame at the size the loader resized it to (``K`` scaled to that size; the coefficients act on
normalised coordinates, so resizing first is exact up to the resize's own filtering, and cheaper than the other order):

1. ``K' = K`` with both focal lengths times the smallest ``s`` in [:data:`S_MIN`, :data:`S_MAX`] for which every output
   pixel centre samples inside the hull of the source pixel centres and the map does not fold back
   (:func:`pinhole_scale`): no blank border, like COLMAP's undistorter with ``blank_pixels=0``. A perspective model
   with zero coefficients gives ``s = 1`` (the image returned as it is); a fisheye one is equidistant, and undistorted.
2. Output pixel centre ``(i + 0.5, j + 0.5)`` -> ``x = (u - cx) / fx'`` -> :func:`distort` (float64) -> ``K`` -> the
   source pixel, sampled bilinearly (float32, ``align_corners=False``: the pixel-centre-at-0.5 convention of
   :func:`b3dgs.data.scene.scale_intrinsics`).

Models (:data:`MODELS`): COLMAP's (``colmap/sensor/models.h``) and ``NERFSTUDIO_OPENCV``, transforms.json's OPENCV
(nerfstudio / instant-ngp: radial ``1 + k1 r^2 + ... + k4 r^8``, tangential ``p1, p2``), each an optional fisheye angle
map (``x -> x atan(r) / r``) then rational radial, tangential and thin-prism terms (:class:`Distortion`). Images with
alpha are composited over the background by :func:`b3dgs.data.images.load_image` first and remapped after, which equals
remapping RGBA then compositing (compositing is affine in premultiplied colour and alpha; bilinear weights sum to 1).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch

from b3dgs.errors import B3dgsError

#: model -> coefficient names, in the order the format stores them (COLMAP: after fx, fy, cx, cy / f, cx, cy)
MODELS: dict[str, tuple[str, ...]] = {
    "SIMPLE_RADIAL": ("k",),
    "RADIAL": ("k1", "k2"),
    "OPENCV": ("k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "OPENCV_FISHEYE": ("k1", "k2", "k3", "k4"),
    "SIMPLE_RADIAL_FISHEYE": ("k",),
    "RADIAL_FISHEYE": ("k1", "k2"),
    "THIN_PRISM_FISHEYE": ("k1", "k2", "p1", "p2", "k3", "k4", "sx1", "sy1"),
    "NERFSTUDIO_OPENCV": ("k1", "k2", "k3", "k4", "p1", "p2"),
}
FISHEYE = ("OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "THIN_PRISM_FISHEYE")
S_MIN, S_MAX = 0.5, 5.0  # focal scale bounds (COLMAP's undistorter: image scale 1/s in [min_scale 0.2, max_scale 2])
_FIX = ("undistort the images with COLMAP (`colmap image_undistorter`, which may crop) and load the result, or pass "
        "data.undistort=false to use the views as pinhole (distortion ignored)")

__all__ = ["FISHEYE", "MODELS", "Distortion", "describe", "distort", "pinhole_scale", "sampling_grid", "undistort_image"]


def describe(model: str, coeffs) -> str:
    """``"k1=0.058, p1=-0.00098"``: the non-zero coefficients of lens ``model`` (names :data:`MODELS`)."""
    return ", ".join(f"{n}={c:.3g}" for n, c in zip(MODELS[model], coeffs) if c != 0.0) or "all zero"


@dataclass(frozen=True)
class Distortion:
    """A lens model and its coefficients (names :data:`MODELS` ``[model]``); ``where`` names its camera in messages."""

    model: str
    coeffs: tuple[float, ...]
    where: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        names = MODELS.get(self.model)
        if names is None:
            raise B3dgsError(f"{self.where or 'a camera'}: lens model {self.model} cannot be undistorted "
                             f"(supported: {', '.join(MODELS)})", _FIX)
        if len(self.coeffs) != len(names):
            raise B3dgsError(f"{self.where or 'a camera'}: lens model {self.model} takes {len(names)} coefficients "
                             f"({', '.join(names)}), got {len(self.coeffs)}", _FIX)
        if not all(math.isfinite(c) for c in self.coeffs):
            raise B3dgsError(f"{self.where or 'a camera'}: lens model {self.model} has non-finite coefficients "
                             f"({self.describe()})", "write finite distortion coefficients in the scene files, or pass "
                             "data.undistort=false to ignore them")

    @property
    def is_identity(self) -> bool:
        """Zero coefficients of a perspective model (a fisheye model with zero coefficients is still equidistant)."""
        return self.model not in FISHEYE and all(c == 0.0 for c in self.coeffs)

    def describe(self) -> str:
        """``"k1=0.058, p1=-0.00098"``: the non-zero coefficients."""
        return describe(self.model, self.coeffs)

    def terms(self) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, float], tuple[float, float]]:
        """(radial numerator r^2..r^8, radial denominator r^2..r^6, tangential p1 p2, thin prism sx1 sy1)."""
        c = dict(zip(MODELS[self.model], self.coeffs))
        g = lambda *ks: tuple(c.get(k, 0.0) for k in ks)  # noqa: E731
        if self.model in ("SIMPLE_RADIAL", "SIMPLE_RADIAL_FISHEYE"):
            return (c["k"], 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0), (0.0, 0.0)
        if self.model == "FULL_OPENCV":
            return g("k1", "k2", "k3") + (0.0,), g("k4", "k5", "k6"), g("p1", "p2"), (0.0, 0.0)
        return g("k1", "k2", "k3", "k4"), (0.0, 0.0, 0.0), g("p1", "p2"), g("sx1", "sy1")


def distort(d: Distortion, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The forward distortion of normalised pinhole coordinates (float64): where ``(x, y)`` lands in the distorted
    image, in its normalised coordinates (closed form, no iteration)."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    if d.model in FISHEYE:  # equidistant angle map: radius r -> theta = atan(r)
        r = np.hypot(x, y)
        with np.errstate(invalid="ignore", divide="ignore"):
            f = np.where(r > 1e-12, np.arctan(r) / r, 1.0)
        x, y = x * f, y * f
    (a1, a2, a3, a4), (b1, b2, b3), (p1, p2), (s1, s2) = d.terms()
    r2 = x * x + y * y
    radial = (1.0 + r2 * (a1 + r2 * (a2 + r2 * (a3 + r2 * a4)))) / (1.0 + r2 * (b1 + r2 * (b2 + r2 * b3)))
    xy = x * y
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x) + s1 * r2
    yd = y * radial + 2.0 * p2 * xy + p1 * (r2 + 2.0 * y * y) + s2 * r2
    return xd, yd


def _source(d: Distortion, K: np.ndarray, s: float, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Source pixel coordinates of output pixel positions ``(u, v)`` of the pinhole view ``K`` with focals times ``s``."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    xd, yd = distort(d, (u - cx) / (s * fx), (v - cy) / (s * fy))
    return fx * xd + cx, fy * yd + cy


def _border(w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """Every border pixel centre of a ``w`` x ``h`` image."""
    xs, ys = np.arange(w) + 0.5, np.arange(h) + 0.5
    u = np.concatenate([xs, xs, np.full(h, 0.5), np.full(h, w - 0.5)])
    v = np.concatenate([np.full(w, 0.5), np.full(w, h - 0.5), ys, ys])
    return u, v


def _feasible(d: Distortion, K: np.ndarray, w: int, h: int, s: float, border, rays) -> bool:
    """Whether focal scale ``s`` samples every border pixel inside the source's pixel-centre hull, and the map does
    not fold back along rays from the principal point to the border (distorted radius increasing)."""
    U, V = _source(d, K, s, *border)
    eps = 1e-9
    if not (np.isfinite(U).all() and np.isfinite(V).all() and U.min() >= 0.5 - eps and U.max() <= w - 0.5 + eps
            and V.min() >= 0.5 - eps and V.max() <= h - 0.5 + eps):
        return False
    ru, rv = rays
    cx, cy = K[0, 2], K[1, 2]
    U, V = _source(d, K, s, cx + ru, cy + rv)
    dist = np.hypot((U - cx) / K[0, 0], (V - cy) / K[1, 1])
    return bool(np.isfinite(dist).all() and (np.diff(dist, axis=0) > 0).all())


def pinhole_scale(d: Distortion, K: np.ndarray, w: int, h: int, iters: int = 60) -> float:
    """The focal scale ``s`` of the undistorted view (module docstring): the smallest in [S_MIN, S_MAX] that samples
    every output pixel inside the source, by bisection; 1.0 for a perspective model with zero coefficients. Raises
    :class:`B3dgsError` when even ``S_MAX`` does not (the distortion is too strong, or the map folds)."""
    if d.is_identity:
        return 1.0
    K = np.asarray(K, np.float64)
    border = _border(w, h)
    pick = np.linspace(0, len(border[0]) - 1, min(len(border[0]), 256)).round().astype(int)
    t = np.linspace(0.0, 1.0, 65)[1:, None]  # 64 steps from the principal point to 256 border pixels
    rays = (t * (border[0][pick] - K[0, 2]), t * (border[1][pick] - K[1, 2]))
    if not _feasible(d, K, w, h, S_MAX, border, rays):
        raise B3dgsError(f"{d.where or 'a camera'}: its lens distortion ({d.model} {d.describe()}) is too strong to "
                         f"undistort into a pinhole view of the same {w}x{h} size without blank borders (it would need "
                         f"focal lengths over {S_MAX:g}x, or the model folds back inside the image)", _FIX)
    lo, hi = S_MIN, S_MAX
    if _feasible(d, K, w, h, lo, border, rays):
        return lo
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        if _feasible(d, K, w, h, mid, border, rays):
            hi = mid
        else:
            lo = mid
        if hi - lo < 1e-12 * hi:
            break
    return hi


def sampling_grid(d: Distortion, K: np.ndarray, w: int, h: int) -> tuple[np.ndarray, torch.Tensor]:
    """(``K'``, the ``grid_sample`` grid (1, h, w, 2) float32 in [-1, 1]) of undistorting a ``w`` x ``h`` view with
    intrinsics ``K`` (at that size) and lens ``d``."""
    K = np.asarray(K, np.float64)
    s = pinhole_scale(d, K, w, h)
    Kp = K.copy()
    Kp[[0, 1], [0, 1]] *= s  # both focal lengths
    grid = np.empty((h, w, 2), np.float32)
    step = max(1, 2**20 // w)  # rows per block: float64 temporaries of about 1M pixels
    for r in range(0, h, step):
        u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(r, min(h, r + step)) + 0.5)
        U, V = _source(d, K, s, u, v)
        g = np.stack([2.0 * U / w - 1.0, 2.0 * V / h - 1.0], axis=-1)
        if not np.isfinite(g).all() or float(np.abs(g).max()) > 1.0 + 1e-6:
            raise B3dgsError(f"{d.where or 'a camera'}: its lens distortion ({d.model} {d.describe()}) maps part of "
                             f"the {w}x{h} pinhole view outside the image (the model is not monotone there)", _FIX)
        grid[r:r + step] = np.clip(g, -1.0, 1.0)
    return Kp, torch.from_numpy(grid)[None]


def undistort_image(image: np.ndarray, K: np.ndarray, d: Distortion,
                    cache: Optional[dict] = None) -> tuple[np.ndarray, np.ndarray]:
    """(the pinhole image float32 (H, W, 3), ``K'``) of a distorted ``image`` (float32 (H, W, 3), intrinsics ``K`` at
    its size). ``cache``: a dict reused across frames, keyed by (lens, K, size), so frames sharing a camera share one
    grid. A perspective model with zero coefficients returns ``image`` and ``K`` as they are."""
    if d.is_identity:
        return image, np.asarray(K, np.float64)
    h, w = image.shape[:2]
    K = np.asarray(K, np.float64)
    cache, key = {} if cache is None else cache, (d, K.tobytes(), w, h)
    if key not in cache:
        cache[key] = sampling_grid(d, K, w, h)
    Kp, grid = cache[key]
    src = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)[None]
    out = torch.nn.functional.grid_sample(src, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return np.ascontiguousarray(out[0].permute(1, 2, 0).clamp_(0.0, 1.0).numpy()), Kp.copy()
