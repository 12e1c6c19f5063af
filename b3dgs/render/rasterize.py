"""Tile rasterizer of 3D Gaussian splatting with two backends.

``bin_gaussians`` assigns 2D Gaussians to 16x16 screen tiles (shared by all S samples: the union
of their footprints, sorted by mean depth), and ``rasterize`` alpha-composites them front to back
with the standard 3DGS rules:

    pixel (px, py) has centre (px + 0.5, py + 0.5); walk the tile list with T = 1:
      d = mean - centre; power = -0.5 (a dx^2 + c dy^2) - b dx dy; skip if power > 0
      alpha = min(0.99, o exp(power)); skip if alpha < 1/255
      test_T = T (1 - alpha); stop if test_T < 1e-4 (not composited)
      w = alpha T; rgb += w colour; depth += w z; T = test_T
    rgb += T background; alpha_out = 1 - T

Backends: ``"torch"`` (pure PyTorch autograd, float32/float64, the gradcheck reference) and
``"cpu"`` (C++/OpenMP forward and backward kernels, deterministic gradient reductions).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from b3dgs.errors import B3dgsError

MIN_ALPHA = 1.0 / 255.0
MAX_ALPHA = 0.99
MIN_T = 1e-4
BACKENDS = ("cpu", "torch")
# Elements (samples x tiles x Gaussians x pixels) per chunk of the torch backend; ~20 such
# tensors are alive at once in the backward, i.e. ~0.6 GB in float64.
_TORCH_CHUNK_ELEMS = 1 << 22


@dataclass
class TileBins:
    tile_offsets: Tensor  # int64 (num_tiles + 1,), CSR offsets into flat_ids; tile t = ty * tiles_x + tx
    flat_ids: Tensor  # int64 (P,), Gaussian indices, front-to-back within each tile
    tiles_x: int
    tiles_y: int
    tile_size: int

    @property
    def num_pairs(self) -> int:
        return int(self.flat_ids.numel())

    @property
    def num_tiles(self) -> int:
        return self.tiles_x * self.tiles_y

    def tile_counts(self) -> Tensor:
        return self.tile_offsets[1:] - self.tile_offsets[:-1]


@dataclass
class RasterOutput:
    rgb: Tensor  # (S, H, W, 3) colour composited over the background
    alpha: Tensor  # (S, H, W) 1 - final transmittance
    depth: Tensor  # (S, H, W) sum_i w_i z_i (not normalised by alpha)
    weight_sum: Optional[Tensor] = None  # (S, N) sum over pixels of w_kp (detached)
    weight_sq_sum: Optional[Tensor] = None  # (S, N) sum over pixels of w_kp^2 (detached)
    n_contrib: Optional[Tensor] = None  # (S, H, W) int32, Gaussians composited per pixel


# ------------------------------------------------------------------------------------------ Binning
def _shape_str(t: Tensor) -> str:
    return str(tuple(t.shape))


@torch.no_grad()
def bin_gaussians(means2d: Tensor, radii: Tensor, depths: Tensor, width: int, height: int, tile_size: int = 16,
                  extent: Optional[Tensor] = None, backend: str = "torch") -> TileBins:
    """Shared tile binning of (S, N) projected Gaussians, sorted by tile, mean depth, then id.

    Gaussian k goes to every tile overlapping the union over samples with ``radii > 0`` of
    ``[x - ex, x + ex] x [y - ey, y + ey]`` (tiles floor((x - ex)/ts) .. ceil((x + ex)/ts) - 1,
    clamped), with (ex, ey) = ``extent`` (S, N, 2) or (r, r) without it. The depth key of a Gaussian
    is its mean depth over the samples where it is visible. ``backend="cpu"`` runs the same rule in
    C++ (a stable counting sort by tile over the depth order).
    """
    if means2d.dim() != 3 or means2d.shape[-1] != 2:
        raise B3dgsError(f"bin_gaussians: means2d must be (S, N, 2), got {_shape_str(means2d)}",
                         fix="pass means2d as the projected 2-D centres, a float tensor of shape (S, N, 2) "
                             "(b3dgs.render.projection's output)")
    S, N = means2d.shape[:2]
    for name, t in (("radii", radii), ("depths", depths)):
        if tuple(t.shape) != (S, N):
            raise B3dgsError(f"bin_gaussians: {name} must be (S, N) = ({S}, {N}), got {_shape_str(t)}",
                             fix=f"pass {name} with one entry per projected Gaussian, shape (S, N) like "
                                 "means2d[..., 0]")
    if width <= 0 or height <= 0 or tile_size <= 0:
        raise B3dgsError(f"bin_gaussians: bad width/height/tile_size {width}/{height}/{tile_size}",
                         fix="pass the image's width and height in pixels (> 0) and tile_size > 0, e.g. the default "
                             "16")
    if extent is None:
        extent = radii.detach()[..., None].expand(S, N, 2)
    elif tuple(extent.shape) != (S, N, 2):
        raise B3dgsError(f"bin_gaussians: extent must be (S, N, 2) = ({S}, {N}, 2), got {_shape_str(extent)}",
                         fix="pass extent as per-axis pixel half-extents of shape (S, N, 2), or extent=None to use "
                             "radii")
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    fn = _BIN_BACKENDS.get(backend)
    if fn is None:
        raise B3dgsError(f"bin_gaussians: backend must be one of {BACKENDS}, got {backend!r}",
                         fix=f"pass backend= one of {BACKENDS} (renderer=cpu uses cpu, renderer=torch uses torch)")
    return fn(means2d, radii, depths, extent, width, height, tile_size, tiles_x, tiles_y)


def _bin_cpu(means2d, radii, depths, extent, width, height, tile_size, tiles_x, tiles_y) -> TileBins:
    from b3dgs.render._ext import load_extension

    dtype = means2d.dtype
    offsets, flat_ids = load_extension().bin_tiles(
        means2d.detach().contiguous(), radii.detach().to(dtype).contiguous(),
        extent.detach().to(dtype).contiguous(), depths.detach().to(dtype).contiguous(),
        width, height, tile_size, torch.get_num_threads())
    return TileBins(offsets, flat_ids, tiles_x, tiles_y, tile_size)


def _bin_torch(means2d, radii, depths, extent, width, height, tile_size, tiles_x, tiles_y) -> TileBins:
    S, N = means2d.shape[:2]
    num_tiles = tiles_x * tiles_y
    dev = means2d.device
    m, r, d, e = (t.detach().double() for t in (means2d, radii, depths, extent))
    x, y, ex, ey = m[..., 0], m[..., 1], e[..., 0], e[..., 1]
    valid = (r > 0) & torch.isfinite(r) & torch.isfinite(x) & torch.isfinite(y) & torch.isfinite(d)
    reach = valid & (ex > 0) & (ey > 0)  # visible samples that can reach alpha 1/255
    inf = math.inf
    xmin = torch.where(reach, x - ex, inf).amin(0)
    xmax = torch.where(reach, x + ex, -inf).amax(0)
    ymin = torch.where(reach, y - ey, inf).amin(0)
    ymax = torch.where(reach, y + ey, -inf).amax(0)
    nvalid = valid.sum(0)
    vis = reach.any(0)
    zero = torch.zeros((), dtype=torch.float64, device=dev)
    xmin, xmax = torch.where(vis, xmin, zero), torch.where(vis, xmax, zero)
    ymin, ymax = torch.where(vis, ymin, zero), torch.where(vis, ymax, zero)
    tx0 = torch.floor(xmin / tile_size).clamp(0, tiles_x).long()
    tx1 = torch.ceil(xmax / tile_size).clamp(0, tiles_x).long()
    ty0 = torch.floor(ymin / tile_size).clamp(0, tiles_y).long()
    ty1 = torch.ceil(ymax / tile_size).clamp(0, tiles_y).long()
    wx = (tx1 - tx0).clamp_min(0)
    wy = (ty1 - ty0).clamp_min(0)
    counts = torch.where(vis, wx * wy, torch.zeros_like(wx))

    # Rank of every Gaussian by (mean depth over valid samples, id).
    dkey = torch.where(valid, d, zero).sum(0) / nvalid.clamp_min(1)
    order = torch.sort(dkey, stable=True).indices
    rank = torch.empty_like(order)
    rank[order] = torch.arange(N, dtype=torch.int64, device=dev)

    gid = torch.repeat_interleave(torch.arange(N, dtype=torch.int64, device=dev), counts)
    P = int(gid.numel())
    if P > 0:
        starts = torch.cumsum(counts, 0) - counts
        local = torch.arange(P, dtype=torch.int64, device=dev) - starts[gid]
        wxg = wx[gid]
        tile = (ty0[gid] + torch.div(local, wxg, rounding_mode="floor")) * tiles_x + tx0[gid] + local % wxg
        key = tile * max(N, 1) + rank[gid]
        key, perm = torch.sort(key)
        flat_ids = gid[perm]
        tile_counts = torch.bincount(tile, minlength=num_tiles)
    else:
        flat_ids = torch.zeros(0, dtype=torch.int64, device=dev)
        tile_counts = torch.zeros(num_tiles, dtype=torch.int64, device=dev)
    tile_offsets = torch.zeros(num_tiles + 1, dtype=torch.int64, device=dev)
    torch.cumsum(tile_counts, 0, out=tile_offsets[1:])
    return TileBins(tile_offsets, flat_ids, tiles_x, tiles_y, tile_size)


_BIN_BACKENDS = {"cpu": _bin_cpu, "torch": _bin_torch}


# --------------------------------------------------------------------------------- Input validation
def _check_inputs(means2d, conics, colors, opacities, depths, bins, width, height, background, backend):
    if backend not in BACKENDS:
        raise B3dgsError(f"rasterize: backend must be one of {BACKENDS}, got {backend!r}",
                         fix=f"pass backend= one of {BACKENDS} (renderer=cpu uses cpu, renderer=torch uses torch)")
    if not isinstance(means2d, Tensor) or means2d.dim() != 3 or means2d.shape[-1] != 2:
        raise B3dgsError(f"rasterize: means2d must be a (S, N, 2) tensor, got {_shape_str(means2d) if isinstance(means2d, Tensor) else type(means2d)}",
                         fix="pass means2d as the projected 2-D centres, a float tensor of shape (S, N, 2) "
                             "(b3dgs.render.projection's output)")
    S, N = means2d.shape[:2]
    dtype = means2d.dtype
    if dtype not in (torch.float32, torch.float64):
        raise B3dgsError(f"rasterize: means2d must be float32 or float64, got {dtype}",
                         fix="cast the inputs to float32 (or all to float64) before rasterize, e.g. means2d.float()")
    expected = {"conics": (conics, (S, N, 3)), "colors": (colors, (S, N, 3)),
                "opacities": (opacities, (S, N)), "depths": (depths, (S, N))}
    for name, (t, shape) in expected.items():
        if not isinstance(t, Tensor):
            raise B3dgsError(f"rasterize: {name} must be a tensor, got {type(t)}",
                             fix=f"pass {name} as a torch tensor (convert numpy arrays with torch.from_numpy)")
        if tuple(t.shape) != shape:
            raise B3dgsError(f"rasterize: {name} must have shape {shape}, got {_shape_str(t)}",
                             fix=f"pass {name} with shape {shape}: one row per Gaussian of means2d, S = number of "
                                 "cameras")
        if t.dtype != dtype:
            raise B3dgsError(f"rasterize: {name} has dtype {t.dtype}, expected {dtype} (same as means2d)",
                             fix=f"cast {name} to {dtype}, the dtype of means2d (e.g. {name}.to(means2d.dtype))")
    if not isinstance(background, Tensor) or tuple(background.shape) != (3,):
        raise B3dgsError(f"rasterize: background must be a (3,) tensor, got "
                         f"{_shape_str(background) if isinstance(background, Tensor) else type(background)}",
                         fix="pass background as a float tensor of 3 RGB values, e.g. torch.ones(3) for white")
    for name, t in (("means2d", means2d), ("conics", conics), ("colors", colors),
                    ("opacities", opacities), ("depths", depths), ("background", background)):
        need = _BACKEND_DEVICE_TYPE[backend] or means2d.device.type
        if t.device != means2d.device or t.device.type != need:
            raise B3dgsError(f"rasterize: {name} is on {t.device}; the {backend} backend needs every input on "
                             f"one {need} device",
                             fix=f"move every input to one {need} device (.to(means2d.device)); renderer.device_name "
                                 "picks it for b3dgs-train")
    # the C++ backend checks finiteness and Gaussian ids inside its own passes (_raise_bad_inputs)
    if backend != "cpu":
        _check_finite(means2d=means2d, conics=conics, colors=colors, opacities=opacities, depths=depths)
    _check_finite(background=background)
    if width <= 0 or height <= 0:
        raise B3dgsError(f"rasterize: width/height must be positive, got {width}x{height}",
                         fix="pass the image's width and height in pixels, both > 0 (camera.width, camera.height)")
    ts = bins.tile_size
    if bins.tiles_x != (width + ts - 1) // ts or bins.tiles_y != (height + ts - 1) // ts:
        raise B3dgsError(f"rasterize: bins ({bins.tiles_x}x{bins.tiles_y} tiles of {ts}) do not match "
                         f"the image size {width}x{height}",
                         fix="rebuild the bins with bin_gaussians(..., width, height) for this image size before "
                             "rasterize")
    if bins.tile_offsets.dtype != torch.int64 or tuple(bins.tile_offsets.shape) != (bins.num_tiles + 1,):
        raise B3dgsError(f"rasterize: bins.tile_offsets must be int64 ({bins.num_tiles + 1},), got "
                         f"{bins.tile_offsets.dtype} {_shape_str(bins.tile_offsets)}",
                         fix="pass the TileBins that bin_gaussians returned, unchanged")
    if bins.flat_ids.dtype != torch.int64 or bins.flat_ids.dim() != 1:
        raise B3dgsError(f"rasterize: bins.flat_ids must be int64 (P,), got {bins.flat_ids.dtype} "
                         f"{_shape_str(bins.flat_ids)}", fix="pass the TileBins that bin_gaussians returned, unchanged")
    P = bins.num_pairs
    if int(bins.tile_offsets[0]) != 0 or int(bins.tile_offsets[-1]) != P:
        raise B3dgsError("rasterize: bins.tile_offsets must start at 0 and end at len(flat_ids)",
                         fix="pass the TileBins that bin_gaussians returned, unchanged")
    if backend != "cpu" and P > 0 and (int(bins.flat_ids.min()) < 0 or int(bins.flat_ids.max()) >= N):
        _raise_stale_bins(N)


_NAN_FIX = ("the Gaussians hold NaN/Inf (training diverged): lower the learning rates (e.g. model.lr_means) or check "
            "the data")


def _check_finite(**tensors: Tensor) -> None:
    for name, t in tensors.items():
        if not bool(torch.isfinite(t.detach()).all()):
            raise B3dgsError(f"rasterize: {name} contains NaN or Inf", fix=_NAN_FIX)


def _raise_stale_bins(n: int) -> None:
    raise B3dgsError(f"rasterize: bins.flat_ids out of range for N={n} Gaussians (stale bins?)",
                     fix="rebuild the bins with bin_gaussians after the Gaussians were added or pruned, before "
                         "rasterize")


def _raise_bad_inputs(flags: Tensor, n: int, **tensors: Tensor) -> None:
    """The error for the C++ forward's in-kernel checks: ``flags`` = (non-finite entries, ids out of range)."""
    nonfinite, bad_ids = (int(v) for v in flags.tolist())
    if bad_ids:
        _raise_stale_bins(n)
    if nonfinite:
        _check_finite(**tensors)  # names the first tensor holding a NaN / Inf
        raise B3dgsError("rasterize: an input contains NaN or Inf", fix=_NAN_FIX)


