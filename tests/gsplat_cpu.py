"""A CPU stand-in for gsplat 1.5.3's compiled extension ``gsplat.cuda._backend._C`` (tests only).

gsplat's Python (``rasterization``, the ``_wrapper`` autograd functions, channel padding, packing)
calls a handful of kernels by name; this module provides them as PyTorch functions written from the
formulas of gsplat's ``.cu`` sources, so that its Python runs unchanged on the CPU. :func:`install`
puts the module into ``sys.modules`` as ``gsplat.cuda._backend`` before gsplat imports it, so gsplat
never looks for nvcc.

What is emulated (pinhole camera, the 3DGS path ``rasterization(..., packed=False)`` takes):
projection (``projection_ewa_3dgs_fused_fwd/bwd``), tile intersection (``intersect_tile``,
``intersect_offset``), rasterization to pixels (``rasterize_to_pixels_3dgs_fwd/bwd``) and to
pixel lists (``rasterize_to_indices_3dgs``), and SH colours (``spherical_harmonics_fwd/bwd``).
Anything else raises ``NotImplementedError`` naming the kernel.

Faithful where it matters for testing a caller:
- outputs a CUDA kernel leaves unwritten (``at::empty`` entries of culled Gaussians, masked SH
  colours) are NaN here, so code that reads them fails visibly instead of by chance;
- float→int conversions follow CUDA's saturating rules (NaN radius -> 0);
- backward passes are autograd of the same forward, restricted to what the CUDA backward touches:
  culled Gaussians (radius 0) and masked SH entries get exactly zero gradient.
"""
from __future__ import annotations

import math
import sys
import types
from typing import Optional

import torch
from torch import Tensor

CPU_EMULATION = True  # read by b3dgs.render.gsplat_backend.gsplat_emulated()
ALPHA_THRESHOLD = 1.0 / 255.0
MAX_ALPHA = 0.999
T_STOP = 1e-4  # a pixel stops when the transmittance would reach this (exclusive)
EXTEND_MAX = 3.33  # radius in sigmas before the opacity-aware bound
# CameraModelType values; gsplat's _make_lazy_cuda_obj looks each name up on the module itself
PINHOLE, ORTHO, FISHEYE, FTHETA = 0, 1, 2, 3
CameraModelType = types.SimpleNamespace(PINHOLE=PINHOLE, ORTHO=ORTHO, FISHEYE=FISHEYE, FTHETA=FTHETA)
_PAIRS_PER_CHUNK = 1 << 22  # (pixel, intersection) pairs materialised at once by the rasterizer


def __getattr__(name: str):
    if name.startswith("_"):  # dunder probes (hasattr) must see an ordinary AttributeError
        raise AttributeError(name)
    raise NotImplementedError(f"gsplat CPU emulation: kernel {name!r} is not emulated "
                              "(fix: use the pinhole 3DGS path, rasterization(..., packed=False))")


# ------------------------------------------------------------------------------------------------
# projection
# ------------------------------------------------------------------------------------------------
def _rotmat(quats: Tensor) -> Tensor:
    """(M, 4) wxyz -> (M, 3, 3); normalised by rsqrt without a floor, as gsplat (zero -> NaN)."""
    q = quats * torch.rsqrt((quats * quats).sum(-1, keepdim=True))
    w, x, y, z = q.unbind(-1)
    rows = [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]
    return torch.stack(rows, -1).reshape(q.shape[:-1] + (3, 3))


def _sym3(c6: Tensor) -> Tensor:
    """(M, 6) upper triangle (xx, xy, xz, yy, yz, zz) -> (M, 3, 3) symmetric."""
    a, b, c, d, e, f = c6.unbind(-1)
    return torch.stack([a, b, c, b, d, e, c, e, f], -1).reshape(c6.shape[:-1] + (3, 3))


