"""Projection, SH colours and the full render (projection + binning + rasterization)."""
import math

import pytest
import torch

from b3dgs.render.preprocess import preprocess
from b3dgs.render.projection import covariance_3d, eval_sh, project, quat_to_rotmat, sh_basis
from b3dgs.render.render import render
from b3dgs.types import Camera


def cam(w=40, h=30, f=35.0, dtype=torch.float32):
    K = torch.tensor([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]], dtype=dtype)
    view = torch.eye(4, dtype=dtype)
    a = 0.1
    view[:3, :3] = torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]], dtype=dtype)
    view[:3, 3] = torch.tensor([0.05, -0.02, 0.1], dtype=dtype)
    return Camera("c", K.float(), view.float(), w, h)


def gaussians(n=30, seed=0, dtype=torch.float64, sh=1):
    g = torch.Generator().manual_seed(seed)
    means = torch.empty(n, 3, dtype=dtype)
    means[:, :2] = (torch.rand(n, 2, generator=g, dtype=dtype) - 0.5) * 1.2
    means[:, 2] = 2.0 + torch.rand(n, generator=g, dtype=dtype)
    return {
        "means": means, "quats": torch.randn(n, 4, generator=g, dtype=dtype),
        "scales": torch.log(0.05 + 0.1 * torch.rand(n, 3, generator=g, dtype=dtype)),
        "opacities": torch.logit(0.2 + 0.5 * torch.rand(n, generator=g, dtype=dtype)),
        "sh0": 0.5 * torch.randn(n, 1, 3, generator=g, dtype=dtype),
        "shN": 0.1 * torch.randn(n, (sh + 1) ** 2 - 1, 3, generator=g, dtype=dtype),
    }


def test_projection_matches_matrix_reference():
    p = gaussians(50)
    c = cam()
    cov = covariance_3d(p["quats"], p["scales"])
    R = quat_to_rotmat(p["quats"])
    S = torch.diag_embed(torch.exp(2 * p["scales"]))
    assert torch.allclose(cov, R @ S @ R.transpose(-1, -2), atol=1e-12)
    proj = project(p["means"], cov, c.viewmat.double(), c.K.double(), c.width, c.height)
    V = c.viewmat.double()
    pc = p["means"] @ V[:3, :3].T + V[:3, 3]
    x, y, z = pc.unbind(-1)
    fx, fy = c.K[0, 0].double(), c.K[1, 1].double()
    J = torch.zeros(50, 2, 3, dtype=torch.float64)
    J[:, 0, 0], J[:, 0, 2] = fx / z, -fx * x / z**2  # all means are inside the clamp range here
    J[:, 1, 1], J[:, 1, 2] = fy / z, -fy * y / z**2
    cov2 = J @ V[:3, :3] @ cov @ V[:3, :3].T @ J.transpose(-1, -2) + 0.3 * torch.eye(2, dtype=torch.float64)
    assert torch.allclose(proj.cov2d[:, 0], cov2[:, 0, 0]) and torch.allclose(proj.cov2d[:, 1], cov2[:, 0, 1])
    assert torch.allclose(proj.cov2d[:, 2], cov2[:, 1, 1])
    conic = torch.linalg.inv(cov2)
    assert torch.allclose(proj.conics, torch.stack([conic[:, 0, 0], conic[:, 0, 1], conic[:, 1, 1]], -1))
    assert torch.allclose(proj.means2d[:, 0], fx * x / z + c.K[0, 2])
    # 3DGS's major-axis eigenvalue, with its 0.1 floor under the square root
    mid = 0.5 * (cov2[:, 0, 0] + cov2[:, 1, 1])
    lam = mid + torch.sqrt(torch.clamp(mid**2 - torch.linalg.det(cov2), min=0.1))
    assert torch.all(proj.radii[proj.radii > 0] == torch.ceil(3 * lam.sqrt())[proj.radii > 0])


def test_near_plane_culls():
    p = gaussians(4)
    p["means"][0, 2] = -1.0  # behind the camera
    p["means"][1, 2] = 0.005  # in front of the near plane
    c = cam()
    proj = project(p["means"], covariance_3d(p["quats"], p["scales"]), torch.eye(4, dtype=torch.float64), c.K.double(),
                   c.width, c.height)
    assert proj.radii[0] == 0 and proj.radii[1] == 0 and proj.radii[2] > 0