# ----------------------------------------------------------------------------- Pure PyTorch backend
def _tile_pixel_centres(bins: TileBins, tiles: Tensor, width: int, height: int, dtype):
    ts = bins.tile_size
    local = torch.arange(ts * ts, device=tiles.device)
    lx, ly = local % ts, local // ts
    tx, ty = tiles % bins.tiles_x, tiles // bins.tiles_x
    px = tx[:, None] * ts + lx[None, :]  # (Tc, ts*ts)
    py = ty[:, None] * ts + ly[None, :]
    inside = (px < width) & (py < height)
    return px.to(dtype) + 0.5, py.to(dtype) + 0.5, inside


def _torch_chunk(mx, my, ca, cb, cc, op, col, z, valid, pxc, pyc, inside, want_weights: bool):
    """Composite one chunk: per-pair inputs (s, Tc, K[, 3]), pixel centres (Tc, Pix).

    Returns rgb (s, Tc, Pix, 3) without background, depth (s, Tc, Pix), final T (s, Tc, Pix),
    n_contrib (s, Tc, Pix) and, if requested, per-pair weight sums (s, Tc, K) x 2.
    """
    dx = mx[..., None] - pxc[None, :, None, :]  # (s, Tc, K, Pix)
    dy = my[..., None] - pyc[None, :, None, :]
    power = -0.5 * (ca[..., None] * dx * dx + cc[..., None] * dy * dy) - cb[..., None] * dx * dy
    raw = op[..., None] * torch.exp(torch.clamp(power, max=0.0))
    alpha = torch.clamp(raw, max=MAX_ALPHA)
    with torch.no_grad():
        ok = valid[..., None] & (power <= 0) & (alpha >= MIN_ALPHA)
        a0 = torch.where(ok, alpha, torch.zeros_like(alpha))
        # Stop rule: the inclusive transmittance is a non-increasing prefix product, so
        # "composite while T (1 - alpha) >= 1e-4" keeps exactly where the cumprod is >= 1e-4.
        keep = ok & (torch.cumprod(1.0 - a0, dim=-2) >= MIN_T)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    one_m = 1.0 - alpha
    K = alpha.shape[-2]
    if K > 0:
        T_excl = torch.cumprod(torch.cat([torch.ones_like(one_m[..., :1, :]), one_m[..., :-1, :]], dim=-2), dim=-2)
        T_final = T_excl[..., -1, :] * one_m[..., -1, :]
    else:
        T_excl = one_m
        T_final = torch.ones(alpha.shape[:-2] + alpha.shape[-1:], dtype=alpha.dtype, device=alpha.device)
    w = alpha * T_excl  # (s, Tc, K, Pix)
    rgb = torch.einsum("stkp,stkc->stpc", w, col)
    depth = torch.einsum("stkp,stk->stp", w, z)
    with torch.no_grad():
        n_contrib = keep.sum(-2, dtype=torch.int32)
        if want_weights:
            wd = w.detach() * inside[None, :, None, :]
            wsum = wd.sum(-1)
            wsq = (wd * wd).sum(-1)
        else:
            wsum = wsq = torch.zeros(0, dtype=alpha.dtype, device=alpha.device)
    return rgb, depth, T_final, n_contrib, wsum, wsq


