"""gsplat (CUDA) behind our render contract, and per-Gaussian weight sums from a pixel-pair list.

gsplat 1.5.3's ``rasterization`` takes leading batch dimensions, so the S samples of a batched
render (posterior draws, jitter) are one call with batch shape (S,) and one camera. We call it with
``packed=False`` so that ``radii``/``means2d`` stay (…, C, N, …) and line up with our (S, N) layout.

gsplat does not return Σ_p w_kp and Σ_p w_kp²; :func:`weight_sums` computes them from the
(Gaussian, pixel) pairs that ``rasterize_to_indices_in_range`` lists front to back, with the same
α rule as gsplat's compositing. It is plain PyTorch and runs only when a block asks for weights.

Adapted here to our contract (each fix tested on the CPU emulation of gsplat's kernels, ``tests/gsplat_cpu.py``):
near plane (gsplat culls z < near, ours z <= near: we pass the next float32 above ``near``); zero quaternions
(replaced by (1, 0, 0, 0), their gradient then 0); culled Gaussians (``means2d``/``depths``/radius returned as 0, not
left unwritten); the Jacobian clamp (gsplat's 0.15·W/fx margin in every backend). What is left as gsplat has it
(radii, α cap 0.999, termination, the ``covars=`` gradient on the upper triangle) is in docs/design.md, "Renderers".
"""
from __future__ import annotations

import functools
import sys
from typing import Mapping, Optional

import torch
from torch import Tensor

from b3dgs.errors import B3dgsError
from b3dgs.render.preprocess import effective_sh_degree, expand_samples, guarded_params
from b3dgs.render.render import RenderOutput, check_render_params
from b3dgs.types import Camera

GSPLAT_MAX_ALPHA = 0.999
_ALL_BATCHES = 1 << 30  # "every batch of every tile" for rasterize_to_indices_in_range (a uint32)


def weight_sums(gauss_ids: Tensor, pixel_ids: Tensor, image_ids: Tensor, means2d: Tensor, conics: Tensor,
                opacities: Tensor, width: int, height: int, max_alpha: float = GSPLAT_MAX_ALPHA) -> tuple[Tensor, Tensor]:
    """Σ_p w_kp and Σ_p w_kp² per image and Gaussian, from the composited (Gaussian, pixel) pairs.

    gauss_ids, pixel_ids (row-major in the image), image_ids: (M,) pairs grouped by pixel (as gsplat lists them),
    front to back within each pixel; means2d (I, N, 2), conics (I, N, 3), opacities (I, N). w = α·T with α = min(max_alpha,
    o·exp(-q/2)) at the pixel centre and T the product of (1 - α) of the pixel's earlier pairs
    (a segmented product, taken in log space in float64). Returns two (I, N) float64 tensors.
    """
    I, N = opacities.shape
    if means2d.shape != (I, N, 2) or conics.shape != (I, N, 3):
        raise B3dgsError(f"weight_sums: means2d {tuple(means2d.shape)} / conics {tuple(conics.shape)} do not "
                         f"match opacities (I, N) = ({I}, {N})",
                         fix="pass means2d (I, N, 2), conics (I, N, 3) and opacities (I, N) from the same projection "
                             "of N Gaussians into I cameras")
    dev = opacities.device
    wsum = torch.zeros(I * N, dtype=torch.float64, device=dev)
    wsq = torch.zeros(I * N, dtype=torch.float64, device=dev)
    M = int(gauss_ids.numel())
    if M == 0:
        return wsum.view(I, N), wsq.view(I, N)
    # gsplat's kernel writes each pixel's pairs contiguously, front to back, at the pixel's running offset in
    # (image, pixel) order (rasterize_to_indices_3dgs: ``chunk_starts[pix_id] + cnt``), and so does the test suite's
    # emulation: the pairs are already grouped by pixel, so no sort is needed, only the group starts
    pix_key = image_ids.long() * (width * height) + pixel_ids.long()
    flat = image_ids.long() * N + gauss_ids.long()
    pid = pixel_ids.long()
    # one gather of the pairs' Gaussian data in the inputs' dtype (float32 from gsplat), widened after it: the same
    # values as widening first, with half the bytes gathered
    dt = torch.promote_types(torch.promote_types(means2d.dtype, conics.dtype), opacities.dtype)
    tab = torch.cat([means2d.detach().reshape(-1, 2).to(dt), conics.detach().reshape(-1, 3).to(dt),
                     opacities.detach().reshape(-1, 1).to(dt)], dim=-1)
    g = tab.index_select(0, flat).double()
    m, c, o = g[:, :2], g[:, 2:5], g[:, 5]
    dx = m[:, 0] - ((pid % width).double() + 0.5)
    dy = m[:, 1] - (torch.div(pid, width, rounding_mode="floor").double() + 0.5)
    sigma = 0.5 * (c[:, 0] * dx * dx + c[:, 2] * dy * dy) + c[:, 1] * dx * dy
    alpha = torch.clamp(o * torch.exp(-sigma), max=max_alpha)
    log_keep = torch.log1p(-alpha)
    incl = torch.cumsum(log_keep, 0)
    excl = incl - log_keep
    # each pair's group start: the smallest pair index of its pixel (an int64 atomic min per pixel; the scan with
    # indices that torch.cummax runs took 8 ms of a 27 ms DPMM step on an H200, bench/results/device_h200.md)
    idx = torch.arange(M, device=dev)
    first = torch.full((I * width * height,), M, dtype=torch.long, device=dev).scatter_reduce_(0, pix_key, idx, "amin")
    seg_first = first[pix_key]
    w = alpha * torch.exp(excl - excl[seg_first])  # T before this pair, within its pixel
    wsum.index_add_(0, flat, w)
    wsq.index_add_(0, flat, w * w)
    return wsum.view(I, N), wsq.view(I, N)


