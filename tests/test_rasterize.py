"""Tests of the tile rasterizer (b3dgs.render.rasterize): torch vs C++ backends, gradients,
determinism, sample batching, early termination, weights and input validation."""
from __future__ import annotations

import math

import pytest
import torch

from b3dgs.render.rasterize import RasterOutput, TileBins, bin_gaussians, rasterize


@pytest.fixture(scope="module")
def cpu_ext():
    from b3dgs.render._ext import load_extension

    try:
        return load_extension()
    except RuntimeError as e:  # pragma: no cover - only without a compiler
        pytest.skip(f"C++ extension unavailable: {e}")


def random_gaussians(S, N, W, H, dtype=torch.float64, sigma=(1.0, 6.0), seed=0, margin=5.0):
    """Random 2D Gaussians: means in (slightly beyond) the image, conics from random SPD 2x2."""
    g = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.rand(*shape, generator=g, dtype=dtype)

    means = rand(S, N, 2) * torch.tensor([W + 2 * margin, H + 2 * margin], dtype=dtype) - margin
    sig = sigma[0] + (sigma[1] - sigma[0]) * rand(S, N, 2)
    th = rand(S, N) * 2 * math.pi
    rot = torch.stack([th.cos(), -th.sin(), th.sin(), th.cos()], -1).reshape(S, N, 2, 2)
    cov = rot @ torch.diag_embed(sig**2) @ rot.transpose(-1, -2)
    inv = torch.linalg.inv(cov)
    conics = torch.stack([inv[..., 0, 0], inv[..., 0, 1], inv[..., 1, 1]], -1)
    radii = torch.ceil(3 * sig.amax(-1))
    colors = rand(S, N, 3)
    opac = 0.05 + 0.94 * rand(S, N)
    depths = 1 + 5 * rand(S, N)
    return means, conics, colors, opac, depths, radii


def run(backend, inputs, bins, W, H, bg, grads=True, weights=False, seed=1):
    """Renders and backprops a fixed random linear loss of rgb/alpha/depth; returns (out, grads)."""
    ins = [t.detach().clone().requires_grad_(grads) for t in inputs]
    out = rasterize(*ins, bins, W, H, bg, backend=backend, return_weights=weights)
    if not grads:
        return out, None
    g = torch.Generator().manual_seed(seed)
    loss = sum((o * torch.randn(o.shape, generator=g, dtype=o.dtype)).sum()
               for o in (out.rgb, out.alpha, out.depth))
    loss.backward()
    return out, [t.grad for t in ins]


