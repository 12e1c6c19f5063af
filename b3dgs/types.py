"""Shared data types: cameras and scenes.

Conventions used everywhere in b3dgs:
- world-to-camera ``viewmat`` in the OpenCV convention (x right, y down, z forward);
- pixel intrinsics ``K`` at the camera's current resolution, pixel centres at integer + 0.5;
- images are float32 (H, W, 3) in [0, 1].
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field, replace
from typing import Optional

import numpy as np
import torch
from torch import Tensor

from b3dgs.errors import B3dgsError


@dataclass
class Camera:
    """A pinhole camera with an optional ground-truth image."""

    name: str
    K: Tensor  # (3, 3) float32 pixel intrinsics
    viewmat: Tensor  # (4, 4) float32 world-to-camera (OpenCV)
    width: int
    height: int
    image: Optional[Tensor] = None  # (H, W, 3) float32 in [0, 1]

    def __post_init__(self) -> None:
        if tuple(self.K.shape) != (3, 3):
            raise B3dgsError(f"Camera {self.name!r}: K must be (3, 3), got {tuple(self.K.shape)}",
                             fix="pass K as a (3, 3) pinhole intrinsics matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
        if tuple(self.viewmat.shape) != (4, 4):
            raise B3dgsError(f"Camera {self.name!r}: viewmat must be (4, 4), got {tuple(self.viewmat.shape)}",
                             fix="pass viewmat as a (4, 4) world-to-camera matrix (append the row [0, 0, 0, 1] to a "
                                 "3x4 [R|t])")
        if self.width <= 0 or self.height <= 0:
            raise B3dgsError(f"Camera {self.name!r}: width/height must be positive, got {self.width}x{self.height}",
                             fix="pass the image's width and height in pixels, both > 0")
        if self.image is not None and tuple(self.image.shape) != (self.height, self.width, 3):
            raise B3dgsError(f"Camera {self.name!r}: image must be (H, W, 3) = ({self.height}, {self.width}, 3), "
                             f"got {tuple(self.image.shape)}",
                             fix="pass the image at the camera's size, a float tensor of shape (height, width, 3), or "
                                 "scale K to the image's size")
        if not torch.isfinite(self.K).all() or not torch.isfinite(self.viewmat).all():
            raise B3dgsError(f"Camera {self.name!r}: K or viewmat contains NaN/Inf",
                             fix="pass finite intrinsics and pose; repair that camera's entry in the scene's poses "
                                 "file")

    def focal_max(self) -> float:
        """max(fx, fy) as a Python float, read once per camera object (a device copy made by :meth:`to` inherits the
        host camera's value, so renders on a GPU need no device read for it)."""
        v = self.__dict__.get("_focal_max")
        if v is None:
            v = float(max(self.K[0, 0], self.K[1, 1]))
            self.__dict__["_focal_max"] = v
        return v

    @property
    def camtoworld(self) -> Tensor:
        """Inverse of the rigid ``viewmat``: [Rᵀ | -Rᵀt] (no general matrix inverse)."""
        R, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        out = torch.eye(4, dtype=self.viewmat.dtype, device=self.viewmat.device)
        out[:3, :3] = R.T
        out[:3, 3] = -R.T @ t
        return out

    @property
    def center(self) -> Tensor:
        """Camera centre in world coordinates, -Rᵀt."""
        return -self.viewmat[:3, :3].T @ self.viewmat[:3, 3]

    @property
    def center64(self) -> np.ndarray:
        """-Rᵀt in float64, the same bits on every CPU: the float32 products are exact in float64 and summed in a
        fixed order. ``center``'s float32 matmul rounds differently across CPUs (and renders keep it for their bits);
        analysis that must rebuild identically elsewhere (support distances) reads this one."""
        v = self.viewmat.detach().cpu().double().numpy()
        R, t = v[:3, :3], v[:3, 3]
        return -(R[0] * t[0] + R[1] * t[1] + R[2] * t[2])

    def with_image(self, image: Optional[Tensor]) -> "Camera":
        return replace(self, image=image)

    def resized(self, width: int, height: int) -> "Camera":
        """This camera rendered at ``width`` x ``height``: K scaled per axis (exact in the pixel-centre-at-0.5
        convention, computed in float64) and the image, if any, area-averaged on its own device."""
        width, height = int(width), int(height)
        if (width, height) == (self.width, self.height):
            return self
        sx, sy = width / self.width, height / self.height
        K = self.K.double()
        K = torch.stack([K[0] * sx, K[1] * sy, K.new_tensor([0.0, 0.0, 1.0])]).to(self.K.dtype)
        image = None if self.image is None else resize_image(self.image, width, height)
        return Camera(self.name, K, self.viewmat, width, height, image)

    def fit(self, max_side: Optional[int], *, upscale: bool = False, min_side: int = 1) -> "Camera":
        """This camera :meth:`resized` so that its longer side is ``max_side`` px (:func:`fit_size`)."""
        return self.resized(*fit_size(self.width, self.height, max_side, upscale=upscale, min_side=min_side))

    def to(self, device: "torch.device | str") -> "Camera":
        """This camera with K, viewmat and image on ``device`` (itself if already there)."""
        device = torch.device(device)
        if self.viewmat.device == device:
            return self
        self.focal_max()  # read here, on the host; the copy keeps it (no device read per render)
        moved = copy.copy(self)  # already validated: no second pass over the image on the new device
        moved.K, moved.viewmat = self.K.to(device), self.viewmat.to(device)
        moved.image = None if self.image is None else self.image.to(device, non_blocking=True)
        return moved


def fit_size(width: float, height: float, max_side: Optional[int], *, upscale: bool = False,
             min_side: int = 1) -> tuple[int, int]:
    """(w, h) of a ``width`` x ``height`` image scaled so that its longer side is ``max_side`` px, the shorter one
    rounded (at least ``min_side``); the one "fit the long side" rule of b3dgs (data loading, scoring resolution,
    rendered frames, the viewer's frames). ``max_side=None``, or an image already that small without ``upscale``,
    keeps the size; ``max_side <= 0`` is a ValueError."""
    if max_side is not None and max_side <= 0:
        raise B3dgsError(f"max_side must be positive, got {max_side}",
                         fix="pass max_side as a positive number of pixels, or None to keep the size")
    if max_side is None or (not upscale and max(width, height) <= max_side):
        return int(width), int(height)
    s = max_side / max(width, height)
    return max(min_side, int(round(width * s))), max(min_side, int(round(height * s)))


def resize_image(image: Tensor, width: int, height: int) -> Tensor:
    """(H, W, C) -> (height, width, C) by area averaging (exact box filter for integer factors), on the image's
    own device and dtype; the one downscale of tensors in b3dgs (decoding from files goes through PIL's BOX)."""
    if tuple(image.shape[:2]) == (int(height), int(width)):
        return image
    import torch.nn.functional as F

    x = image.permute(2, 0, 1).unsqueeze(0)
    return F.interpolate(x, size=(int(height), int(width)), mode="area")[0].permute(1, 2, 0).contiguous()


@dataclass
class Scene:
    """A normalised multi-view scene: train/test cameras and optional initial points."""

    name: str
    train: list[Camera]
    test: list[Camera]
    points: Optional[Tensor] = None  # (M, 3) float32 initial points (SfM or ground truth)
    point_colors: Optional[Tensor] = None  # (M, 3) float32 in [0, 1]
    extent: float = 1.0  # radius of the camera rig after normalisation (3DGS "cameras_extent")
    bounds_min: Tensor = field(default_factory=lambda: -torch.ones(3))  # (3,) for random init
    bounds_max: Tensor = field(default_factory=lambda: torch.ones(3))  # (3,)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # views outside ``train_indices`` (active-view studies): cameras WITHOUT images (``image=None``); their
    # images stay in a :class:`b3dgs.data.scene.CandidateStore` that only the study driver holds
    candidates: list[Camera] = field(default_factory=list)
    # training views held out for calibration (``data.calib_every``): with images, never trained on, never test
    calib: list[Camera] = field(default_factory=list)
