"""Differentiable EWA projection of 3D Gaussians and spherical-harmonic colours (pure torch).

Shared by both rasterizer backends. Every function accepts an optional leading sample dimension S
(posterior samples render in one call); per-Gaussian tensors are then (S, N, ...).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from b3dgs.errors import B3dgsError

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
    """Σ = R diag(s²) Rᵀ from quaternions and log-scales; (…, 3, 3). Elementwise (no tiny batched matmuls)."""
    R = quat_to_rotmat(quats)
    M = R * torch.exp(log_scales).unsqueeze(-2)  # columns scaled: M = R diag(s)
    return (M.unsqueeze(-2) * M.unsqueeze(-3)).sum(-1)  # Σ_ik = Σ_j M_ij M_kj


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Real SH basis values of degree 0..3 at unit directions (…, 3) -> (…, (degree+1)²)."""
    if degree < 0 or degree > 3:
        raise B3dgsError(f"SH degree must be in 0..3, got {degree}",
                         fix="pass an SH degree of 0, 1, 2 or 3 (model.sh_degree for b3dgs-train)")
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * xz, SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4 * zz - xx - yy),
                SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy), SH_C3[5] * z * (xx - yy),
                SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, dim=-1)


def eval_sh(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Evaluate real SH of degree 0..3. coeffs (…, B, 3) with B >= (degree+1)², dirs (…, 3) unit."""
    nb = (degree + 1) ** 2
    if coeffs.shape[-2] < nb:
        raise B3dgsError(f"eval_sh: degree {degree} needs {nb} coefficients, got {coeffs.shape[-2]}",
                         fix=f"pass coeffs with at least {nb} SH coefficients per Gaussian (sh0 and shN "
                             "concatenated), or a lower degree")
    if degree == 0:
        return SH_C0 * coeffs[..., 0, :]
    basis = sh_basis(degree, dirs.detach() if not dirs.requires_grad else dirs)
    return (basis.unsqueeze(-1) * coeffs[..., :nb, :]).sum(-2)


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    return (rgb - 0.5) / SH_C0


@dataclass
class Projection:
    means2d: Tensor  # (S, N, 2) pixel coordinates
    conics: Tensor  # (S, N, 3) inverse 2D covariance (a, b, c)
    depths: Tensor  # (S, N) camera-space z
    radii: Tensor  # (S, N) float, 0 where culled
    cov2d: Tensor  # (S, N, 3) 2D covariance (xx, xy, yy) incl. blur


def project(means: Tensor, cov3d: Tensor, viewmat: Tensor, K: Tensor, width: int, height: int, near: float = 0.01,
            blur: float = BLUR_PX) -> Projection:
    """EWA splatting projection (Zwicker et al. 2001) of (S, N, 3) means and (S, N, 3, 3) covariances."""
    R = viewmat[:3, :3].to(means.dtype)
    t = viewmat[:3, 3].to(means.dtype)
    p = means @ R.T + t
    x, y, z = p.unbind(-1)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    valid = z > near
    zs = torch.where(valid, z, torch.ones_like(z))
    # Clamp the Jacobian's linearisation point to the field of view widened by 0.3 tan(fov/2) = 0.15 W/fx on each
    # side (3DGS: |x/z| <= 1.3 tan(fov/2); gsplat: the same around the principal point).
    margin_x, margin_y = 0.15 * width / fx, 0.15 * height / fy
    tx = zs * torch.clamp(x / zs, -(cx / fx + margin_x), (width - cx) / fx + margin_x)
    ty = zs * torch.clamp(y / zs, -(cy / fy + margin_y), (height - cy) / fy + margin_y)
    # J = [[fx/z, 0, -fx tx/z²], [0, fy/z, -fy ty/z²]]; cov2d = J (R Σ Rᵀ) Jᵀ written out elementwise
    Rc = R.to(cov3d.dtype)
    cov_cam = torch.einsum("ij,...jk,lk->...il", Rc, cov3d, Rc)
    ja, jb = fx / zs, -fx * tx / (zs * zs)
    jc, jd = fy / zs, -fy * ty / (zs * zs)
    c00, c01, c02 = cov_cam[..., 0, 0], cov_cam[..., 0, 1], cov_cam[..., 0, 2]
    c11, c12, c22 = cov_cam[..., 1, 1], cov_cam[..., 1, 2], cov_cam[..., 2, 2]
    a = ja * ja * c00 + 2 * ja * jb * c02 + jb * jb * c22 + blur
    b = ja * jc * c01 + ja * jd * c02 + jb * jc * c12 + jb * jd * c22
    c = jc * jc * c11 + 2 * jc * jd * c12 + jd * jd * c22 + blur
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