def _plan_chunks(bins: TileBins, S: int, budget: int):
    """Groups of tiles (sorted by decreasing count) and sample ranges so chunks fit the budget."""
    counts = bins.tile_counts()
    order = torch.argsort(counts, descending=True, stable=True)
    cnt_sorted = counts[order].tolist()
    npix = bins.tile_size * bins.tile_size
    s_block = max(1, min(S, budget // max(1, max(cnt_sorted[0] if cnt_sorted else 1, 1) * npix)))
    chunks = []
    i = 0
    nt = len(cnt_sorted)
    while i < nt:
        kmax = max(cnt_sorted[i], 1)
        ntiles = max(1, budget // (s_block * kmax * npix))
        j = min(nt, i + ntiles)
        chunks.append((i, j, cnt_sorted[i]))
        i = j
    return order, chunks, s_block


def _rasterize_torch(means2d, conics, colors, opacities, depths, bins, width, height, background,
                     return_weights):
    S, N = means2d.shape[:2]
    dtype = means2d.dtype
    ts = bins.tile_size
    num_tiles = bins.num_tiles
    counts = bins.tile_counts()
    order, chunks, s_block = _plan_chunks(bins, S, _TORCH_CHUNK_ELEMS)
    need_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (means2d, conics, colors, opacities, depths))
    offsets = bins.tile_offsets
    per_g = torch.cat([means2d, conics, opacities[..., None], colors, depths[..., None]], dim=-1)  # (S,N,10)

    parts = []  # per sample block: (rgb, depth, T, n_contrib) over the sorted tiles
    dev = means2d.device
    wsum = torch.zeros(S, N, dtype=dtype, device=dev) if return_weights else None
    wsq = torch.zeros(S, N, dtype=dtype, device=dev) if return_weights else None
    for s0 in range(0, S, s_block):
        s1 = min(S, s0 + s_block)
        parts_s = []
        for i, j, kmax in chunks:
            tiles = order[i:j]
            pxc, pyc, inside = _tile_pixel_centres(bins, tiles, width, height, dtype)
            kk = torch.arange(kmax, device=dev)
            valid = kk[None, :] < counts[tiles][:, None]  # (Tc, K)
            pos = (offsets[tiles][:, None] + kk[None, :]).clamp_max(max(bins.num_pairs - 1, 0))
            gidx = torch.where(valid, bins.flat_ids[pos] if bins.num_pairs > 0 else pos, 0)  # (Tc, K)
            data = per_g[s0:s1][:, gidx]  # (s, Tc, K, 10)
            mx, my, ca, cb, cc, op = (data[..., q] for q in range(6))
            col, z = data[..., 6:9], data[..., 9]
            args = (mx, my, ca, cb, cc, op, col, z, valid, pxc, pyc, inside, return_weights)
            out = checkpoint(_torch_chunk, *args, use_reentrant=False) if need_grad else _torch_chunk(*args)
            parts_s.append(out[:4])
            ws_c, wq_c = out[4:]
            if return_weights and kmax > 0:
                flat = gidx.reshape(-1)
                for acc, part in ((wsum, ws_c), (wsq, wq_c)):
                    acc[s0:s1].index_add_(1, flat, torch.where(valid, part, 0).reshape(s1 - s0, -1))
        parts.append([torch.cat(p, 1) for p in zip(*parts_s)])
    inv = torch.empty_like(order)
    inv[order] = torch.arange(num_tiles, device=order.device)

    def to_image(x: Tensor) -> Tensor:  # (S, num_tiles(sorted), Pix, ...) -> (S, H, W, ...)
        x = x.index_select(1, inv)
        tail = x.shape[3:]
        x = x.reshape((S, bins.tiles_y, bins.tiles_x, ts, ts) + tail)
        x = x.permute((0, 1, 3, 2, 4) + tuple(range(5, 5 + len(tail))))
        x = x.reshape((S, bins.tiles_y * ts, bins.tiles_x * ts) + tail)
        return x[:, :height, :width]

    rgb, depth, T, n_contrib = (to_image(torch.cat(p, 0)) for p in zip(*parts))
    rgb = rgb + T[..., None] * background.to(dtype)
    return RasterOutput(rgb=rgb, alpha=1.0 - T, depth=depth, weight_sum=wsum, weight_sq_sum=wsq,
                        n_contrib=n_contrib)


# -------------------------------------------------------------------------------------- C++ backend
class _RasterizeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, background, tile_offsets, flat_ids,
                geom, return_weights):
        from b3dgs.render._ext import load_extension

        ext = load_extension()
        width, height, ts, tiles_x, tiles_y = geom
        nthreads = torch.get_num_threads()
        rgb, depth, T, last, nc, wsum, wsq, flags = ext.forward(
            means2d, conics, colors, opacities, depths, tile_offsets, flat_ids, background,
            width, height, ts, tiles_x, tiles_y, bool(return_weights), nthreads)
        if bool(flags.any()):
            _raise_bad_inputs(flags, means2d.shape[1], means2d=means2d, conics=conics, colors=colors,
                              opacities=opacities, depths=depths)
        ctx.geom = geom
        ctx.save_for_backward(means2d, conics, colors, opacities, depths, background, tile_offsets,
                              flat_ids, T, last)
        ctx.set_materialize_grads(False)  # unused outputs (depth, alpha in the training loss) come as None
        alpha = 1.0 - T
        ctx.mark_non_differentiable(nc, wsum, wsq)
        return rgb, alpha, depth, nc, wsum, wsq

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_depth, _g_nc, _g_ws, _g_wq):
        from b3dgs.render._ext import load_extension

        ext = load_extension()
        means2d, conics, colors, opacities, depths, background, tile_offsets, flat_ids, T, last = ctx.saved_tensors
        width, height, ts, tiles_x, tiles_y = ctx.geom
        g_rgb = torch.zeros(T.shape + (3,), dtype=T.dtype) if g_rgb is None else g_rgb.contiguous()
        none = torch.zeros(0, dtype=T.dtype)  # no gradient: the kernel skips that output's terms
        gm, gc, gcol, go, gz = ext.backward(
            means2d, conics, colors, opacities, depths, tile_offsets, flat_ids, background, T, last,
            g_rgb, none if g_depth is None else g_depth.contiguous(), none if g_alpha is None else g_alpha.contiguous(),
            width, height, ts, tiles_x, tiles_y, torch.get_num_threads())
        g_bg = (g_rgb * T[..., None]).sum(dim=(0, 1, 2)) if ctx.needs_input_grad[5] else None
        return gm, gc, gcol, go, gz, g_bg, None, None, None, None


