"""Procedural synthetic scene: an analytic ground truth generated in code (no files), a deterministic function of
``seed``.

The world (z up) holds a smooth-coloured ground disk (radius 1.5 at z = 0) and a few ellipsoids (spheroids resting on
the disk, rotated about z, plus one floating sphere), each with a smooth, spatially varying albedo (low-frequency
sinusoids). Shading is Lambertian under a fixed directional light plus ambient, so a surface point's colour does not
depend on the viewpoint (exactly representable by view-independent 3DGS colours). Images are ray-cast in numpy with
2x2 supersampling per pixel over the background colour (black by default).

Cameras: ``n_views`` on the upper hemisphere (radius 3.5, elevations 15-65 degrees, a Fibonacci spiral with a
seed-dependent azimuth offset), looking at (0, 0, 0.35), 50 degree field of view. Initial points: ``n_points``
samples on the visible-side surfaces with their shaded colours, a "perfect SfM".
"""
from __future__ import annotations

import inspect
import math
from dataclasses import dataclass
from typing import Any, Optional, Sequence

import numpy as np
import torch

from b3dgs.data.scene import RawScene, select_evenly
from b3dgs.errors import B3dgsError
from b3dgs.schema import is_int
from b3dgs.types import Camera

__all__ = ["Ellipsoid", "SyntheticWorld", "load_synthetic", "make_cameras", "make_world", "validate_synthetic"]

DISK_RADIUS = 1.5
LIGHT_DIR = np.array([0.4, -0.3, 0.87]) / np.linalg.norm([0.4, -0.3, 0.87])
AMBIENT = 0.35


@dataclass
class Albedo:
    """albedo(p) = clip(base + amp * sin(2 pi freq . p + phase)) per channel."""

    base: np.ndarray  # (3,)
    amp: np.ndarray  # (3,)
    freq: np.ndarray  # (3, 3) one spatial frequency vector per channel (cycles / unit)
    phase: np.ndarray  # (3,)

    def __call__(self, p: np.ndarray) -> np.ndarray:
        arg = 2 * math.pi * p @ self.freq.T + self.phase
        return np.clip(self.base + self.amp * np.sin(arg), 0.03, 0.97)