def brute_force(means, conics, colors, opac, depths, bins: TileBins, W, H, bg):
    """Literal per-pixel implementation of the compositing rules (float64, Python loops)."""
    S, N = opac.shape
    rgb = torch.zeros(S, H, W, 3, dtype=torch.float64)
    alpha = torch.zeros(S, H, W, dtype=torch.float64)
    depth = torch.zeros(S, H, W, dtype=torch.float64)
    ncon = torch.zeros(S, H, W, dtype=torch.int32)
    wsum = torch.zeros(S, N, dtype=torch.float64)
    wsq = torch.zeros(S, N, dtype=torch.float64)
    ts = bins.tile_size
    for s in range(S):
        for py in range(H):
            for px in range(W):
                t = (py // ts) * bins.tiles_x + px // ts
                ids = bins.flat_ids[bins.tile_offsets[t]: bins.tile_offsets[t + 1]].tolist()
                T, c, d = 1.0, [0.0, 0.0, 0.0], 0.0
                for k in ids:
                    dx = float(means[s, k, 0]) - (px + 0.5)
                    dy = float(means[s, k, 1]) - (py + 0.5)
                    a, b, cc = (float(v) for v in conics[s, k])
                    power = -0.5 * (a * dx * dx + cc * dy * dy) - b * dx * dy
                    if power > 0:
                        continue
                    al = min(0.99, float(opac[s, k]) * math.exp(power))
                    if al < 1 / 255:
                        continue
                    test_T = T * (1 - al)
                    if test_T < 1e-4:
                        break
                    w = al * T
                    c = [c[i] + w * float(colors[s, k, i]) for i in range(3)]
                    d += w * float(depths[s, k])
                    wsum[s, k] += w
                    wsq[s, k] += w * w
                    ncon[s, py, px] += 1
                    T = test_T
                rgb[s, py, px] = torch.tensor(c, dtype=torch.float64) + T * bg.double()
                alpha[s, py, px] = 1 - T
                depth[s, py, px] = d
    return rgb, alpha, depth, ncon, wsum, wsq


def rel_err(x, y):
    x, y = x.detach().double(), y.detach().double()
    return float((x - y).abs().max() / y.abs().max().clamp_min(1e-12))


# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("backend", ["torch", "cpu"])
@pytest.mark.parametrize("with_extent", [False, True])
def test_binning_matches_brute_force(backend, with_extent, request):
    if backend == "cpu":
        request.getfixturevalue("cpu_ext")
    W, H = 50, 37
    means, conics, colors, opac, depths, radii = random_gaussians(2, 60, W, H, seed=3)
    radii[0, :10] = 0  # culled in sample 0 only: rect from sample 1
    radii[:, 10:15] = 0  # culled everywhere: never binned
    g = torch.Generator().manual_seed(4)
    extent = radii[..., None] * torch.rand(2, 60, 2, generator=g, dtype=radii.dtype) if with_extent else None
    if with_extent:
        extent[1, 20:25] = 0  # visible in sample 1 but never reaching alpha 1/255 there
    ex = extent if with_extent else radii[..., None].expand(2, 60, 2)
    bins = bin_gaussians(means, radii, depths, W, H, extent=extent, backend=backend)
    tx, ty = bins.tiles_x, bins.tiles_y
    assert (tx, ty) == (4, 3) and bins.tile_offsets.shape == (13,)
    lists = [[] for _ in range(tx * ty)]
    for k in range(60):
        vis = [s for s in range(2) if radii[s, k] > 0]
        ok = [s for s in vis if ex[s, k, 0] > 0 and ex[s, k, 1] > 0]
        if not ok:
            continue
        x0 = min(float(means[s, k, 0] - ex[s, k, 0]) for s in ok)
        x1 = max(float(means[s, k, 0] + ex[s, k, 0]) for s in ok)
        y0 = min(float(means[s, k, 1] - ex[s, k, 1]) for s in ok)
        y1 = max(float(means[s, k, 1] + ex[s, k, 1]) for s in ok)
        zk = sum(float(depths[s, k]) for s in vis) / len(vis)
        for y in range(max(0, math.floor(y0 / 16)), min(ty, math.ceil(y1 / 16))):
            for x in range(max(0, math.floor(x0 / 16)), min(tx, math.ceil(x1 / 16))):
                lists[y * tx + x].append((zk, k))
    for t in range(tx * ty):
        got = bins.flat_ids[bins.tile_offsets[t]: bins.tile_offsets[t + 1]].tolist()
        assert got == [k for _, k in sorted(lists[t])], f"tile {t}"
    assert bins.num_pairs == sum(len(lst) for lst in lists)


def test_forward_matches_brute_force_and_weights(cpu_ext):
    W, H = 21, 18
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    inputs = random_gaussians(2, 40, W, H, sigma=(1.0, 4.0), seed=5)[:5]
    radii = random_gaussians(2, 40, W, H, sigma=(1.0, 4.0), seed=5)[5]
    bins = bin_gaussians(inputs[0], radii, inputs[4], W, H)
    ref = brute_force(*inputs, bins, W, H, bg)
    for backend in ("torch", "cpu"):
        out, _ = run(backend, inputs, bins, W, H, bg, grads=False, weights=True)
        got = (out.rgb, out.alpha, out.depth, out.n_contrib, out.weight_sum, out.weight_sq_sum)
        for name, g, r in zip(("rgb", "alpha", "depth", "n_contrib", "wsum", "wsq"), got, ref):
            assert g.shape == r.shape, (backend, name)
            assert torch.allclose(g.double(), r.double(), rtol=1e-10, atol=1e-12), (backend, name)
        # Sum of weights over Gaussians = 1 - T per pixel.
        assert torch.allclose(out.weight_sum.sum(-1), out.alpha.sum((-1, -2)), rtol=1e-10)


def _extreme_gaussians(W, H, dtype):
    """Gaussians that stress the culling intervals: huge and far off-image, needle-thin and long,
    nearly singular conics, opacities at the 1/255 threshold, means on pixel centres."""
    rows = [  # (mean x, mean y, sigma 1, sigma 2, angle, opacity)
        (-3000.0, 10.0, 1500.0, 3.0, 0.0, 0.9), (W / 2, -40000.0, 2.0, 20000.0, 0.001, 0.8),
        (5e4, 5e4, 3e4, 3e4, 0.3, 0.5), (W / 2, H / 2, 0.05, 200.0, 0.7, 0.95),
        (3.5, 4.5, 0.3, 0.3, 0.0, 0.99), (10.0, 7.0, 1e-3, 1e-3, 0.0, 0.9), (12.3, 9.9, 4.0, 4.0, 0.0, 1 / 255 + 1e-6),
        (8.0, 12.0, 30.0, 0.02, 2.3, 0.6), (-8.0, H + 6.0, 9.0, 2.0, 0.5, 0.99), (W + 0.5, 3.5, 6.0, 6.0, 0.0, 0.3),
    ]
    t = torch.tensor(rows, dtype=torch.float64)
    c, s = t[:, 4].cos(), t[:, 4].sin()
    rot = torch.stack([c, -s, s, c], -1).reshape(-1, 2, 2)
    cov = rot @ torch.diag_embed(t[:, 2:4] ** 2) @ rot.transpose(-1, -2)
    inv = torch.linalg.inv(cov)
    n = len(rows)
    g = torch.Generator().manual_seed(3)
    means = t[None, :, :2]
    conics = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1)[None]
    colors = torch.rand(1, n, 3, generator=g, dtype=torch.float64)
    opac = t[None, :, 5]
    depths = torch.linspace(1, 2, n, dtype=torch.float64)[None]
    return [x.to(dtype) for x in (means, conics, colors, opac, depths)]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_culling_is_conservative_on_extreme_gaussians(cpu_ext, dtype):
    # The C++ kernels evaluate only the pixels inside per-row intervals computed in float with a margin;
    # a pixel wrongly left out would lose a whole contribution (alpha >= 1/255), far above these tolerances.
    W, H = 24, 20
    inputs = _extreme_gaussians(W, H, dtype)
    radii = torch.full(inputs[3].shape, 1e5, dtype=dtype)  # bin every Gaussian into every tile
    bins = bin_gaussians(inputs[0], radii, inputs[4], W, H)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=dtype)
    out, _ = run("cpu", inputs, bins, W, H, bg, grads=False, weights=True)
    if dtype == torch.float64:  # against the literal per-pixel walk
        ref = brute_force(*inputs, bins, W, H, bg)
        tol = 1e-10
    else:  # float32 means at 5e4 px are too coarse for a float64 reference: the torch backend (no culling)
        t = run("torch", inputs, bins, W, H, bg, grads=False, weights=True)[0]
        ref = (t.rgb, t.alpha, t.depth, t.n_contrib, t.weight_sum)
        tol = 1e-5
    for name, got, want in zip(("rgb", "alpha", "depth", "n_contrib", "wsum"), (out.rgb, out.alpha, out.depth,
                               out.n_contrib, out.weight_sum), ref):
        assert torch.allclose(got.double(), want.double(), rtol=tol, atol=tol), name
    assert int(ref[3].sum()) > 2 * W * H  # most pixels composite several of them


