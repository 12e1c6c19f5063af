"""Training schedules: the resolution each step trains at and the Gaussian budget it may densify to.

``schedule=constant`` trains every step at the data's resolution with densification unconstrained by the
schedule (the trainer as it always was, bit for bit). ``schedule=dash`` follows DashGaussian (Chen et al.,
CVPR 2025): early steps train on downsampled views and the resolution rises, by the training images'
frequency content, to full resolution at ``full_res_at`` of the run; the densification budget grows with it.

What the core reads from a schedule (never which one it holds): :meth:`TrainingSchedule.camera`, the training camera
of a step (a downsampled, cached copy); :meth:`TrainingSchedule.step_info`, the hooks' ``info`` (``resolution_scale``,
``budget_fraction``); :meth:`TrainingSchedule.lr_progress`, the progress of the means' learning-rate decay.
"""
from __future__ import annotations

import bisect
import math
from dataclasses import dataclass
from typing import Any, ClassVar, Optional, Sequence

import torch
from torch import Tensor

from b3dgs.errors import B3dgsError
from b3dgs.types import Camera

__all__ = ["ConstantSchedule", "DashSchedule", "TrainingSchedule", "band_energy", "make_schedule"]


@dataclass
class TrainingSchedule:
    """Base: full resolution, no budget, the means' learning rate decayed over the whole run."""

    name: ClassVar[str] = "constant"

    def validate(self, **kwargs: Any) -> None:
        """Check the schedule's own field values; raise :class:`~b3dgs.errors.B3dgsError` naming the field and the fix."""

    def initialize(self, train: Sequence[Camera], max_steps: int) -> None:
        """Derive the schedule from the training views (called once when the Gaussians are created)."""

    def scale(self, step: int) -> float:
        """Downscale factor s >= 1 of ``step`` (rendered size = full size / s)."""
        return 1.0

    def camera(self, camera: Camera, step: int) -> Camera:
        return camera

    def step_info(self, step: int) -> dict:
        return {}

    def lr_progress(self, step: int, max_steps: int) -> float:
        return min(max(step / max(max_steps, 1), 0.0), 1.0)

    def summary(self) -> dict:
        """What metrics.json records about the schedule."""
        return {"name": self.name}


@dataclass
class ConstantSchedule(TrainingSchedule):
    """Every step at the data's resolution; densification as the strategy alone decides (today's training)."""