def _project_rows(mean, cov3, vm, K, width, height, eps2d):
    """Per row (M,): camera-space mean, blurred 2-D covariance (a, b, c), means2d, conics, compensation."""
    R, t = vm[:, :3, :3], vm[:, :3, 3]
    p = (R @ mean.unsqueeze(-1)).squeeze(-1) + t
    cov_c = R @ cov3 @ R.transpose(-1, -2)
    fx, fy, cx, cy = K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2]
    x, y, z = p.unbind(-1)
    rz = 1.0 / z
    # linearisation point clamped to the view plus 0.3 tan(fov/2) on each side (15% of the image)
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    tx = z * torch.clamp(x * rz, min=-(cx / fx + 0.3 * tan_x), max=(width - cx) / fx + 0.3 * tan_x)
    ty = z * torch.clamp(y * rz, min=-(cy / fy + 0.3 * tan_y), max=(height - cy) / fy + 0.3 * tan_y)
    zero = torch.zeros_like(z)
    J = torch.stack([fx * rz, zero, -fx * tx * rz * rz, zero, fy * rz, -fy * ty * rz * rz], -1).reshape(-1, 2, 3)
    cov2 = J @ cov_c @ J.transpose(-1, -2)
    a, b, c = cov2[:, 0, 0], cov2[:, 0, 1], cov2[:, 1, 1]
    det_orig = a * c - b * b
    a, c = a + eps2d, c + eps2d
    det = a * c - b * b
    comp = torch.sqrt(torch.clamp(det_orig / det, min=0.0))
    conics = torch.stack([c / det, -b / det, a / det], -1)
    means2d = torch.stack([fx * x * rz + cx, fy * y * rz + cy], -1)
    return p, torch.stack([a, b, c], -1), det, means2d, conics, comp


def _rows(means, covars, quats, scales, viewmats, Ks, sel=None):
    """Gather the (batch, camera, Gaussian) rows: per-row mean, 3-D covariance, viewmat, K, and the index."""
    N, C = means.shape[-2], viewmats.shape[-3]
    B = means.numel() // (3 * N) if N else 1
    idx = torch.arange(B * C * N, device=means.device) if sel is None else sel
    b, c, n = idx // (C * N), (idx // N) % C, idx % N
    mean = means.reshape(B, N, 3)[b, n]
    if covars is not None:
        cov3 = _sym3(covars.reshape(B, N, 6)[b, n])
    else:
        R = _rotmat(quats.reshape(B, N, 4)[b, n])
        M = R * scales.reshape(B, N, 3)[b, n].unsqueeze(-2)
        cov3 = M @ M.transpose(-1, -2)
    return mean, cov3, viewmats.reshape(B, C, 4, 4)[b, c], Ks.reshape(B, C, 3, 3)[b, c], (B, C, N, b, n)


def _f2i(v: Tensor) -> Tensor:
    """CUDA's float -> int32 conversion: saturating, NaN -> 0."""
    return torch.nan_to_num(v.double(), nan=0.0).clamp(-2.0 ** 31, 2.0 ** 31 - 1).to(torch.int32)


def _check_camera(camera_model) -> None:
    if camera_model != PINHOLE:
        raise NotImplementedError(f"gsplat CPU emulation: camera model {camera_model} is not emulated "
                                  "(fix: camera_model='pinhole')")