@pytest.mark.parametrize("S", [1, 3])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_backends_agree(cpu_ext, S, dtype):
    # float64: <= 1e-9 relative (observed ~1e-15). float32: outputs and gradients
    # <= 1e-5 relative to the largest entry (different summation orders; observed <= 5e-7).
    W, H = 50, 37
    *inputs, radii = random_gaussians(S, 300, W, H, dtype=dtype, seed=10 + S)
    bins = bin_gaussians(inputs[0], radii, inputs[4], W, H)
    assert bins.num_pairs > 300
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=dtype)
    out_t, grads_t = run("torch", inputs, bins, W, H, bg, weights=True)
    out_c, grads_c = run("cpu", inputs, bins, W, H, bg, weights=True)
    tol_out = 1e-5 if dtype == torch.float32 else 1e-9
    tol_grad = 1e-5 if dtype == torch.float32 else 1e-9
    for name in ("rgb", "alpha", "depth", "weight_sum", "weight_sq_sum"):
        a, b = getattr(out_c, name), getattr(out_t, name)
        assert a.dtype == dtype and a.shape == b.shape
        assert rel_err(a, b) <= tol_out, name
    # n_contrib can differ only where a float32 alpha sits exactly on a threshold.
    assert (out_c.n_contrib != out_t.n_contrib).float().mean() < 1e-3
    for name, a, b in zip(("means2d", "conics", "colors", "opacities", "depths"), grads_c, grads_t):
        assert a.shape == b.shape and a.dtype == dtype
        assert rel_err(a, b) <= tol_grad, name