def test_sh_basis_is_orthonormal():
    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(400_000, 3, generator=g, dtype=torch.float64), dim=-1)
    Y = sh_basis(3, d)
    gram = 4 * math.pi * (Y.T @ Y) / d.shape[0]
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=0.02)
    c = torch.randn(7, 16, 3, dtype=torch.float64)
    dd = torch.nn.functional.normalize(torch.randn(7, 3, dtype=torch.float64), dim=-1)
    assert torch.allclose(eval_sh(3, c, dd), torch.einsum("nb,nbc->nc", sh_basis(3, dd), c))
    assert torch.allclose(eval_sh(0, c, dd), 0.28209479177387814 * c[:, 0])


def test_full_render_gradcheck_torch_backend():
    p = gaussians(6, seed=3)
    p["scales"] = torch.log(torch.full((6, 3), 0.25, dtype=torch.float64))  # large, smooth footprints
    p["opacities"] = torch.logit(torch.full((6,), 0.3, dtype=torch.float64))
    c = Camera("tiny", torch.tensor([[12.0, 0, 8], [0, 12.0, 8], [0, 0, 1]]), torch.eye(4), 16, 16)
    names = ["means", "scales", "quats", "opacities", "sh0", "shN"]

    def f(*xs):
        q = dict(zip(names, xs))
        out = render(q, c, sh_degree=1, backend="torch", background=torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64))
        return out.rgb, out.alpha

    inputs = tuple(p[k].clone().requires_grad_(True) for k in names)
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-9), (torch.float32, 1e-5)])
def test_backends_agree_on_full_render(dtype, tol):
    p = gaussians(200, seed=1, dtype=dtype, sh=3)
    c = cam(53, 37)
    res = {}
    for backend in ("cpu", "torch"):
        q = {k: v.clone().requires_grad_(True) for k, v in p.items()}
        out = render(q, c, sh_degree=3, backend=backend)
        (out.rgb * torch.linspace(0, 1, out.rgb.numel(), dtype=dtype).view_as(out.rgb)).sum().backward()
        res[backend] = (out.rgb.detach(), {k: v.grad for k, v in q.items()})
    a, b = res["cpu"], res["torch"]
    scale = a[0].abs().max()
    assert (a[0] - b[0]).abs().max() <= tol * scale
    for k in p:
        ga, gb = a[1][k], b[1][k]
        assert (ga - gb).abs().max() <= tol * max(float(gb.abs().max()), 1e-12), k


def test_samples_render_in_one_call_and_covars_path():
    p = gaussians(80, seed=2, dtype=torch.float32)
    c = cam()
    single = render(p, c, sh_degree=1).rgb
    batched = {k: v.unsqueeze(0).expand((3,) + v.shape).clone() for k, v in p.items()}
    batched["means"][1] += 0.01
    out = render(batched, c, sh_degree=1)
    assert out.rgb.shape == (3, c.height, c.width, 3)
    assert torch.allclose(out.rgb[0], single, atol=1e-6) and torch.allclose(out.rgb[2], single, atol=1e-6)
    assert not torch.allclose(out.rgb[1], single, atol=1e-4)
    cov = covariance_3d(p["quats"], p["scales"])
    q = {k: v for k, v in p.items() if k not in ("quats", "scales")}
    q["covars"] = cov
    assert torch.allclose(render(q, c, sh_degree=1).rgb, single, atol=1e-6)


def test_render_rejects_bad_shapes():
    p = gaussians(5, dtype=torch.float32)
    p["opacities"] = p["opacities"][:4]
    with pytest.raises(ValueError, match="opacities"):
        render(p, cam())


PRE_OUTPUTS = ("means2d", "conics", "colors", "opacities", "depths")


def _pre_grads(params, c, S, backend, deg=3):
    q = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    pre = preprocess(q, c, S, deg, backend)
    g = torch.Generator().manual_seed(7)
    loss = sum((getattr(pre, k) * torch.randn(getattr(pre, k).shape, generator=g, dtype=pre.means2d.dtype)).sum()
               for k in PRE_OUTPUTS)
    loss.backward()
    return pre, {k: v.grad for k, v in q.items()}


