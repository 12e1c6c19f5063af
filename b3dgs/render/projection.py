"""Differentiable EWA projection of 3D Gaussians and spherical-harmonic colours (pure torch).

Shared by both rasterizer backends. Every function accepts an optional leading sample dimension S
(posterior samples render in one call); per-Gaussian tensors are then (S, N, ...).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)

BLUR_PX = 0.3  # low-pass filter added to the 2D covariance (3DGS)
EXTENT_SIGMA = 3.0  # screen-space radius = 3 sigma of the major axis


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """(…, 4) quaternions (w, x, y, z), normalised here, to (…, 3, 3) rotation matrices."""
    q = F.normalize(quats, dim=-1)
    w, x, y, z = q.unbind(-1)
    r = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return r.reshape(q.shape[:-1] + (3, 3))


def covariance_3d(quats: Tensor, log_scales: Tensor) -> Tensor:
    """Σ = R diag(s²) Rᵀ from quaternions and log-scales; (…, 3, 3)."""
    R = quat_to_rotmat(quats)
    M = R * torch.exp(log_scales).unsqueeze(-2)
    return M @ M.transpose(-1, -2)


def eval_sh(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Evaluate real SH of degree 0..3. coeffs (…, B, 3) with B >= (degree+1)², dirs (…, 3) unit."""
    if degree < 0 or degree > 3:
        raise ValueError(f"SH degree must be in 0..3, got {degree}")
    out = SH_C0 * coeffs[..., 0, :]
    if degree == 0:
        return out
    x, y, z = dirs[..., 0:1], dirs[..., 1:2], dirs[..., 2:3]
    out = out - SH_C1 * y * coeffs[..., 1, :] + SH_C1 * z * coeffs[..., 2, :] - SH_C1 * x * coeffs[..., 3, :]
    if degree == 1:
        return out
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    out = (
        out
        + SH_C2[0] * xy * coeffs[..., 4, :]
        + SH_C2[1] * yz * coeffs[..., 5, :]
        + SH_C2[2] * (2 * zz - xx - yy) * coeffs[..., 6, :]
        + SH_C2[3] * xz * coeffs[..., 7, :]
        + SH_C2[4] * (xx - yy) * coeffs[..., 8, :]
    )
    if degree == 2:
        return out
    out = (
        out
        + SH_C3[0] * y * (3 * xx - yy) * coeffs[..., 9, :]
        + SH_C3[1] * xy * z * coeffs[..., 10, :]
        + SH_C3[2] * y * (4 * zz - xx - yy) * coeffs[..., 11, :]
        + SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * coeffs[..., 12, :]
        + SH_C3[4] * x * (4 * zz - xx - yy) * coeffs[..., 13, :]
        + SH_C3[5] * z * (xx - yy) * coeffs[..., 14, :]
        + SH_C3[6] * x * (xx - 3 * yy) * coeffs[..., 15, :]
    )
    return out


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    return (rgb - 0.5) / SH_C0


def sh0_to_rgb(sh0: Tensor) -> Tensor:
    return sh0 * SH_C0 + 0.5


@dataclass
class Projection:
    means2d: Tensor  # (S, N, 2) pixel coordinates
    conics: Tensor  # (S, N, 3) inverse 2D covariance (a, b, c)
    depths: Tensor  # (S, N) camera-space z
    radii: Tensor  # (S, N) float, 0 where culled
    cov2d: Tensor  # (S, N, 3) 2D covariance (xx, xy, yy) incl. blur


def project(
    means: Tensor,
    cov3d: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near: float = 0.01,
    blur: float = BLUR_PX,
) -> Projection:
    """EWA splatting projection (Zwicker et al. 2001) of (S, N, 3) means and (S, N, 3, 3) covariances."""
    R = viewmat[:3, :3].to(means.dtype)
    t = viewmat[:3, 3].to(means.dtype)
    p = means @ R.T + t
    x, y, z = p.unbind(-1)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    valid = z > near
    zs = torch.where(valid, z, torch.ones_like(z))
    # Clamp the Jacobian's linearisation point to the field of view plus a 30% margin, as in 3DGS.
    margin_x, margin_y = 0.3 * width / fx, 0.3 * height / fy
    tx = zs * torch.clamp(x / zs, -(cx / fx + margin_x), (width - cx) / fx + margin_x)
    ty = zs * torch.clamp(y / zs, -(cy / fy + margin_y), (height - cy) / fy + margin_y)
    zero = torch.zeros_like(zs)
    J = torch.stack(
        [fx / zs, zero, -fx * tx / (zs * zs), zero, fy / zs, -fy * ty / (zs * zs)], dim=-1
    ).reshape(zs.shape + (2, 3))
    cov_cam = R @ cov3d @ R.T
    cov2 = J @ cov_cam @ J.transpose(-1, -2)
    a = cov2[..., 0, 0] + blur
    b = cov2[..., 0, 1]
    c = cov2[..., 1, 1] + blur
    det = a * c - b * b
    valid = valid & (det > 0)
    det_s = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], dim=-1)
    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], dim=-1)
    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
        radii = torch.ceil(EXTENT_SIGMA * torch.sqrt(lam))
        mx, my = means2d[..., 0], means2d[..., 1]
        onscreen = (mx + radii > 0) & (mx - radii < width) & (my + radii > 0) & (my - radii < height)
        radii = torch.where(valid & onscreen & torch.isfinite(radii), radii, torch.zeros_like(radii))
    return Projection(means2d, conics, z, radii, torch.stack([a, b, c], dim=-1))