def _smooth_case():
    """3 large, semi-transparent Gaussians over one 16x16 tile: every pixel has
    1/255 < alpha < 0.99 for each of them and T stays far above 1e-4 (smooth function)."""
    means = torch.tensor([[[7.0, 8.5], [9.2, 6.1], [5.3, 10.4]]], dtype=torch.float64)
    conics = torch.tensor([[[1 / 64, 0.002, 1 / 49], [1 / 81, -0.003, 1 / 64], [1 / 49, 0.001, 1 / 81]]],
                          dtype=torch.float64)
    colors = torch.tensor([[[0.9, 0.1, 0.2], [0.2, 0.8, 0.3], [0.1, 0.3, 0.7]]], dtype=torch.float64)
    opac = torch.tensor([[0.6, 0.5, 0.7]], dtype=torch.float64)
    depths = torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64)
    radii = torch.full((1, 3), 30.0, dtype=torch.float64)
    return means, conics, colors, opac, depths, radii


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_gradcheck(cpu_ext, backend):
    W = H = 16
    *inputs, radii = _smooth_case()
    bins = bin_gaussians(inputs[0], radii, inputs[4], W, H)
    bg = torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64)
    out = rasterize(*inputs, bins, W, H, bg, backend=backend)
    assert out.n_contrib.min() == 3  # all pixels see all 3 Gaussians above 1/255, none clamped

    def f(*xs):
        o = rasterize(*xs, bins, W, H, bg, backend=backend)
        return o.rgb, o.alpha, o.depth

    xs = [t.clone().requires_grad_() for t in inputs]
    assert torch.autograd.gradcheck(f, xs, eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)
    # Full Jacobian on a cropped output (a few pixels) as a stricter complement.

    def f_crop(*xs):
        o = rasterize(*xs, bins, W, H, bg, backend=backend)
        return o.rgb[:, 3:5, 6:8], o.alpha[:, 10:12, 1:3], o.depth[:, 14:, 14:]

    assert torch.autograd.gradcheck(f_crop, xs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_cpu_backward_deterministic(cpu_ext):
    W, H = 64, 48
    *inputs, radii = random_gaussians(2, 2000, W, H, dtype=torch.float32, seed=7)
    bins = bin_gaussians(inputs[0], radii, inputs[4], W, H)
    bg = torch.tensor([0.1, 0.2, 0.3])
    nthreads = torch.get_num_threads()
    results = []
    try:
        for nt in (nthreads, nthreads, 1, 2):
            torch.set_num_threads(nt)
            out, grads = run("cpu", inputs, bins, W, H, bg, weights=True)
            results.append([out.rgb, out.alpha, out.depth, out.weight_sum, *grads])
    finally:
        torch.set_num_threads(nthreads)
    for other in results[1:]:
        for a, b in zip(results[0], other):
            assert torch.equal(a, b)


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_samples_equal_individual_renders(cpu_ext, backend):
    W, H = 40, 30
    S = 3
    *inputs, radii = random_gaussians(S, 150, W, H, seed=11)
    radii[1, :20] = 0  # some Gaussians culled in one sample: still binned via the union
    bins = bin_gaussians(inputs[0], radii, inputs[4], W, H)
    bg = torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64)
    out, grads = run(backend, inputs, bins, W, H, bg, weights=True)
    for s in range(S):
        ins_s = [t[s: s + 1] for t in inputs]
        g = torch.Generator().manual_seed(1)
        # Same loss restricted to sample s: regenerate the full random cotangents and slice.
        cot = [torch.randn(o.shape, generator=g, dtype=o.dtype) for o in (out.rgb, out.alpha, out.depth)]
        xs = [t.clone().requires_grad_() for t in ins_s]
        o = rasterize(*xs, bins, W, H, bg, backend=backend, return_weights=True)
        ((o.rgb * cot[0][s: s + 1]).sum() + (o.alpha * cot[1][s: s + 1]).sum()
         + (o.depth * cot[2][s: s + 1]).sum()).backward()
        for name in ("rgb", "alpha", "depth", "weight_sum", "n_contrib"):
            a, b = getattr(o, name)[0], getattr(out, name)[s]
            assert torch.allclose(a.double(), b.double(), rtol=1e-12, atol=1e-14), (name, s)
        for x, gfull in zip(xs, grads):
            assert torch.allclose(x.grad[0], gfull[s], rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_early_termination_and_background(cpu_ext, backend):
    W, H = 32, 32
    n = 10
    # An opaque stack at pixel (4, 4)'s centre; alpha = 0.95 exactly at that centre.
    means = torch.tensor([4.5, 4.5], dtype=torch.float64).expand(1, n, 2).clone()
    conics = torch.tensor([0.5, 0.0, 0.5], dtype=torch.float64).expand(1, n, 3).clone()
    colors = torch.rand(1, n, 3, dtype=torch.float64)
    opac = torch.full((1, n), 0.95, dtype=torch.float64)
    depths = torch.arange(1, n + 1, dtype=torch.float64)[None]
    radii = torch.full((1, n), 5.0, dtype=torch.float64)
    bins = bin_gaussians(means, radii, depths, W, H)
    assert bins.num_pairs == n  # only the first tile
    bg = torch.tensor([0.25, 0.5, 0.75], dtype=torch.float64)
    out = rasterize(means, conics, colors, opac, depths, bins, W, H, bg, backend=backend)
    # T: 0.05, 0.0025, 1.25e-4, then 6.25e-6 < 1e-4 -> stop: 3 composited, T = 1.25e-4 kept.
    assert int(out.n_contrib[0, 4, 4]) == 3
    assert abs(float(out.alpha[0, 4, 4]) - (1 - 0.05**3)) < 1e-12
    w = torch.tensor([0.95, 0.05 * 0.95, 0.05**2 * 0.95], dtype=torch.float64)
    exp_rgb = (w[:, None] * colors[0, :3]).sum(0) + 0.05**3 * bg
    assert torch.allclose(out.rgb[0, 4, 4], exp_rgb, atol=1e-12)
    assert abs(float(out.depth[0, 4, 4]) - float((w * depths[0, :3]).sum())) < 1e-12
    # Direct neighbour: alpha = 0.95 exp(-0.25), 0.2601^7 < 1e-4 -> 6 composited.
    assert int(out.n_contrib[0, 4, 5]) == 6 and int(out.n_contrib[0, 5, 4]) == 6
    # Far from the stack: nothing covers, the background shows through exactly.
    assert torch.equal(out.rgb[0, 20:, 20:], bg.expand(12, 12, 3))
    assert torch.equal(out.alpha[0, 20:, 20:], torch.zeros(12, 12, dtype=torch.float64))
    assert int(out.n_contrib[0, 20:, 20:].max()) == 0


def test_empty_scene(cpu_ext):
    W, H = 20, 10
    means = torch.zeros(1, 0, 2)
    empty = torch.zeros(1, 0)
    bins = bin_gaussians(means, empty, empty, W, H)
    bg = torch.tensor([0.1, 0.2, 0.3])
    for backend in ("torch", "cpu"):
        out = rasterize(means, torch.zeros(1, 0, 3), torch.zeros(1, 0, 3), empty, empty, bins, W, H,
                        bg, backend=backend, return_weights=True)
        assert isinstance(out, RasterOutput)
        assert torch.equal(out.rgb, bg.expand(1, H, W, 3)) and float(out.alpha.abs().max()) == 0
        assert out.weight_sum.shape == (1, 0)


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_bad_inputs(backend):
    W, H = 20, 20
    *inputs, radii = random_gaussians(1, 5, W, H, dtype=torch.float32)
    means, conics, colors, opac, depths = inputs
    bins = bin_gaussians(means, radii, depths, W, H)
    bg = torch.zeros(3)
    with pytest.raises(ValueError, match="conics"):
        rasterize(means, conics[..., :2], colors, opac, depths, bins, W, H, bg, backend=backend)
    with pytest.raises(ValueError, match="opacities"):
        rasterize(means, conics, colors, opac[0], depths, bins, W, H, bg, backend=backend)
    with pytest.raises(ValueError, match="colors"):
        rasterize(means, conics, colors.double(), opac, depths, bins, W, H, bg, backend=backend)
    bad = means.clone()
    bad[0, 2, 0] = float("nan")
    with pytest.raises(ValueError, match="means2d.*NaN"):
        rasterize(bad, conics, colors, opac, depths, bins, W, H, bg, backend=backend)
    with pytest.raises(ValueError, match="background"):
        rasterize(means, conics, colors, opac, depths, bins, W, H, torch.zeros(4), backend=backend)
    with pytest.raises(ValueError, match="bins"):
        rasterize(means, conics, colors, opac, depths, bins, W + 16, H, bg, backend=backend)
    with pytest.raises(ValueError, match="backend"):
        rasterize(means, conics, colors, opac, depths, bins, W, H, bg, backend="cuda")
    with pytest.raises(ValueError, match="means2d"):
        bin_gaussians(means[0], radii, depths, W, H)


@pytest.mark.parametrize("backend", ["torch", "cpu"])
@pytest.mark.parametrize("name", ["means2d", "conics", "colors", "opacities", "depths"])
@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_input_is_named(backend, name, value):
    """Every input's NaN / Inf is caught and named; the C++ backend detects it inside its own pass."""
    W, H = 20, 20
    *inputs, radii = random_gaussians(1, 5, W, H, dtype=torch.float32)
    bins = bin_gaussians(inputs[0], radii, inputs[4], W, H)
    args = dict(zip(["means2d", "conics", "colors", "opacities", "depths"], inputs))
    bad = args[name].clone()
    bad.view(-1)[-1] = value  # the last entry: not one the binning may have culled away
    args[name] = bad
    with pytest.raises(ValueError, match=f"{name} contains NaN or Inf"):
        rasterize(*args.values(), bins, W, H, torch.zeros(3), backend=backend)


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_stale_bins_are_refused(backend):
    W, H = 20, 20
    *inputs, radii = random_gaussians(1, 5, W, H, dtype=torch.float32)
    bins = bin_gaussians(inputs[0], radii, inputs[4], W, H)
    bins.flat_ids = bins.flat_ids.clone()
    bins.flat_ids[-1] = 5  # an id of a Gaussian that no longer exists
    with pytest.raises(ValueError, match="out of range"):
        rasterize(*inputs, bins, W, H, torch.zeros(3), backend=backend)


@pytest.mark.parametrize("outputs", [("rgb",), ("depth",), ("alpha",), ("rgb", "alpha")])
def test_cpu_gradients_of_a_subset_of_outputs(cpu_ext, outputs):
    """Outputs without a gradient reach the C++ backward as None (its RGB-only path when only rgb is used):
    the gradients still equal the torch reference's (float64)."""
    W, H = 37, 29
    inputs = random_gaussians(1, 40, W, H)[:5]
    radii = random_gaussians(1, 40, W, H)[5]
    bins = bin_gaussians(inputs[0], radii, inputs[4], W, H)
    bg = torch.tensor([0.2, 0.4, 0.1], dtype=torch.float64)
    g = torch.Generator().manual_seed(3)
    grads = {}
    for backend in ("torch", "cpu"):
        ins = [t.detach().clone().requires_grad_(True) for t in inputs]
        out = rasterize(*ins, bins, W, H, bg, backend=backend)
        g.manual_seed(3)
        loss = sum((getattr(out, name) * torch.rand(getattr(out, name).shape, generator=g, dtype=torch.float64)).sum()
                   for name in outputs)
        loss.backward()
        grads[backend] = [t.grad for t in ins]
    for a, b in zip(grads["torch"], grads["cpu"]):
        torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-12)


