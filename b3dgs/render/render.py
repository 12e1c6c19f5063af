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

from b3dgs.errors import B3dgsError
from b3dgs.render.preprocess import preprocess
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
    bins: Optional[TileBins]  # our tile lists (None for backends that keep their own)
    weight_sum: Optional[Tensor] = None  # (S, N) sum_p w_kp
    weight_sq_sum: Optional[Tensor] = None  # (S, N) sum_p w_kp^2
    means2d_source: Optional[Tensor] = None  # the tensor the backend differentiates (when not means2d itself)

    @property
    def visible(self) -> Tensor:
        return self.radii > 0

    @property
    def means2d_grad(self) -> Optional[Tensor]:
        """d loss / d means2d as (S, N, 2) after backward (with ``retain_means2d_grad``), else None."""
        src = self.means2d if self.means2d_source is None else self.means2d_source
        return None if src.grad is None else src.grad.reshape(self.means2d.shape)


def check_render_params(params: Mapping[str, Tensor]) -> tuple[int, int, bool]:
    """Validate parameter shapes; returns (S, N, batched)."""
    required = ("means", "opacities", "sh0") + (() if "covars" in params else ("quats", "scales"))
    missing = [k for k in required if k not in params]
    if missing:
        raise B3dgsError(f"render: missing Gaussian parameters {missing}",
                         fix="pass every Gaussian parameter: means, opacities, sh0, and quats + scales (or covars), "
                             "e.g. module.params()")
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
            raise B3dgsError(f"render: parameter {name!r} has shape {tuple(t.shape)}; expected ([S,] {n}, ...)",
                             fix=f"pass {name!r} with one row per Gaussian ({n}), optionally after a leading sample "
                                 "dimension S")
        if t.dim() == 2 + tail_dims:
            if s != 1 and t.shape[0] not in (1, s):
                raise B3dgsError(f"render: inconsistent sample dimension for {name!r}: {t.shape[0]} vs {s}",
                                 fix=f"give {name!r} the same leading sample dimension S as the other sampled "
                                     "parameters (or 1 to share it)")
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
    S, N, batched = check_render_params(params)
    dtype = params["means"].dtype
    pre = preprocess(params, camera, S, sh_degree, backend, near)
    means2d = pre.means2d
    if retain_means2d_grad and means2d.requires_grad:
        means2d.retain_grad()
    if background is None:
        background = torch.zeros(3, dtype=dtype, device=means2d.device)
    bins = bin_gaussians(means2d.detach(), pre.radii, pre.depths.detach(), camera.width, camera.height,
                         extent=pre.extent, backend=backend)
    out = rasterize(
        means2d, pre.conics, pre.colors, pre.opacities, pre.depths, bins, camera.width, camera.height,
        background.to(means2d.device, dtype), backend=backend, return_weights=return_weights,
    )
    depth = out.depth / out.alpha.clamp_min(1e-6)
    rgb, alpha = out.rgb, out.alpha
    if not batched:
        rgb, alpha, depth = rgb[0], alpha[0], depth[0]
    return RenderOutput(
        rgb=rgb, alpha=alpha, depth=depth, means2d=means2d, radii=pre.radii, depths=pre.depths, bins=bins,
        weight_sum=out.weight_sum, weight_sq_sum=out.weight_sq_sum,
    )