def band_energy(spectrum: Tensor, scale: float) -> float:
    """Sum of a centred magnitude spectrum (H, W) inside the central window of size (H/scale, W/scale): the part
    of the spectrum that an image downsampled by ``scale`` can still represent (its Nyquist band)."""
    h, w = spectrum.shape[-2:]
    ch, cw = h // 2, w // 2
    hh, hw = max(int(h / scale) // 2, 0), max(int(w / scale) // 2, 0)
    return float(spectrum[..., ch - hh: ch + hh + 1, cw - hw: cw + hw + 1].sum())


def _solve_scale(spectrum: Tensor, target: float, s_max: float, iters: int = 40) -> float:
    """The largest downscale factor in [1, s_max] whose band still holds ``target`` (bisection; the band energy
    falls monotonically as the factor grows)."""
    lo, hi = 1.0, float(s_max)
    if band_energy(spectrum, hi) >= target:
        return hi
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        if band_energy(spectrum, mid) >= target:
            lo = mid
        else:
            hi = mid
    return lo


def mean_spectrum(images: Sequence[Tensor]) -> Tensor:
    """Mean centred FFT magnitude (H, W) of images (H, W, 3) of one size, channels summed, in float64."""
    acc: Optional[Tensor] = None
    for img in images:
        f = torch.fft.fftshift(torch.fft.fft2(img.detach().to("cpu", torch.float64).permute(2, 0, 1)), dim=(-2, -1))
        mag = f.abs().sum(0)
        acc = mag if acc is None else acc + mag
    assert acc is not None
    return acc / len(images)


@dataclass
class DashSchedule(TrainingSchedule):
    """Resolution and primitive schedule after DashGaussian (Chen et al., CVPR 2025), written for our trainer.

    Resolution: training starts at the largest factor ``s0 <= max_scale`` whose central spectral band still holds
    ``1 / start_energy_factor`` of every view's magnitude; the band energy then rises log-linearly,
    E(t) = E(s0) (E(1) / E(s0))^(t / T) with T = ``full_res_at`` x max_steps, quantised to ``levels`` factors (each
    level's images cached while in use; the schedule only rises). Primitive schedule: a strategy may fill the share
    ``(1/s)^(2 - t/T)`` of its head-room (``budget_fraction``). Trim (beyond DashGaussian): with ``keep`` < 1, from full
    resolution (or the first level with factor <= ``keep_below``) the info holds ``keep_fraction`` and the strategy
    keeps that share of its Gaussians once, by compositing weight. The means' learning-rate decay starts when the
    factor first drops below 2. Densification statistics are in NDC units, so need no rescaling. docs/schedule.md
    gives the details.

    Defaults chosen on fox, fern, lego seed 0 (bench/results/schedule_screen.md, schedule_screen2.md) and judged on
    seven scenes x three seeds (bench/results/schedule.md); ``budget`` is off: -1.3 dB on fox, -0.0 on fern there.
    """

    name: ClassVar[str] = "dash"
    full_res_at: float = 0.5        # fraction of max_steps at which training reaches full resolution
    max_scale: float = 8.0          # cap on the starting downscale factor
    start_energy_factor: float = 4.0  # start where the band holds 1/this of every view's spectrum magnitude
    levels: int = 12                # number of distinct resolutions (incl. full)
    min_side: int = 16              # never train below this many pixels on the SHORT side (>= 11: the SSIM window)
    budget: bool = False            # grow the densification head-room with the resolution (DashGaussian's)
    keep: float = 0.45              # < 1: at full resolution keep this share of the Gaussians, the most used
    keep_below: float = 1.0         # trim once the downscale factor is <= this (1: at full resolution)
    delay_lr_decay: bool = True     # start the means' lr decay when the factor drops below 2

    def __post_init__(self) -> None:
        # derived by initialize() from the training views (not configuration, not dataclass fields)
        self._scales: list[float] = []  # level factors, descending, the last one 1
        self._starts: list[int] = []  # first step of each level
        self._full_steps = 0
        self._lr_start = 0
        self._cache: dict = {}
        self._cache_level = -1

    def validate(self, **kwargs: Any) -> None:
        if not 0.0 <= float(self.full_res_at) <= 1.0:
            raise B3dgsError(f"schedule.full_res_at must be in [0, 1], got {self.full_res_at}", "pass e.g. schedule.full_res_at=0.5")
        if not float(self.max_scale) >= 1.0:
            raise B3dgsError(f"schedule.max_scale must be >= 1, got {self.max_scale}", "pass e.g. schedule.max_scale=8")
        if not float(self.start_energy_factor) > 1.0:
            raise B3dgsError(f"schedule.start_energy_factor must be > 1, got {self.start_energy_factor}",
                             "pass e.g. schedule.start_energy_factor=4")
        if not float(self.keep_below) >= 1.0:
            raise B3dgsError(f"schedule.keep_below must be >= 1 (a downscale factor), got {self.keep_below}",
                             "pass e.g. schedule.keep_below=1.0, the trim at full resolution")
        if not 0.0 < float(self.keep) <= 1.0:
            raise B3dgsError(f"schedule.keep must be in (0, 1], got {self.keep}", "pass e.g. schedule.keep=1.0")
        if int(self.levels) < 2:
            raise B3dgsError(f"schedule.levels must be >= 2, got {self.levels}", "pass e.g. schedule.levels=12")
        if int(self.min_side) < 11:
            raise B3dgsError(f"schedule.min_side must be >= 11 (the SSIM loss's window), got {self.min_side}",
                             "pass e.g. schedule.min_side=16")

    # ------------------------------------------------------------------ set-up
    def initialize(self, train: Sequence[Camera], max_steps: int) -> None:
        self._cache, self._cache_level = {}, -1
        self._full_steps = int(round(float(self.full_res_at) * int(max_steps)))
        imgs = [c.image for c in train if c.image is not None]
        if not imgs or self._full_steps <= 0:
            self._scales, self._starts, self._lr_start = [1.0], [0], 0
            return
        short_side = min(min(int(c.width), int(c.height)) for c in train)
        s_cap = max(1.0, min(float(self.max_scale), short_side / float(self.min_side)))
        by_size: dict[tuple, list[Tensor]] = {}
        for im in imgs:
            by_size.setdefault(tuple(im.shape[:2]), []).append(im)
        # the starting factor: the largest one whose band keeps 1/start_energy_factor of EVERY view's magnitude
        s0 = s_cap
        spectra = []
        for group in by_size.values():
            for im in group:
                spec = mean_spectrum([im])
                s0 = min(s0, _solve_scale(spec, band_energy(spec, 1.0) / float(self.start_energy_factor), s_cap))
            spectra.append((mean_spectrum(group), len(group)))
        # the schedule follows the largest group's mean spectrum (one size in every scene we know; mixed sizes
        # share the criterion through the relative band)
        spec = max(spectra, key=lambda x: x[1])[0]
        e_tot, e0 = band_energy(spec, 1.0), band_energy(spec, s0)
        n = int(self.levels)
        scales = [s0 ** (1.0 - k / (n - 1)) for k in range(n)]  # geometric from s0 down to 1
        scales[-1] = 1.0
        starts = [0]
        for s in scales[1:]:
            e = band_energy(spec, s)
            frac = 1.0 if not (e_tot > e0 > 0) else math.log(max(e, e0) / e0) / math.log(e_tot / e0)
            starts.append(int(round(min(max(frac, 0.0), 1.0) * self._full_steps)))
        for i in range(1, n):  # monotone (quantisation can tie)
            starts[i] = max(starts[i], starts[i - 1])
        starts[-1] = self._full_steps
        self._scales, self._starts = scales, starts
        below2 = [st for s, st in zip(scales, starts) if s < 2.0]
        self._lr_start = below2[0] if (below2 and self.delay_lr_decay) else 0

    # ------------------------------------------------------------------ per step
    def level(self, step: int) -> int:
        return max(bisect.bisect_right(self._starts, step) - 1, 0)  # the last level started (starts ascend)

    def scale(self, step: int) -> float:
        return float(self._scales[self.level(step)]) if self._scales else 1.0

    def camera(self, camera: Camera, step: int) -> Camera:
        lv = self.level(step) if self._scales else 0
        s = self._scales[lv] if self._scales else 1.0
        if s <= 1.0:
            if self._cache:
                self._cache, self._cache_level = {}, -1
            return camera
        if lv != self._cache_level:  # the schedule only rises: the lower level's images are never needed again
            self._cache, self._cache_level = {}, lv
        w, h = max(1, int(round(camera.width / s))), max(1, int(round(camera.height / s)))
        key = (camera.name, id(camera))
        hit = self._cache.get(key)
        if hit is None or hit[0] is not camera:
            hit = (camera, camera.resized(w, h))
            self._cache[key] = hit
        return hit[1]

    def step_info(self, step: int) -> dict:
        s = self.scale(step)
        out = {"resolution_scale": 1.0 / s}
        if step >= self._full_steps or s <= max(1.0, float(self.keep_below)):
            if float(self.keep) < 1.0:
                out["keep_fraction"] = float(self.keep)
        elif self.budget:
            t = min(step / self._full_steps, 1.0) if self._full_steps > 0 else 1.0
            out["budget_fraction"] = float((1.0 / s) ** (2.0 - t))
        return out

    def lr_progress(self, step: int, max_steps: int) -> float:
        if self._lr_start <= 0:
            return super().lr_progress(step, max_steps)
        span = max(int(max_steps) - self._lr_start, 1)
        return min(max((step - self._lr_start) / span, 0.0), 1.0)

    def summary(self) -> dict:
        return {"name": self.name, "full_res_step": self._full_steps, "lr_decay_from": self._lr_start,
                "levels": [{"scale": round(float(s), 4), "from_step": int(st)} for s, st in zip(self._scales, self._starts)]}


def make_schedule(node: Any) -> TrainingSchedule:
    """The schedule of a config's ``schedule`` node (``None``, as in run dirs written before schedules:
    :func:`b3dgs.upgrade.schedule_node`, the constant one)."""
    if isinstance(node, TrainingSchedule):
        return node
    from hydra.utils import instantiate

    from b3dgs.upgrade import schedule_node

    node = schedule_node(node)
    sched = instantiate(node)
    if not isinstance(sched, TrainingSchedule):
        raise B3dgsError(f"schedule._target_={node.get('_target_')} builds a {type(sched).__name__}, not a "
                         "b3dgs.schedule.TrainingSchedule", "pick a schedule= option (constant, dash), or name a "
                         "TrainingSchedule subclass as schedule._target_")
    return sched
