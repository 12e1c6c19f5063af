"""Per-Gaussian preprocessing: EWA projection, SH colour, opacity and binning extents, both backends.

``"torch"`` composes the reference functions of :mod:`b3dgs.render.projection` (autograd);
``"cpu"`` runs one fused C++/OpenMP pass with a hand-written backward (``csrc/preprocess.h``).
Inputs may carry a leading sample dimension S (or 1, shared by all samples); outputs are (S, N, ...).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Optional

import torch
from torch import Tensor

from b3dgs.errors import B3dgsError
from b3dgs.numerics import guard, guard_deferred, guard_where
from b3dgs.render.projection import covariance_3d, eval_sh, project
from b3dgs.types import Camera

MIN_ALPHA = 1.0 / 255.0
# Binning margin: alpha >= 1/255 needs d^T Sigma^-1 d <= 2 ln(255 o); the extent uses 2 ln(255 o) + this.
_K2_MARGIN = 2e-3
_COV6_ROWS = (0, 0, 0, 1, 1, 2)
_COV6_COLS = (0, 1, 2, 1, 2, 2)
# Quaternions whose squared norm would under- or overflow (largest |component| outside [_QUAT_LO,
# _QUAT_HI]) are divided by that component first: the rotation is unchanged, its norm computable.
_QUAT_LO, _QUAT_HI = 1e-15, 1e15


@dataclass
class Preprocessed:
    means2d: Tensor  # (S, N, 2) pixel coordinates
    conics: Tensor  # (S, N, 3) inverse 2D covariance (a, b, c)
    colors: Tensor  # (S, N, 3) SH colour + 0.5, clamped at 0
    opacities: Tensor  # (S, N) sigmoid(logit), 0 where culled
    depths: Tensor  # (S, N) camera-space z
    radii: Tensor  # (S, N) 3-sigma screen radius in pixels, 0 where culled
    extent: Tensor  # (S, N, 2) binning half-widths (x, y) in pixels: where alpha can reach 1/255


def effective_sh_degree(sh_degree: int, shN: Optional[Tensor]) -> int:
    """The SH degree actually evaluated: capped by the coefficients present (0 without shN)."""
    if shN is None or shN.shape[-2] == 0 or sh_degree <= 0:
        return 0
    return min(int(sh_degree), int((shN.shape[-2] + 1) ** 0.5) - 1)


@torch.no_grad()
def binning_extent(cov2d: Tensor, opacities: Tensor, radii: Tensor) -> Tensor:
    """(S, N, 2) half-widths of the region where ``o exp(-q/2)`` can reach 1/255, capped by the radius.

    The axis-aligned bounding box of the ellipse q <= 2 ln(255 o) has half-widths sqrt(k2 cov_xx) and
    sqrt(k2 cov_yy); a tile outside it gets nothing from the Gaussian, so binning with it instead of
    the 3-sigma square changes no pixel and drops about half of the pairs on trained scenes.
    """
    o = opacities.double()
    ok = (radii > 0) & (o >= MIN_ALPHA)
    k2 = 2.0 * torch.log(255.0 * o.clamp_min(MIN_ALPHA)) + _K2_MARGIN
    r = radii.double()
    ex = torch.minimum(r, torch.sqrt(k2 * cov2d[..., 0].double()) * (1.0 + 1e-6) + 1e-3)
    ey = torch.minimum(r, torch.sqrt(k2 * cov2d[..., 2].double()) * (1.0 + 1e-6) + 1e-3)
    ext = torch.stack([ex, ey], dim=-1)
    return torch.where(ok[..., None], ext, torch.zeros_like(ext)).to(radii.dtype)


def _guarded_quats(quats: Tensor) -> Tensor:
    """Quaternions whose norm the kernels can take: rescale rows of extreme norm (exact, counted as
    ``render.quat_rescale``); zero rows keep the kernels' floor max(|q|, 1e-12), i.e. the identity
    rotation, counted as ``render.quat_zero``."""
    with torch.no_grad():
        amax = quats.detach().abs().amax(-1, keepdim=True)
        zero = amax == 0
        extreme = ~zero & ((amax < _QUAT_LO) | (amax > _QUAT_HI))
    guard_deferred("render.quat_zero", zero)
    # normalize(q / m) = normalize(q) for any m > 0, so a detached m keeps the gradient exact
    return guard_where("render.quat_rescale", extreme,
                       lambda: quats / torch.where(extreme, amax, torch.ones_like(amax)), quats)


def scale_log_cap(camera: Camera, dtype: torch.dtype) -> float:
    """log_cap of :func:`_guarded_log_scales`: a log-scale above log(z) + log_cap is clamped there."""
    f = camera.focal_max()
    big = math.sqrt(torch.finfo(dtype).max) / 4.0
    return math.log(math.sqrt(big / 3.0) / (f + 1.3 * max(camera.width, camera.height)))


def _guarded_log_scales(params: Mapping[str, Tensor], camera: Camera, near: float) -> Tensor:
    """Log-scales capped where the 2-D covariance would overflow the dtype (counted as ``render.scale_clamp``).

    With |tx/z| clamped to the view (3DGS), the Jacobian's rows have norm <= (f + 1.3 max(W, H)) / z, so
    a scale s <= z sqrt(A / 3) / (f + 1.3 max(W, H)), with A = sqrt(dtype max) / 4, keeps the entries of
    the 2-D covariance below A and their determinant finite. Only Gaussians tens of orders of magnitude
    larger than their distance to the camera are touched; ordinary inputs pass unchanged.
    """
    log_scales, means = params["scales"], params["means"]
    with torch.no_grad():
        vm = camera.viewmat.to(means.device, means.dtype)
        z = (means.detach() @ vm[2, :3] + vm[2, 3]).clamp_min(near)  # ([S,] N)
        if z.dim() > log_scales.dim() - 1:
            z = z.amin(0)  # per-sample means, shared scales: the nearest sample bounds
        cap = (torch.log(z) + scale_log_cap(camera, log_scales.dtype)).unsqueeze(-1).to(log_scales.dtype)
        over = log_scales.detach() > cap
    return guard_where("render.scale_clamp", over, cap, log_scales)


def guarded_params(params: Mapping[str, Tensor], camera: Camera, near: float) -> Mapping[str, Tensor]:
    """``params`` with the counted guards of :func:`_guarded_quats` and :func:`_guarded_log_scales`
    applied (the same tensors where none fires); both backends render the result."""
    if "covars" in params:
        return params
    quats = _guarded_quats(params["quats"])
    scales = _guarded_log_scales(params, camera, near)
    if quats is params["quats"] and scales is params["scales"]:
        return params
    return dict(params, quats=quats, scales=scales)


def expand_samples(t: Tensor, S: int, tail: int) -> Tensor:
    """(…, N, *tail) with an optional sample dimension -> (S, N, *tail), a view (shared by both backends)."""
    return t.expand((S,) + t.shape[-tail - 1:]) if t.dim() == tail + 2 else t.unsqueeze(0).expand((S,) + t.shape)


def _preprocess_torch(params: Mapping[str, Tensor], camera: Camera, S: int, deg: int, near: float) -> Preprocessed:
    means = params["means"]
    dtype = means.dtype
    means_s = expand_samples(means, S, 1)
    cov3d = params["covars"] if "covars" in params else covariance_3d(params["quats"], params["scales"])
    dev = means.device
    proj = project(means_s, expand_samples(cov3d, S, 2), camera.viewmat.to(dev, dtype), camera.K.to(dev, dtype),
                   camera.width, camera.height, near)
    sh0 = params["sh0"]
    if deg > 0:
        nb = (deg + 1) ** 2
        coeffs = torch.cat([expand_samples(sh0, S, 2), expand_samples(params["shN"], S, 2)[..., : nb - 1, :]], dim=-2)
        dirs = torch.nn.functional.normalize(means_s - camera.center.to(dev, dtype), dim=-1)
        colors = eval_sh(deg, coeffs, dirs)
    else:
        colors = eval_sh(0, expand_samples(sh0, S, 2), means_s)
    colors = torch.clamp_min(colors + 0.5, 0.0)
    # a Gaussian culled in one sample (radius 0) stays invisible there, even though the shared
    # binning (union over samples) may list it
    opac = expand_samples(torch.sigmoid(params["opacities"]), S, 0) * (proj.radii > 0)
    extent = binning_extent(proj.cov2d.detach(), opac.detach(), proj.radii)
    return Preprocessed(proj.means2d, proj.conics, colors, opac, proj.depths, proj.radii, extent)


def _camera_args(camera: Camera, near: float) -> tuple:
    vm = camera.viewmat.double()[:3, :4].reshape(-1).tolist()
    K = camera.K.double()
    intr = [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]
    return vm, intr, camera.center.double().tolist(), int(camera.width), int(camera.height), float(near)


class _PreprocessCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, cov6, logits, sh0, shN, cam, degree, S, rot_mode, log_cap):
        from b3dgs.render._ext import load_extension

        ext = load_extension()
        outs = ext.preprocess_forward(means, quats, scales, cov6, logits, sh0, shN, *cam, degree, S, rot_mode,
                                      torch.get_num_threads(), log_cap)
        means2d, conics, colors, opac, depths, radii, extent, flags = outs
        ctx.cam, ctx.degree, ctx.S, ctx.rot_mode = cam, degree, S, rot_mode
        ctx.save_for_backward(means, quats, scales, cov6, logits, sh0, shN, radii)
        ctx.mark_non_differentiable(radii, extent, flags)
        return means2d, conics, colors, opac, depths, radii, extent, flags

    @staticmethod
    def backward(ctx, g_m2, g_con, g_col, g_op, g_z, _g_r, _g_e, _g_f):
        from b3dgs.render._ext import load_extension

        means, quats, scales, cov6, logits, sh0, shN, radii = ctx.saved_tensors
        S, N = radii.shape

        def grad(g, *tail):
            return torch.zeros((S, N) + tail, dtype=means.dtype) if g is None else g.contiguous()

        gm, gq, gs, gc, gl, g0, gN = load_extension().preprocess_backward(
            means, quats, scales, cov6, logits, sh0, shN, *ctx.cam, ctx.degree, S, ctx.rot_mode, radii,
            grad(g_m2, 2), grad(g_con, 3), grad(g_col, 3), grad(g_op), grad(g_z), torch.get_num_threads())
        n = ctx.needs_input_grad
        return (gm if n[0] else None, gq if n[1] else None, gs if n[2] else None, gc if n[3] else None,
                gl if n[4] else None, g0 if n[5] else None, gN if n[6] else None, None, None, None, None, None)


def _lead(t: Tensor, tail: int) -> Tensor:
    """(…, N, *tail) with an optional sample dimension -> contiguous (S or 1, N, *tail)."""
    t = t if t.dim() == tail + 2 else t.unsqueeze(0)
    return t.contiguous()


def _preprocess_cpu(params: Mapping[str, Tensor], camera: Camera, S: int, deg: int, near: float
                    ) -> tuple[Preprocessed, list[int]]:
    """The C++ pass and its guard flags (quaternion rows all zero, quaternion rows of extreme norm, log-scales
    that may need the overflow cap), detected inside the pass (``csrc/preprocess.h``)."""
    means = _lead(params["means"], 1)
    dtype = means.dtype
    empty = torch.zeros(0, dtype=dtype)
    rot_mode = "covars" not in params
    if rot_mode:
        quats, scales, cov6 = _lead(params["quats"], 1), _lead(params["scales"], 1), empty
    else:
        quats, scales, cov6 = empty, empty, _lead(params["covars"][..., list(_COV6_ROWS), list(_COV6_COLS)], 1)
    logits = _lead(params["opacities"], 0)
    sh0 = _lead(params["sh0"], 2).reshape(-1, means.shape[1], 3)
    shN = _lead(params["shN"], 2)[..., : (deg + 1) ** 2 - 1, :].contiguous() if deg > 0 else empty
    *outs, flags = _PreprocessCPU.apply(means, quats, scales, cov6, logits, sh0, shN, _camera_args(camera, near),
                                        deg, S, rot_mode, scale_log_cap(camera, dtype))
    return Preprocessed(*outs), flags.tolist()


_BACKENDS = {"cpu": _preprocess_cpu, "torch": _preprocess_torch}


def preprocess(params: Mapping[str, Tensor], camera: Camera, S: int, sh_degree: int = 3, backend: str = "cpu",
               near: float = 0.01) -> Preprocessed:
    """Project, colour and bound every Gaussian for ``camera`` (validated ``params``; S samples).

    Both backends render :func:`guarded_params`. The C++ backend first renders ``params`` as they are and
    detects inside its pass whether a guard would fire; only then (rare: degenerate inputs) it applies the
    guards and renders again, so ordinary steps make no separate passes over the parameters.
    """
    fn = _BACKENDS.get(backend)
    if fn is None:
        raise B3dgsError(f"preprocess: backend must be one of {sorted(_BACKENDS)}, got {backend!r}",
                         fix=f"pass backend= one of {sorted(_BACKENDS)} (renderer=cpu and renderer=torch choose it)")
    deg = effective_sh_degree(sh_degree, params.get("shN"))
    if backend == "cpu":
        pre, (quat_zero, quat_extreme, scale_over) = _preprocess_cpu(params, camera, S, deg, near)
        if not (quat_extreme or scale_over):
            guard("render.quat_zero", quat_zero)
            return pre
        return _preprocess_cpu(guarded_params(params, camera, near), camera, S, deg, near)[0]
    return fn(guarded_params(params, camera, near), camera, S, deg, near)