def test_default_build_has_no_lane_counters(cpu_ext):
    """The lane-occupancy counters (bench/lanes.py) exist only in the B3DGS_LANE_STATS=1 build: the default kernels
    count nothing, and the two builds never share a cache entry."""
    import os

    from b3dgs.render import _ext

    assert os.environ.get(_ext.LANE_STATS_ENV) != "1"
    assert list(cpu_ext.lane_stats(False)) == []
    default = _ext.cache_dir()
    os.environ[_ext.LANE_STATS_ENV] = "1"
    try:
        assert _ext.cache_dir() != default and "-DB3_LANE_STATS" in _ext._cflags()
    finally:
        del os.environ[_ext.LANE_STATS_ENV]
    assert _ext.cache_dir() == default


@pytest.mark.slow
def test_fma_build_matches_the_default_build(cpu_ext, tmp_path):
    """The opt-in B3DGS_FMA=1 build (its own cache entry, a separate compile) renders and differentiates like the
    default build up to float32 rounding (bench/results/fma.md measures its speed)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    from b3dgs.render import _ext

    os.environ[_ext.FMA_ENV] = "1"
    try:
        flags, fma_dir = _ext._cflags(), _ext.cache_dir()
    finally:
        del os.environ[_ext.FMA_ENV]
    assert "-DB3_FMA" in flags and "-ffp-contract=fast" in flags and "-ffp-contract=off" not in flags
    assert fma_dir != _ext.cache_dir()
    root = Path(__file__).resolve().parents[1]
    child = (
        "import sys, torch\n"
        "from bench.render import camera, random_gaussians\n"
        "from b3dgs.render.renderers import make_renderer\n"
        "p = {k: v.clone().requires_grad_(True) for k, v in random_gaussians(3000).items()}\n"
        "out = make_renderer('cpu').render(p, camera(64, 64), sh_degree=3, retain_means2d_grad=True)\n"
        "out.rgb.sum().backward()\n"
        "torch.save({'rgb': out.rgb.detach(), **{k: v.grad for k, v in p.items()}}, sys.argv[1])\n")
    res = {}
    for label, extra in (("default", {}), ("fma", {_ext.FMA_ENV: "1"})):
        env = {k: v for k, v in os.environ.items() if k != _ext.FMA_ENV}
        env.update(extra, PYTHONPATH=str(root))
        subprocess.run([sys.executable, "-c", child, str(tmp_path / f"{label}.pt")], env=env, check=True, cwd=root)
        res[label] = torch.load(tmp_path / f"{label}.pt")
    for k, a in res["default"].items():
        b = res["fma"][k]
        scale = float(a.abs().max()) + 1e-12
        assert torch.isfinite(b).all() and float((a - b).abs().max()) <= 1e-4 * scale, k