@torch.no_grad()
def projection_ewa_3dgs_fused_fwd(means, covars, quats, scales, opacities, viewmats, Ks, width, height, eps2d,
                                  near_plane, far_plane, radius_clip, calc_compensations, camera_model):
    _check_camera(camera_model)
    mean, cov3, vm, K, (B, C, N, b, n) = _rows(means, covars, quats, scales, viewmats, Ks)
    p, cov2, det, m2d, conics, comp = _project_rows(mean, cov3, vm, K, width, height, eps2d)
    z = p[:, 2]
    ok = ~((z < near_plane) | (z > far_plane))  # gsplat culls z < near: z == near stays
    ok &= ~(det <= 0)  # a NaN determinant is not culled here (the radius below becomes 0)
    extend = torch.full_like(z, EXTEND_MAX)
    if opacities is not None:
        o = opacities.reshape(B, N)[b, n]
        if calc_compensations:
            o = o * comp
        ok &= ~(o < ALPHA_THRESHOLD)
        extend = torch.minimum(extend, torch.sqrt(2.0 * torch.log(o / ALPHA_THRESHOLD)))
    rx = torch.ceil(extend * torch.sqrt(cov2[:, 0]))
    ry = torch.ceil(extend * torch.sqrt(cov2[:, 2]))
    ok &= ~((rx <= radius_clip) & (ry <= radius_clip))
    ok &= ~((m2d[:, 0] + rx <= 0) | (m2d[:, 0] - rx >= width) | (m2d[:, 1] + ry <= 0) | (m2d[:, 1] - ry >= height))
    lead = means.shape[:-2] + (C, N)
    radii = torch.where(ok[:, None], _f2i(torch.stack([rx, ry], -1)), torch.zeros((), dtype=torch.int32))
    nan = torch.tensor(float("nan"), dtype=means.dtype, device=means.device)
    means2d = torch.where(ok[:, None], m2d, nan)  # at::empty: culled entries are never written
    depths = torch.where(ok, z, nan)
    conics = torch.where(ok[:, None], conics, nan)
    comps = torch.where(ok, comp, torch.zeros_like(comp)) if calc_compensations else None  # at::zeros
    out = (radii.reshape(lead + (2,)), means2d.reshape(lead + (2,)), depths.reshape(lead), conics.reshape(lead + (3,)),
           comps.reshape(lead) if comps is not None else None)
    return out


def projection_ewa_3dgs_fused_bwd(means, covars, quats, scales, viewmats, Ks, width, height, eps2d, camera_model,
                                  radii, conics, compensations, v_means2d, v_depths, v_conics, v_compensations,
                                  viewmats_requires_grad):
    _check_camera(camera_model)
    sel = torch.nonzero((radii > 0).all(-1).reshape(-1)).squeeze(-1)
    leaves = [means, covars if covars is not None else quats, scales, viewmats]
    leaves = [None if t is None else t.detach().requires_grad_(True) for t in leaves]
    m_, a_, s_, v_ = leaves
    with torch.enable_grad():
        if covars is not None:
            mean, cov3, vm, K, _ = _rows(m_, a_, None, None, v_, Ks, sel)
        else:
            mean, cov3, vm, K, _ = _rows(m_, None, a_, s_, v_, Ks, sel)
        p, _, _, m2d, con, comp = _project_rows(mean, cov3, vm, K, width, height, eps2d)
        loss = ((m2d * v_means2d.reshape(-1, 2)[sel]).sum() + (p[:, 2] * v_depths.reshape(-1)[sel]).sum()
                + (con * v_conics.reshape(-1, 3)[sel]).sum())
        if v_compensations is not None:
            loss = loss + (comp * v_compensations.reshape(-1)[sel]).sum()
        wrt = [t for t in leaves if t is not None]
        grads = torch.autograd.grad(loss, wrt, allow_unused=True) if sel.numel() else [None] * len(wrt)
    grads = [torch.zeros_like(t) if g is None else g for t, g in zip(wrt, grads)]
    g = dict(zip([i for i, t in enumerate(leaves) if t is not None], grads))
    v_means, v_viewmats = g[0], (g[3] if viewmats_requires_grad else None)
    if covars is not None:
        return v_means, g[1], None, None, v_viewmats
    return v_means, None, g[1], g[2], v_viewmats


# ------------------------------------------------------------------------------------------------
# tile intersection
# ------------------------------------------------------------------------------------------------
def _n_bits(n: int) -> int:
    return int(math.floor(math.log2(n))) + 1