@functools.lru_cache(maxsize=64)
def _near_plane(near: float) -> float:
    """gsplat culls ``z < near_plane``, our backends ``z <= near`` (in float32): the next float32 above ``near``
    makes gsplat cull exactly what ours cull."""
    n32 = torch.tensor(near, dtype=torch.float32)
    return float(torch.nextafter(n32, torch.tensor(float("inf"))))


def _identity_for_zero(quats: Tensor) -> Tensor:
    """Zero quaternions -> (1, 0, 0, 0): our contract renders them with the identity rotation (gsplat's
    unfloored rsqrt would make them NaN and cull them). Their quaternion gradient is zero here."""
    ident = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=quats.dtype, device=quats.device)
    return torch.where((quats == 0).all(-1, keepdim=True), ident, quats)


def gsplat_emulated() -> bool:
    """Whether gsplat's compiled backend is the test suite's CPU emulation (``tests/gsplat_cpu.py``)."""
    backend = sys.modules.get("gsplat.cuda._backend")
    return bool(getattr(getattr(backend, "_C", None), "CPU_EMULATION", False))


def render_gsplat(params: Mapping[str, Tensor], camera: Camera, *, sh_degree: int = 3,
                  background: Optional[Tensor] = None, return_weights: bool = False,
                  retain_means2d_grad: bool = False, near: float = 0.01, tile_size: int = 16,
                  eps2d: float = 0.3) -> RenderOutput:
    """Render with ``gsplat.rasterization`` (CUDA, float32; or the test suite's CPU emulation); see the module
    docstring."""
    from gsplat import rasterization
    from gsplat.cuda._wrapper import rasterize_to_indices_in_range

    S, N, batched = check_render_params(params)
    params = guarded_params(params, camera, near)  # the same counted quaternion / scale guards as our backends
    means = expand_samples(params["means"], S, 1)
    dev, dtype = means.device, means.dtype
    if (dev.type != "cuda" and not (dev.type == "cpu" and gsplat_emulated())) or dtype != torch.float32:
        raise B3dgsError(f"renderer=gsplat needs float32 CUDA tensors, got {dtype} on {dev}",
                         "let the trainer move the model, or use renderer=torch on this device")
    deg = effective_sh_degree(sh_degree, params.get("shN"))
    sh = expand_samples(params["sh0"], S, 2)
    if deg > 0:
        sh = torch.cat([sh, expand_samples(params["shN"], S, 2)[..., : (deg + 1) ** 2 - 1, :]], dim=-2)
    if "covars" in params:
        quats = scales = None
        covars = expand_samples(params["covars"], S, 2)  # gsplat reads its upper triangle, like our C++ backend
    else:
        quats, covars = _identity_for_zero(expand_samples(params["quats"], S, 1)), None
        scales = torch.exp(expand_samples(params["scales"], S, 1))
    opac = torch.sigmoid(expand_samples(params["opacities"], S, 0))
    viewmats = camera.viewmat.to(dev, dtype).expand(S, 1, 4, 4)
    Ks = camera.K.to(dev, dtype).expand(S, 1, 3, 3)
    bg = torch.zeros(3, device=dev, dtype=dtype) if background is None else background.to(dev, dtype)
    W, H = int(camera.width), int(camera.height)
    img, alphas, meta = rasterization(
        means, quats, scales, opac, sh, viewmats, Ks, W, H, near_plane=_near_plane(near), eps2d=eps2d, sh_degree=deg,
        packed=False, tile_size=tile_size, backgrounds=bg.expand(S, 1, 3), render_mode="RGB+ED",
        covars=covars, rasterize_mode="classic")
    m2d = meta["means2d"]  # (S, 1, N, 2); its .grad is the densification statistic
    if retain_means2d_grad and m2d.requires_grad:
        m2d.retain_grad()
    radii = meta["radii"]
    radii = (radii.amax(-1) if radii.dim() == 4 else radii)[:, 0].to(dtype)  # (S, N) larger screen radius
    # gsplat leaves means2d / depths of culled Gaussians unwritten (at::empty): never return them
    vis = (meta["radii"] > 0).all(-1)[:, 0] if meta["radii"].dim() == 4 else (meta["radii"] > 0)[:, 0]
    radii = torch.where(vis, radii, torch.zeros_like(radii))
    means2d = torch.where(vis[..., None], m2d[:, 0], torch.zeros((), device=dev, dtype=dtype))
    depths = torch.where(vis, meta["depths"][:, 0], torch.zeros((), device=dev, dtype=dtype))
    wsum = wsq = None
    if return_weights:
        with torch.no_grad():
            gids, pids, iids = rasterize_to_indices_in_range(
                0, _ALL_BATCHES, torch.ones(S, 1, H, W, device=dev, dtype=dtype), m2d.detach(), meta["conics"],
                meta["opacities"], W, H, tile_size, meta["isect_offsets"], meta["flatten_ids"])
            ws, wq = weight_sums(gids, pids, iids, m2d.detach()[:, 0], meta["conics"][:, 0], meta["opacities"][:, 0],
                                 W, H)
            wsum, wsq = ws.to(dtype), wq.to(dtype)
    rgb, depth, alpha = img[:, 0, ..., :3], img[:, 0, ..., 3], alphas[:, 0, ..., 0]
    if not batched:
        rgb, alpha, depth = rgb[0], alpha[0], depth[0]
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, means2d=means2d, radii=radii, depths=depths,
                        bins=None, weight_sum=wsum, weight_sq_sum=wsq, means2d_source=m2d)
