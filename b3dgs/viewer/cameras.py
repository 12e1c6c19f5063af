"""The browser's camera as a b3dgs :class:`~b3dgs.types.Camera` and back.

viser's cameras follow OpenCV (+x right, +y down, +z forward) like b3dgs: a pose is the camera-to-world
rotation ``wxyz`` (a unit quaternion) and the centre ``position``; ``fov`` is the vertical field of view.
The viewer renders a centred pinhole with square pixels at the canvas's aspect ratio.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from b3dgs.types import Camera, fit_size

__all__ = ["camera_pose", "fov_y", "mat_to_wxyz", "render_size", "view_camera", "wxyz_to_mat"]


def wxyz_to_mat(wxyz) -> np.ndarray:
    """(3, 3) rotation of a quaternion (w, x, y, z) (normalised first)."""
    q = np.asarray(wxyz, dtype=np.float64)
    return Rotation.from_quat(np.roll(q, -1)).as_matrix()  # scipy's order is (x, y, z, w)


def mat_to_wxyz(R) -> np.ndarray:
    """Unit quaternion (w, x, y, z) with w >= 0 of a rotation matrix."""
    q = np.roll(Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat(), 1)
    return -q if q[0] < 0 else q


def fov_y(camera: Camera) -> float:
    """Vertical field of view (radians) of a b3dgs camera."""
    return 2.0 * math.atan(0.5 * camera.height / float(camera.K[1, 1]))


def camera_pose(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz, position) of a b3dgs camera in viser's convention (camera-to-world)."""
    c2w = camera.camtoworld.detach().cpu().double().numpy()
    return mat_to_wxyz(c2w[:3, :3]), c2w[:3, 3].copy()


def render_size(aspect: float, max_side: int) -> tuple[int, int]:
    """(width, height) with the longer side ``max_side`` px and the given width / height ratio."""
    if not (aspect > 0 and math.isfinite(aspect)):
        aspect = 1.0
    return fit_size(aspect, 1.0, max(int(max_side), 8), upscale=True, min_side=8)


def view_camera(wxyz, position, fov: float, width: int, height: int, name: str = "viewer") -> Camera:
    """A centred pinhole b3dgs camera (square pixels) at a viser pose with vertical field of view ``fov``."""
    R = wxyz_to_mat(wxyz)
    t = np.asarray(position, dtype=np.float64)
    view = np.eye(4)
    view[:3, :3] = R.T
    view[:3, 3] = -R.T @ t
    f = 0.5 * height / math.tan(0.5 * float(fov))
    K = torch.tensor([[f, 0.0, 0.5 * width], [0.0, f, 0.5 * height], [0.0, 0.0, 1.0]], dtype=torch.float32)
    return Camera(name=name, K=K, viewmat=torch.from_numpy(view).float(), width=int(width), height=int(height))