@dataclass
class Ellipsoid:
    center: np.ndarray  # (3,)
    R: np.ndarray  # (3, 3) local-to-world rotation
    axes: np.ndarray  # (3,) semi-axes
    albedo: Albedo

    def to_local(self, x: np.ndarray) -> np.ndarray:
        """World points/vectors (already centred if points) to the unit-sphere frame."""
        return (x @ self.R) / self.axes

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Nearest positive ray parameter per ray (inf for a miss). o: (3,), d: (N, 3)."""
        ol = self.to_local((o - self.center)[None])[0]
        dl = self.to_local(d)
        a = (dl * dl).sum(-1)
        b = 2 * dl @ ol
        c = ol @ ol - 1.0
        disc = b * b - 4 * a * c
        t = np.full(len(d), np.inf)
        ok = disc >= 0
        sq = np.sqrt(np.where(ok, disc, 0.0))
        t0 = (-b - sq) / (2 * a)
        t1 = (-b + sq) / (2 * a)
        tt = np.where(t0 > 1e-6, t0, t1)
        hit = ok & (tt > 1e-6)
        t[hit] = tt[hit]
        return t

    def normal(self, p: np.ndarray) -> np.ndarray:
        q = self.to_local(p - self.center) / self.axes  # S^-2 R^T (p - c)
        n = q @ self.R.T
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def inside(self, p: np.ndarray, eps: float = 1e-3) -> np.ndarray:
        return (self.to_local(p - self.center) ** 2).sum(-1) < 1.0 - eps


def _shade(albedo: np.ndarray, n: np.ndarray) -> np.ndarray:
    lam = np.clip(n @ LIGHT_DIR, 0.0, None)[..., None]
    return np.clip(albedo * (AMBIENT + (1 - AMBIENT) * lam), 0.0, 1.0)


class SyntheticWorld:
    """Ground disk + ellipsoids with an analytic ray caster."""

    def __init__(self, ellipsoids: list[Ellipsoid], disk_albedo: Albedo, disk_radius: float = DISK_RADIUS):
        self.ellipsoids = ellipsoids
        self.disk_albedo = disk_albedo
        self.disk_radius = disk_radius

    def cast(self, o: np.ndarray, d: np.ndarray, background: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
        """Colours (N, 3) and ray parameters t (N,) (inf for background) of rays o + t d."""
        n = len(d)
        t_best = np.full(n, np.inf)
        who = np.full(n, -2)  # -2 background, -1 disk, k ellipsoid k
        with np.errstate(divide="ignore", invalid="ignore"):
            td = np.where(d[:, 2] != 0, -o[2] / d[:, 2], np.inf)
        pd = o[None] + td[:, None] * d
        hit = (td > 1e-6) & np.isfinite(td) & ((pd[:, :2] ** 2).sum(-1) <= self.disk_radius**2)
        t_best[hit] = td[hit]
        who[hit] = -1
        for k, e in enumerate(self.ellipsoids):
            t = e.intersect(o, d)
            closer = t < t_best
            t_best[closer] = t[closer]
            who[closer] = k
        rgb = np.full((n, 3), np.asarray(background, dtype=np.float64))
        p = o[None] + np.where(np.isfinite(t_best), t_best, 0.0)[:, None] * d
        m = who == -1
        if m.any():
            nz = np.tile([0.0, 0.0, 1.0 if o[2] >= 0 else -1.0], (int(m.sum()), 1))
            rgb[m] = _shade(self.disk_albedo(p[m]), nz)
        for k, e in enumerate(self.ellipsoids):
            m = who == k
            if m.any():
                rgb[m] = _shade(e.albedo(p[m]), e.normal(p[m]))
        return rgb, t_best

    def render(
        self,
        K: np.ndarray,
        viewmat: np.ndarray,
        width: int,
        height: int,
        supersample: int = 2,
        background: Sequence[float] = (0.0, 0.0, 0.0),
        depth: bool = True,
    ) -> tuple[np.ndarray, Optional[np.ndarray]]:
        """(image float32 (H, W, 3) with ``supersample``^2 rays per pixel, z-depth (H, W) at pixel
        centres (inf on background; None unless ``depth``))."""
        K = np.asarray(K, dtype=np.float64)
        V = np.asarray(viewmat, dtype=np.float64)
        R, tvec = V[:3, :3], V[:3, 3]
        o = -R.T @ tvec
        Kinv = np.linalg.inv(K)
        s = supersample
        offs = (np.arange(s) + 0.5) / s
        u = (np.arange(width)[:, None] + offs[None]).reshape(-1)  # (W*s,)
        v = (np.arange(height)[:, None] + offs[None]).reshape(-1)
        uu, vv = np.meshgrid(u, v)  # (H*s, W*s)
        pix = np.stack([uu, vv, np.ones_like(uu)], -1).reshape(-1, 3)
        dcam = pix @ Kinv.T
        rgb, _ = self.cast(o, dcam @ R, background)
        img = rgb.reshape(height, s, width, s, 3).mean(axis=(1, 3))
        if not depth:
            return img.astype(np.float32), None
        uc, vc = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
        dc = np.stack([uc, vc, np.ones_like(uc)], -1).reshape(-1, 3) @ Kinv.T  # z component = 1
        _, t = self.cast(o, dc @ R, background)
        return img.astype(np.float32), t.reshape(height, width)  # t along (x, y, 1) rays = z-depth

    def sample_points(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """About ``n`` surface points (M, 3) with their shaded colours (M, 3), area-proportional."""
        areas = [math.pi * self.disk_radius**2]
        for e in self.ellipsoids:
            a, b, c = e.axes
            p = 1.6075  # Knud Thomsen's approximation of the ellipsoid area
            areas.append(4 * math.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p))
        counts = np.maximum(1, np.round(n * np.array(areas) / sum(areas)).astype(int))
        pts, cols = [], []
        r = self.disk_radius * np.sqrt(rng.random(counts[0]))
        th = 2 * math.pi * rng.random(counts[0])
        pd = np.stack([r * np.cos(th), r * np.sin(th), np.zeros_like(r)], -1)
        pts.append(pd)
        cols.append(_shade(self.disk_albedo(pd), np.tile([0.0, 0.0, 1.0], (len(pd), 1))))
        for e, cnt in zip(self.ellipsoids, counts[1:]):
            u = rng.normal(size=(cnt, 3))
            u /= np.linalg.norm(u, axis=1, keepdims=True)
            p = e.center + (u * e.axes) @ e.R.T
            pts.append(p)
            cols.append(_shade(e.albedo(p), e.normal(p)))
        P = np.concatenate(pts)
        C = np.concatenate(cols)
        keep = P[:, 2] >= -1e-9
        for e in self.ellipsoids:
            keep &= ~e.inside(P)
        return P[keep], C[keep]


def _hsv_to_rgb(h: float, s: float, v: float) -> np.ndarray:
    k = (np.array([5.0, 3.0, 1.0]) + h * 6.0) % 6.0
    return v - v * s * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)


def _random_albedo(rng: np.random.Generator, hue: float, max_freq: float = 0.8) -> Albedo:
    base = _hsv_to_rgb(hue % 1.0, rng.uniform(0.45, 0.7), rng.uniform(0.6, 0.8))
    amp = rng.uniform(0.1, 0.25, size=3)
    dirs = rng.normal(size=(3, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    freq = dirs * rng.uniform(0.3, max_freq, size=(3, 1))
    return Albedo(base, amp, freq, rng.uniform(0, 2 * math.pi, size=3))


def make_world(seed: int = 0, n_objects: int = 5) -> SyntheticWorld:
    """Seeded world: ``n_objects - 1`` spheroids resting on the disk + one floating sphere."""
    rng = np.random.default_rng(seed)
    ellipsoids: list[Ellipsoid] = []
    placed: list[tuple[np.ndarray, float]] = []
    hue0 = rng.uniform(0, 1)  # object hues are spread evenly around the colour wheel from here
    for k in range(n_objects):
        floating = k == n_objects - 1
        for _ in range(1000):
            if floating:
                axes = np.full(3, rng.uniform(0.22, 0.3))
                center = np.array([*rng.uniform(-0.4, 0.4, size=2), rng.uniform(0.85, 1.0)])
                ok = True
            else:
                axes = np.array([rng.uniform(0.22, 0.42), rng.uniform(0.22, 0.42), rng.uniform(0.2, 0.5)])
                ang = rng.uniform(0, 2 * math.pi)
                rad = rng.uniform(0.0, 1.0)
                center = np.array([rad * math.cos(ang), rad * math.sin(ang), axes[2] * 0.9])
                rxy = float(axes[:2].max())
                ok = np.hypot(*center[:2]) + rxy < DISK_RADIUS - 0.05 and all(
                    np.hypot(*(center[:2] - c[:2])) > rxy + r + 0.05 for c, r in placed
                )
            if ok:
                break
        yaw = rng.uniform(0, 2 * math.pi)
        R = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1.0]])
        if not floating:
            placed.append((center, float(axes[:2].max())))
        ellipsoids.append(Ellipsoid(center, R, axes, _random_albedo(rng, hue0 + k / (n_objects + 1))))
    disk = _random_albedo(rng, hue0 + n_objects / (n_objects + 1), max_freq=0.5)
    disk.base = np.clip(disk.base * 0.75, 0.15, 0.6)  # a slightly darker ground
    return SyntheticWorld(ellipsoids, disk)


def look_at(center: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """OpenCV world-to-camera matrix of a camera at ``center`` looking at ``target`` (z up)."""
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    V = np.eye(4)
    V[:3, :3] = np.stack([x, y, z])
    V[:3, 3] = -V[:3, :3] @ center
    return V


def make_cameras(
    n_views: int = 48,
    resolution: int = 128,
    seed: int = 0,
    radius: float = 3.5,
    fov_deg: float = 50.0,
    elevation_deg: tuple[float, float] = (15.0, 65.0),
    target: Sequence[float] = (0.0, 0.0, 0.35),
) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n_views`` (K, viewmat) pairs on a hemisphere spiral (square images of side ``resolution``)."""
    rng = np.random.default_rng(seed + 7919)
    az0 = rng.uniform(0, 2 * math.pi)
    f = 0.5 * resolution / math.tan(math.radians(fov_deg) / 2)
    K = np.array([[f, 0, resolution / 2], [0, f, resolution / 2], [0, 0, 1.0]])
    s_lo, s_hi = (math.sin(math.radians(e)) for e in elevation_deg)
    golden = math.pi * (3 - math.sqrt(5))
    out = []
    for i in range(n_views):
        sz = s_lo + (s_hi - s_lo) * (i + 0.5) / n_views  # uniform in sin(elevation): area-uniform band
        az = az0 + golden * i
        rxy = math.sqrt(1 - sz * sz)
        c = radius * np.array([rxy * math.cos(az), rxy * math.sin(az), sz])
        out.append((K.copy(), look_at(c, np.asarray(target, dtype=np.float64))))
    return out