@pytest.mark.parametrize("covars", [False, True])
def test_fused_preprocess_matches_torch_reference(covars):
    """The C++ projection + SH + opacity pass equals the autograd reference, values and gradients,
    including culled / clamped / off-screen Gaussians and a mix of shared and per-sample inputs."""
    p = gaussians(120, seed=4, sh=3)
    p["means"][:4, 2] = torch.tensor([-1.0, 0.005, 2.0, 2.0], dtype=torch.float64)  # behind, near plane
    p["means"][2, 0] = 9.0  # far outside the field of view: Jacobian clamp, off-screen
    p["sh0"][5] = -3.0  # colour clamped at 0
    p["means"] = p["means"].unsqueeze(0).repeat(2, 1, 1)  # per-sample means, shared rest
    p["means"][1] += 0.01 * torch.randn(120, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    if covars:
        p["covars"] = covariance_3d(p.pop("quats"), p.pop("scales"))
    c = cam(53, 37)
    (a, ga), (b, gb) = _pre_grads(p, c, 2, "cpu"), _pre_grads(p, c, 2, "torch")
    for k in PRE_OUTPUTS + ("radii", "extent"):
        assert torch.allclose(getattr(a, k), getattr(b, k), rtol=1e-10, atol=1e-12), k
    assert (a.radii == 0).any() and (a.radii > 0).any()
    for k in p:
        if covars and k == "covars":  # the fused pass symmetrises: compare the symmetric part
            ga[k], gb[k] = ga[k] + ga[k].transpose(-1, -2), gb[k] + gb[k].transpose(-1, -2)
        assert torch.allclose(ga[k], gb[k], rtol=1e-9, atol=1e-12), k


@pytest.mark.parametrize("deg", [0, 1, 2, 3])
def test_fused_preprocess_gradcheck(deg):
    p = gaussians(5, seed=6, sh=3)
    c = cam(24, 20)
    names = ["means", "quats", "scales", "opacities", "sh0", "shN"]

    def f(*xs):
        pre = preprocess(dict(zip(names, xs)), c, 1, deg, "cpu")
        return tuple(getattr(pre, k) for k in PRE_OUTPUTS)

    inputs = tuple(p[k].clone().requires_grad_(True) for k in names)
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_extent_binning_changes_no_pixel():
    """Binning by where alpha can reach 1/255 instead of the 3-sigma square drops pairs, never pixels."""
    from b3dgs.render.rasterize import bin_gaussians, rasterize

    p = gaussians(300, seed=8, dtype=torch.float64, sh=1)
    p["opacities"][:100] = torch.logit(torch.full((100,), 0.02, dtype=torch.float64))  # faint: small extent
    c = cam(64, 48)
    pre = preprocess(p, c, 1, 1, "torch")
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    tight = bin_gaussians(pre.means2d, pre.radii, pre.depths, 64, 48, extent=pre.extent)
    square = bin_gaussians(pre.means2d, pre.radii, pre.depths, 64, 48)
    assert tight.num_pairs < 0.8 * square.num_pairs
    args = (pre.means2d, pre.conics, pre.colors, pre.opacities, pre.depths)
    # C++: each pixel composites the same Gaussians in the same order -> bit-identical images
    a = rasterize(*args, tight, 64, 48, bg, backend="cpu")
    b = rasterize(*args, square, 64, 48, bg, backend="cpu")
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.alpha, b.alpha)
    # torch: the same Gaussians per pixel, but the two tile lists are summed in different orders, so the
    # last bits may differ with the machine's vectorisation (3.3e-16 seen)
    a = rasterize(*args, tight, 64, 48, bg, backend="torch")
    b = rasterize(*args, square, 64, 48, bg, backend="torch")
    assert torch.equal(a.n_contrib, b.n_contrib)
    torch.testing.assert_close(a.rgb, b.rgb, rtol=0, atol=1e-12)
    torch.testing.assert_close(a.alpha, b.alpha, rtol=0, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("case", ["ordinary", "quat_zero", "quat_extreme", "scale_huge", "shared_scales_S3"])
def test_cpu_guard_detection_matches_the_guards(dtype, case):
    """The C++ pass detects the guards itself; its result and counts equal those of rendering the
    Python-guarded parameters (the path it falls back to when a guard fires)."""
    from b3dgs.numerics import guard_counts, reset_guards
    from b3dgs.render.preprocess import _preprocess_cpu, guarded_params

    p = gaussians(40, dtype=dtype)
    S = 1
    if case == "quat_zero":
        p["quats"][3] = 0.0
    elif case == "quat_extreme":
        p["quats"][5] *= 1e20
        p["quats"][6] *= 1e-20
    elif case == "scale_huge":
        p["scales"][7, 1] = 200.0 if dtype == torch.float64 else 60.0
    elif case == "shared_scales_S3":
        S = 3
        p["means"] = p["means"] + 0.01 * torch.randn(3, 40, 3, dtype=dtype)
        p["scales"][9, 0] = 200.0 if dtype == torch.float64 else 60.0
    c = cam()
    reset_guards()
    fast = preprocess(p, c, S, 1, "cpu")
    fast_counts = guard_counts()
    reset_guards()
    ref, _ = _preprocess_cpu(guarded_params(p, c, 0.01), c, S, 1, 0.01)
    assert guard_counts() == fast_counts
    if case != "ordinary":
        assert fast_counts, "the case must fire a guard"
    for name in ("means2d", "conics", "colors", "opacities", "depths", "radii", "extent"):
        assert torch.equal(getattr(fast, name), getattr(ref, name)), name