@torch.no_grad()
def intersect_tile(means2d, radii, depths, image_ids, gaussian_ids, I, tile_size, tile_width, tile_height, sort,
                   segmented):
    dev = means2d.device
    packed = means2d.dim() == 2
    m = means2d.reshape(-1, 2).double()
    r = radii.reshape(-1, 2).double()
    on = (r > 0).all(-1)
    ts = float(tile_size)
    x0 = torch.clamp(torch.floor(m[:, 0] / ts - r[:, 0] / ts), 0, tile_width)
    y0 = torch.clamp(torch.floor(m[:, 1] / ts - r[:, 1] / ts), 0, tile_height)
    x1 = torch.clamp(torch.ceil(m[:, 0] / ts + r[:, 0] / ts), 0, tile_width)
    y1 = torch.clamp(torch.ceil(m[:, 1] / ts + r[:, 1] / ts), 0, tile_height)
    x0, y0, x1, y1 = (torch.where(on, v, torch.zeros_like(v)).long() for v in (x0, y0, x1, y1))
    nx, ny = (x1 - x0).clamp_min(0), (y1 - y0).clamp_min(0)
    per = nx * ny
    tiles_per_gauss = per.to(torch.int32).reshape(radii.shape[:-1])
    n_isects = int(per.sum())
    src = torch.repeat_interleave(torch.arange(per.numel(), device=dev), per)
    k = torch.arange(n_isects, device=dev) - torch.repeat_interleave(torch.cumsum(per, 0) - per, per)
    tx, ty = x0[src] + k % nx[src].clamp_min(1), y0[src] + torch.div(k, nx[src].clamp_min(1), rounding_mode="floor")
    tile_id = ty * tile_width + tx
    if packed:
        iid = image_ids.long()[src]
    else:
        iid = torch.div(src, means2d.shape[-2], rounding_mode="floor")
    dbits = depths.reshape(-1).float().contiguous().view(torch.int32).long()[src] & 0xFFFFFFFF
    isect_ids = (iid << (32 + _n_bits(tile_width * tile_height))) | (tile_id << 32) | dbits
    flatten_ids = src.to(torch.int32)
    if sort:  # CUB's radix sort is stable; a segmented sort per image gives the same order
        order = torch.sort(isect_ids, stable=True).indices
        isect_ids, flatten_ids = isect_ids[order], flatten_ids[order]
    return tiles_per_gauss, isect_ids, flatten_ids


@torch.no_grad()
def intersect_offset(isect_ids, I, tile_width, tile_height):
    """Offset of each (image, tile)'s first intersection in the sorted list ([I, th, tw] int32)."""
    n_tiles = tile_width * tile_height
    tb = _n_bits(n_tiles)
    key = isect_ids >> 32
    flat = (key >> tb) * n_tiles + (key & ((1 << tb) - 1))
    want = torch.arange(I * n_tiles, device=isect_ids.device)
    return torch.searchsorted(flat, want).to(torch.int32).reshape(I, tile_height, tile_width)