def load_synthetic(n_views: int = 48, resolution: int = 128, seed: int = 0, n_points: int = 4000, n_objects: int = 5,
                   supersample: int = 2, max_side: Optional[int] = None, background: Sequence[float] = (0.0, 0.0, 0.0),
                   max_images: Optional[int] = None) -> RawScene:
    """Render the procedural scene: ``n_views`` square views of side ``min(resolution, max_side)``, in the generator's
    world frame (z up, disk at z = 0; :func:`b3dgs.data.load_scene` normalises it), ``extras["world"]`` the
    :class:`SyntheticWorld`. The keywords' ranges are :func:`validate_synthetic`'s (``load_synthetic.validate``)."""
    res = min(resolution, max_side) if max_side else resolution
    world = make_world(seed, n_objects)
    rigs = make_cameras(n_views, res, seed)
    cams = []
    for i in select_evenly(len(rigs), max_images):
        K, V = rigs[i]
        img, _ = world.render(K, V, res, res, supersample=supersample, background=background, depth=False)
        cams.append(Camera(f"view_{i:03d}", torch.tensor(K, dtype=torch.float32), torch.tensor(V, dtype=torch.float32),
                           res, res, torch.from_numpy(img)))
    pts, cols = world.sample_points(n_points, np.random.default_rng(seed + 104729))
    return RawScene(f"synthetic_s{seed}", cams, pts, cols.astype(np.float32), extras={"world": world})