def _rasterize_cpu(means2d, conics, colors, opacities, depths, bins, width, height, background,
                   return_weights):
    geom = (int(width), int(height), int(bins.tile_size), int(bins.tiles_x), int(bins.tiles_y))
    rgb, alpha, depth, nc, wsum, wsq = _RasterizeCPU.apply(
        means2d.contiguous(), conics.contiguous(), colors.contiguous(), opacities.contiguous(),
        depths.contiguous(), background.contiguous(), bins.tile_offsets.contiguous(),
        bins.flat_ids.contiguous(), geom, bool(return_weights))
    return RasterOutput(rgb=rgb, alpha=alpha, depth=depth,
                        weight_sum=wsum if return_weights else None,
                        weight_sq_sum=wsq if return_weights else None, n_contrib=nc)


def rasterize(
    means2d: Tensor,
    conics: Tensor,
    colors: Tensor,
    opacities: Tensor,
    depths: Tensor,
    bins: TileBins,
    width: int,
    height: int,
    background: Tensor,
    backend: str = "cpu",
    return_weights: bool = False,
) -> RasterOutput:
    """Alpha-composite binned 2D Gaussians (see the module docstring for the exact rules).

    means2d (S, N, 2), conics (S, N, 3) = (a, b, c) of the inverse covariance, colors (S, N, 3),
    opacities (S, N) in [0, 1], depths (S, N), background (3,). Differentiable w.r.t. means2d,
    conics, colors, opacities, depths (and background) through rgb, alpha and depth.
    """
    _check_inputs(means2d, conics, colors, opacities, depths, bins, width, height, background, backend)
    background = background.to(means2d.dtype)
    return _RASTER_BACKENDS[backend](means2d, conics, colors, opacities, depths, bins, width, height, background,
                                     return_weights)


_RASTER_BACKENDS = {"cpu": _rasterize_cpu, "torch": _rasterize_torch}
_BACKEND_DEVICE_TYPE = {"cpu": "cpu", "torch": None}  # None: any device