# ------------------------------------------------------------------------------------------------
# rasterization
# ------------------------------------------------------------------------------------------------
class _Tiles:
    """Every (image, tile)'s intersection range, padded to the longest, in chunks of whole tiles."""

    def __init__(self, isect_offsets: Tensor, n_isects: int, tile_size: int):
        self.th, self.tw = isect_offsets.shape[-2:]
        self.I = isect_offsets.numel() // (self.th * self.tw)
        start = isect_offsets.reshape(-1).long()
        end = torch.cat([start[1:], start.new_tensor([n_isects])])
        self.start, self.count = start, (end - start).clamp_min(0)
        self.ts = tile_size
        dev = isect_offsets.device
        t = torch.arange(self.I * self.th * self.tw, device=dev) % (self.th * self.tw)
        j = torch.arange(tile_size * tile_size, device=dev)
        self.px = ((t % self.tw)[:, None] * tile_size + j % tile_size).double() + 0.5  # (tiles, P)
        self.py = (torch.div(t, self.tw, rounding_mode="floor")[:, None] * tile_size
                   + torch.div(j, tile_size, rounding_mode="floor")).double() + 0.5

    def chunks(self, first: int = 0, last: Optional[int] = None):
        """(tile indices, (tiles, L) intersection positions, (tiles, L) validity) per chunk; tiles go in
        order of their list length, so a chunk pads only to its own longest list."""
        lo = self.start + first
        cnt = (self.count - first).clamp_min(0)
        if last is not None:
            cnt = torch.minimum(cnt, torch.full_like(cnt, last - first))
        order = torch.argsort(cnt, descending=True, stable=True)
        counts = cnt[order].tolist()
        P, a, n = self.ts * self.ts, 0, len(counts)
        while a < n:
            L = max(counts[a], 1)
            b = min(n, a + max(1, _PAIRS_PER_CHUNK // (L * P)))
            idx = order[a:b]
            ar = torch.arange(L, device=lo.device)
            yield idx, lo[idx, None] + ar, ar < cnt[idx, None]
            a = b

    def to_image(self, per_pixel: Tensor, H: int, W: int) -> Tensor:
        """(I·tiles, P, ...) -> (I, H, W, ...)."""
        tail = per_pixel.shape[2:]
        x = per_pixel.reshape((self.I, self.th, self.tw, self.ts, self.ts) + tail)
        x = x.permute((0, 1, 3, 2, 4) + tuple(range(5, 5 + len(tail))))
        return x.reshape((self.I, self.th * self.ts, self.tw * self.ts) + tail)[:, :H, :W]


def _alphas(xy, conic, opac, px, py):
    """Per (tile, pixel, intersection): delta, sigma, alpha = min(0.999, o exp(-sigma))."""
    dx = xy[:, None, :, 0] - px[:, :, None].to(xy.dtype)
    dy = xy[:, None, :, 1] - py[:, :, None].to(xy.dtype)
    a, b, c = conic[:, None, :, 0], conic[:, None, :, 1], conic[:, None, :, 2]
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    alpha = torch.clamp(opac[:, None, :] * torch.exp(-sigma), max=MAX_ALPHA)
    return dx, dy, sigma, alpha


@torch.no_grad()
def _kept(sigma, alpha, valid, T0=None):
    """Which (pixel, intersection) pairs are composited: alpha >= 1/255, sigma >= 0, and the pixel not done."""
    use = valid[:, None, :] & ~(sigma < 0) & ~(alpha < ALPHA_THRESHOLD)
    a = torch.where(use, alpha, torch.zeros_like(alpha))
    T = torch.cumprod(1 - a, -1)
    if T0 is not None:
        T = T * T0[..., None]
    done = torch.cummax((T <= T_STOP).to(torch.uint8), -1).values.bool()
    return use & ~done


def _composite(xy, conic, opac, col, bg, px, py, valid):
    dx, dy, sigma, alpha = _alphas(xy, conic, opac, px, py)
    keep = _kept(sigma, alpha, valid)
    a = torch.where(keep, alpha, torch.zeros_like(alpha))
    T = torch.cumprod(1 - a, -1)
    T_before = torch.cat([torch.ones_like(T[..., :1]), T[..., :-1]], -1)
    w = a * T_before
    rgb = (w.unsqueeze(-1) * col[:, None]).sum(-2)
    T_final = T[..., -1]
    if bg is not None:
        rgb = rgb + T_final[..., None] * bg[:, None, :]
    return rgb, 1 - T_final, keep, (dx, dy)


def _gather(flatten_ids, pos, valid, means2d, conics, colors, opacities):
    g = torch.where(valid, flatten_ids.long()[pos.clamp_max(max(flatten_ids.numel() - 1, 0))] if flatten_ids.numel()
                    else torch.zeros_like(pos), torch.zeros_like(pos))
    D = colors.shape[-1] if colors is not None else 0
    xy = means2d.reshape(-1, 2)[g]
    con = conics.reshape(-1, 3)[g]
    op = opacities.reshape(-1)[g]
    col = colors.reshape(-1, D)[g] if colors is not None else None
    # padding entries may point at garbage (NaN) rows: neutralise them so no NaN reaches a sum
    xy = torch.where(valid[..., None], xy, torch.zeros_like(xy))
    con = torch.where(valid[..., None], con, torch.zeros_like(con))
    op = torch.where(valid, op, torch.zeros_like(op))
    if col is not None:
        col = torch.where(valid[..., None], col, torch.zeros_like(col))
    return g, xy, con, op, col


def _raster(means2d, conics, colors, opacities, backgrounds, masks, W, H, tile_size, isect_offsets, flatten_ids,
            grads: Optional[tuple] = None):
    tiles = _Tiles(isect_offsets, flatten_ids.numel(), tile_size)
    D = colors.shape[-1]
    n_t, P = tiles.start.numel(), tile_size * tile_size
    T_per_img = tiles.th * tiles.tw
    bg = None if backgrounds is None else backgrounds.reshape(-1, D)
    m = None if masks is None else masks.reshape(-1)
    out_c = torch.zeros(n_t, P, D, dtype=colors.dtype, device=colors.device)
    out_a = torch.zeros(n_t, P, dtype=colors.dtype, device=colors.device)
    last = torch.zeros(n_t, P, dtype=torch.int32, device=colors.device)
    if grads is not None:
        v_c_img, v_a_img, absgrad = grads
        v_col_t = _to_tiles(v_c_img, tiles)
        v_a_t = _to_tiles(v_a_img, tiles)[..., 0]
        acc = [torch.zeros_like(means2d).reshape(-1, 2), torch.zeros_like(conics).reshape(-1, 3),
               torch.zeros_like(colors).reshape(-1, D), torch.zeros_like(opacities).reshape(-1),
               torch.zeros_like(means2d).reshape(-1, 2)]
    for sl, pos, valid in tiles.chunks():
        g, xy, con, op, col = _gather(flatten_ids, pos, valid, means2d, conics, colors, opacities)
        tb = None if bg is None else bg[torch.div(sl, T_per_img, rounding_mode="floor")]
        if grads is None:
            rgb, alpha, keep, _ = _composite(xy, con, op, col, tb, tiles.px[sl], tiles.py[sl], valid)
            out_c[sl], out_a[sl] = rgb, alpha
            last[sl] = torch.where(keep, pos[:, None, :], torch.zeros_like(pos[:, None, :])).amax(-1).to(torch.int32)
        else:
            ins = [t.detach().requires_grad_(True) for t in (xy, con, op, col)]
            with torch.enable_grad():
                rgb, alpha, keep, (dx, dy) = _composite(*ins, None if tb is None else tb.detach(),
                                                        tiles.px[sl], tiles.py[sl], valid)
                loss = (rgb * v_col_t[sl]).sum() + (alpha * v_a_t[sl]).sum()
                gx = torch.autograd.grad(loss, ins + [dx, dy], allow_unused=True) if loss.requires_grad else None
            if gx is None:
                continue
            gx = [torch.zeros_like(t) if v is None else v for t, v in zip(ins + [dx, dy], gx)]
            v_xy, v_con, v_op, v_col, gdx, gdy = gx
            gi = g.reshape(-1)
            acc[0].index_add_(0, gi, v_xy.reshape(-1, 2))
            acc[1].index_add_(0, gi, v_con.reshape(-1, 3))
            acc[2].index_add_(0, gi, v_col.reshape(-1, D))
            acc[3].index_add_(0, gi, v_op.reshape(-1))
            if absgrad:  # Σ over pixels of |d loss / d mean2d| per pixel
                acc[4].index_add_(0, gi, torch.stack([gdx.abs().sum(1), gdy.abs().sum(1)], -1).reshape(-1, 2))
    if grads is not None:
        return acc
    if m is not None:  # a masked tile: background colour, alphas and last ids left unwritten (NaN, -1)
        off = ~m.bool()
        out_c[off] = (bg[torch.div(torch.arange(n_t, device=off.device), T_per_img, rounding_mode="floor")][off, None]
                      if bg is not None else 0.0)
        out_a[off] = float("nan")
        last[off] = -1
    return tiles.to_image(out_c, H, W), tiles.to_image(out_a, H, W), tiles.to_image(last, H, W)


def _to_tiles(img: Tensor, tiles: _Tiles) -> Tensor:
    """(…, H, W, D) image gradient -> (I·tiles, P, D), zero-padded to whole tiles."""
    H, W, D = img.shape[-3:]
    x = img.reshape(tiles.I, H, W, D)
    x = torch.nn.functional.pad(x, (0, 0, 0, tiles.tw * tiles.ts - W, 0, tiles.th * tiles.ts - H))
    x = x.reshape(tiles.I, tiles.th, tiles.ts, tiles.tw, tiles.ts, D).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(tiles.I * tiles.th * tiles.tw, tiles.ts * tiles.ts, D)


@torch.no_grad()
def rasterize_to_pixels_3dgs_fwd(means2d, conics, colors, opacities, backgrounds, masks, image_width, image_height,
                                 tile_size, isect_offsets, flatten_ids):
    c, a, last = _raster(means2d, conics, colors, opacities, backgrounds, masks, image_width, image_height, tile_size,
                         isect_offsets, flatten_ids)
    lead = isect_offsets.shape[:-2]
    return (c.reshape(lead + c.shape[1:]), a.reshape(lead + a.shape[1:] + (1,)), last.reshape(lead + last.shape[1:]))


def rasterize_to_pixels_3dgs_bwd(means2d, conics, colors, opacities, backgrounds, masks, image_width, image_height,
                                 tile_size, isect_offsets, flatten_ids, render_alphas, last_ids, v_render_colors,
                                 v_render_alphas, absgrad):
    if masks is not None:
        raise NotImplementedError("gsplat CPU emulation: the backward pass with tile masks is not emulated "
                                  "(fix: masks=None)")
    v_xy, v_con, v_col, v_op, v_abs = _raster(
        means2d, conics, colors, opacities, backgrounds, None, image_width, image_height, tile_size, isect_offsets,
        flatten_ids, grads=(v_render_colors, v_render_alphas, absgrad))
    shape = lambda t, ref: t.reshape(ref.shape)  # noqa: E731
    return (shape(v_abs, means2d) if absgrad else None, shape(v_xy, means2d), shape(v_con, conics),
            shape(v_col, colors), shape(v_op, opacities))


@torch.no_grad()
def rasterize_to_indices_3dgs(range_start, range_end, transmittances, means2d, conics, opacities, image_width,
                              image_height, tile_size, isect_offsets, flatten_ids):
    """(Gaussian id, image·H·W + pixel id) of every composited pair, per pixel front to back."""
    tiles = _Tiles(isect_offsets, flatten_ids.numel(), tile_size)
    N = means2d.shape[-2]
    bs = tile_size * tile_size
    T0 = _to_tiles(transmittances.unsqueeze(-1), tiles)[..., 0]
    first, last = range_start * bs, min(range_end, 1 << 40) * bs
    gids, pids, orders = [], [], []
    for sl, pos, valid in tiles.chunks(first, last):
        g, xy, con, op, _ = _gather(flatten_ids, pos, valid, means2d, conics, None, opacities)
        _, _, sigma, alpha = _alphas(xy, con, op, tiles.px[sl], tiles.py[sl])
        keep = _kept(sigma, alpha, valid, T0[sl])
        t_i, p_i, l_i = torch.nonzero(keep, as_tuple=True)
        tile = sl[t_i]
        img = torch.div(tile, tiles.th * tiles.tw, rounding_mode="floor")
        x = (tiles.px[sl][t_i, p_i] - 0.5).long()
        y = (tiles.py[sl][t_i, p_i] - 0.5).long()
        inside = (x < image_width) & (y < image_height)
        gids.append((g[t_i, l_i] % N)[inside])
        pix = img * image_height * image_width + y * image_width + x
        pids.append(pix[inside])
        orders.append(l_i[inside])
    if not gids:
        e = torch.zeros(0, dtype=torch.long, device=means2d.device)
        return e, e.clone()
    gid, pid, order = torch.cat(gids), torch.cat(pids), torch.cat(orders)
    srt = torch.argsort(pid * (int(order.max()) + 1 if order.numel() else 1) + order)
    return gid[srt], pid[srt]


# ------------------------------------------------------------------------------------------------
# spherical harmonics (degrees 0-3)
# ------------------------------------------------------------------------------------------------
def _sh_rows(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    out = 0.2820947917738781 * coeffs[:, 0]
    if degree < 1:
        return out
    d = dirs * torch.rsqrt((dirs * dirs).sum(-1, keepdim=True))
    x, y, z = (v[:, None] for v in d.unbind(-1))
    out = out + 0.48860251190292 * (-y * coeffs[:, 1] + z * coeffs[:, 2] - x * coeffs[:, 3])
    if degree < 2:
        return out
    z2, c1, s1 = z * z, x * x - y * y, 2 * x * y
    b2 = [0.5462742152960395 * s1, -1.092548430592079 * z * y, 0.9461746957575601 * z2 - 0.3153915652525201,
          -1.092548430592079 * z * x, 0.5462742152960395 * c1]
    out = out + sum(b * coeffs[:, 4 + i] for i, b in enumerate(b2))
    if degree < 3:
        return out
    c2, s2 = x * c1 - y * s1, x * s1 + y * c1
    t0 = -2.285228997322329 * z2 + 0.4570457994644658
    b3 = [-0.5900435899266435 * s2, 1.445305721320277 * z * s1, t0 * y, z * (1.865881662950577 * z2 - 1.119528997770346),
          t0 * x, 1.445305721320277 * z * c1, -0.5900435899266435 * c2]
    return out + sum(b * coeffs[:, 9 + i] for i, b in enumerate(b3))


def _check_sh(degree: int) -> None:
    if degree > 3:
        raise NotImplementedError(f"gsplat CPU emulation: SH degree {degree} is not emulated (fix: sh_degree <= 3)")


@torch.no_grad()
def spherical_harmonics_fwd(degree, dirs, coeffs, masks):
    _check_sh(degree)
    K = coeffs.shape[-2]
    d, c = dirs.reshape(-1, 3), coeffs.reshape(-1, K, 3)
    colors = _sh_rows(degree, d, c)
    if masks is not None:  # at::empty: masked entries are never written
        colors = torch.where(masks.reshape(-1, 1), colors, torch.full_like(colors, float("nan")))
    return colors.reshape(dirs.shape)


def spherical_harmonics_bwd(num_bases, degree, dirs, coeffs, masks, v_colors, compute_v_dirs):
    _check_sh(degree)
    K = coeffs.shape[-2]
    d = dirs.detach().reshape(-1, 3)
    c = coeffs.detach().reshape(-1, K, 3)
    sel = torch.arange(d.shape[0], device=d.device) if masks is None else torch.nonzero(masks.reshape(-1)).squeeze(-1)
    ds, cs = d[sel].requires_grad_(True), c[sel].requires_grad_(True)
    with torch.enable_grad():
        loss = (_sh_rows(degree, ds, cs) * v_colors.reshape(-1, 3)[sel]).sum()
        gd, gc = torch.autograd.grad(loss, [ds, cs], allow_unused=True) if sel.numel() else (None, None)
    v_coeffs = torch.zeros_like(c)
    v_dirs = torch.zeros_like(d)
    if gc is not None:
        v_coeffs[sel] = gc
    if gd is not None:
        v_dirs[sel] = gd
    return v_coeffs.reshape(coeffs.shape), (v_dirs.reshape(dirs.shape) if compute_v_dirs else None)


# ------------------------------------------------------------------------------------------------
# installation
# ------------------------------------------------------------------------------------------------
BACKEND_MODULE = "gsplat.cuda._backend"


def install() -> Optional[types.ModuleType]:
    """Make this module gsplat's ``_C`` (before gsplat loads its backend); returns what it replaced."""
    previous = sys.modules.get(BACKEND_MODULE)
    backend = types.ModuleType(BACKEND_MODULE, "gsplat's backend, emulated on the CPU by tests/gsplat_cpu.py")
    backend._C = sys.modules[__name__]
    sys.modules[BACKEND_MODULE] = backend
    cuda_pkg = sys.modules.get("gsplat.cuda")
    if cuda_pkg is not None:
        setattr(cuda_pkg, "_backend", backend)
    return previous


def uninstall(previous: Optional[types.ModuleType]) -> None:
    """Undo :func:`install`."""
    if previous is None:
        sys.modules.pop(BACKEND_MODULE, None)
    else:
        sys.modules[BACKEND_MODULE] = previous
    cuda_pkg = sys.modules.get("gsplat.cuda")
    if cuda_pkg is not None:
        if previous is None:
            cuda_pkg.__dict__.pop("_backend", None)
        else:
            setattr(cuda_pkg, "_backend", previous)