def validate_synthetic(*, n_views: Any = 48, resolution: Any = 128, seed: Any = 0, n_points: Any = 4000,
                       n_objects: Any = 5, supersample: Any = 2, **_: Any) -> None:
    """Check the keywords of :func:`load_synthetic` (the ``data.*`` keys of ``data=synthetic``); raise
    :class:`B3dgsError` naming the key and the fix. ``load_synthetic.validate``: the data module calls it when it is
    built, :func:`b3dgs.data.load_scene` before it renders anything."""
    for key, v, lo, what in (("n_views", n_views, 1, "views"), ("resolution", resolution, 1, "the image side in pixels"),
                             ("supersample", supersample, 1, "rays per pixel side"),
                             ("n_objects", n_objects, 1, "ellipsoids on the disk"),
                             ("n_points", n_points, 0, "initial points; 0: random ones"),
                             ("seed", seed, 0, "the seed of the world and the cameras")):
        if not is_int(v, lo):
            raise B3dgsError(f"data.{key}={v} is invalid: it must be an integer >= {lo} ({what})",
                             f"pass data.{key}={_DEFAULTS[key]}")


_DEFAULTS = {k: p.default for k, p in inspect.signature(load_synthetic).parameters.items()}
load_synthetic.validate = validate_synthetic  # type: ignore[attr-defined]  # the format's own check (b3dgs.data.scene)
