"""Top-level differentiable render of a Gaussian set from one camera.

Parameters follow the 3DGS convention: ``means`` (N,3), ``quats`` (N,4) wxyz (unnormalised),
``scales`` (N,3) log-scales, ``opacities`` (N,) logits, ``sh0`` (N,1,3), ``shN`` (N,B-1,3).
Any of them may carry a leading sample dimension S; the others are broadcast. Samples share
one tile binning (union of their screen footprints), so S samples cost far less than S renders.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Optional

import torch
from torch import Tensor

from b3dgs.render.projection import covariance_3d, eval_sh, project
from b3dgs.render.rasterize import TileBins, bin_gaussians, rasterize
from b3dgs.types import Camera

PARAM_NAMES = ("means", "quats", "scales", "opacities", "sh0", "shN")
_PARAM_TAIL = {"means": (3,), "quats": (4,), "scales": (3,), "opacities": (), "sh0": (1, 3)}


@dataclass
class RenderOutput:
    rgb: Tensor  # (S, H, W, 3) or (H, W, 3)
    alpha: Tensor  # (S, H, W) or (H, W)
    depth: Tensor  # expected depth sum_i w_i z_i / alpha, (S, H, W) or (H, W)
    means2d: Tensor  # (S, N, 2); retains grad when requested (densification statistics)
    radii: Tensor  # (S, N) screen radii in pixels, 0 where culled
    depths: Tensor  # (S, N) camera-space depth
    bins: TileBins
    weight_sum: Optional[Tensor] = None  # (S, N) sum_p w_kp
    weight_sq_sum: Optional[Tensor] = None  # (S, N) sum_p w_kp^2

    @property
    def visible(self) -> Tensor:
        return self.radii > 0


def _check_params(params: Mapping[str, Tensor]) -> tuple[int, int, bool]:
    required = ("means", "opacities", "sh0") + (() if "covars" in params else ("quats", "scales"))
    missing = [k for k in required if k not in params]
    if missing:
        raise ValueError(f"render: missing Gaussian parameters {missing}")
    means = params["means"]
    n = means.shape[-2]
    s, batched = 1, False
    for name in PARAM_NAMES + ("covars",):
        if name not in params:
            continue
        t = params[name]
        if name in ("shN", "covars"):
            tail_dims = 2
            ok = t.dim() in (3, 4) and t.shape[-1] == 3 and (name == "shN" or t.shape[-2] == 3)
        else:
            tail = _PARAM_TAIL[name]
            tail_dims = len(tail)
            ok = t.dim() in (1 + tail_dims, 2 + tail_dims) and tuple(t.shape[t.dim() - tail_dims:]) == tail
        if not ok or t.shape[t.dim() - tail_dims - 1] != n:
            raise ValueError(f"render: parameter {name!r} has shape {tuple(t.shape)}; expected ([S,] {n}, ...)")
        if t.dim() == 2 + tail_dims:
            if s != 1 and t.shape[0] not in (1, s):
                raise ValueError(f"render: inconsistent sample dimension for {name!r}: {t.shape[0]} vs {s}")
            s, batched = max(s, t.shape[0]), True
    return s, n, batched


def render(
    params: Mapping[str, Tensor],
    camera: Camera,
    sh_degree: int = 3,
    background: Optional[Tensor] = None,
    backend: str = "cpu",
    return_weights: bool = False,
    retain_means2d_grad: bool = False,
    near: float = 0.01,
) -> RenderOutput:
    """Render Gaussians (optionally S parameter samples at once) from ``camera``.

    ``params`` may hold ``covars`` (…, N, 3, 3) instead of ``quats``/``scales`` (posterior samples of Σ).
    """
    S, N, batched = _check_params(params)
    means = params["means"]
    dtype = means.dtype

    def expand(t: Tensor, tail: int) -> Tensor:
        return t.expand((S,) + t.shape[-tail - 1:]) if t.dim() == tail + 2 else t.unsqueeze(0).expand((S,) + t.shape)

    means_s = expand(means, 1)
    cov3d = params["covars"] if "covars" in params else covariance_3d(params["quats"], params["scales"])
    cov_s = expand(cov3d, 2)
    proj = project(means_s, cov_s, camera.viewmat.to(dtype), camera.K.to(dtype), camera.width, camera.height, near)
    means2d = proj.means2d
    if retain_means2d_grad and means2d.requires_grad:
        means2d.retain_grad()

    # View-dependent colour from SH, evaluated at the (possibly sampled) means.
    deg = sh_degree
    sh0 = params["sh0"]
    shN = params.get("shN")
    if shN is not None and shN.shape[-2] > 0 and deg > 0:
        nb = (deg + 1) ** 2
        if shN.shape[-2] + 1 < nb:
            deg = int((shN.shape[-2] + 1) ** 0.5) - 1
            nb = (deg + 1) ** 2
        coeffs = torch.cat([expand(sh0, 2), expand(shN, 2)[..., : nb - 1, :]], dim=-2)
        cam_center = camera.center.to(dtype)
        dirs = torch.nn.functional.normalize(means_s - cam_center, dim=-1)
        colors = eval_sh(deg, coeffs, dirs)
    else:
        colors = eval_sh(0, expand(sh0, 2), means_s)
    colors = torch.clamp_min(colors + 0.5, 0.0)
    # a Gaussian culled in one sample (radius 0) stays invisible there, even though the shared
    # binning (union over samples) lists it
    opac = expand(torch.sigmoid(params["opacities"]), 0) * (proj.radii > 0)

    if background is None:
        background = torch.zeros(3, dtype=dtype)
    with torch.no_grad():
        bins = bin_gaussians(means2d.detach(), proj.radii, proj.depths.detach(), camera.width, camera.height)
    out = rasterize(
        means2d, proj.conics, colors, opac, proj.depths, bins, camera.width, camera.height,
        background.to(dtype), backend=backend, return_weights=return_weights,
    )
    depth = out.depth / out.alpha.clamp_min(1e-6)
    rgb, alpha = out.rgb, out.alpha
    if not batched:
        rgb, alpha, depth = rgb[0], alpha[0], depth[0]
    return RenderOutput(
        rgb=rgb, alpha=alpha, depth=depth, means2d=means2d, radii=proj.radii, depths=proj.depths, bins=bins,
        weight_sum=out.weight_sum, weight_sq_sum=out.weight_sq_sum,
    )
