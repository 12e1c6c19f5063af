"""gsplat (``renderer=gsplat``) checked without a GPU: gsplat 1.5.3's own Python on the CPU emulation of its
kernels (``tests/gsplat_cpu.py``), against gsplat's torch references and against ``renderer=torch``."""
from __future__ import annotations

import math

import pytest
import torch

from b3dgs.render.renderers import GsplatRenderer, TorchRenderer, gsplat_available
from tests.test_renderers import _camera, _params

pytestmark = pytest.mark.usefixtures("gsplat_cpu")

DEVICES = ["cpu", pytest.param("cuda", marks=[pytest.mark.cuda, pytest.mark.skipif(
    not gsplat_available(), reason="needs CUDA and gsplat (pip install -e '.[cuda]')")])]


def _scene(n=60, seed=0):
    """Quaternions, scales (not logs), opacities in (0, 1), SH and a camera for the kernel-level checks."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 1.2
    quats = torch.randn(n, 4, generator=g)
    scales = 0.03 + 0.08 * torch.rand(n, 3, generator=g)
    cam = _camera()
    return means, quats, scales, cam.viewmat[None], cam.K[None], cam.width, cam.height


def test_projection_and_intersection_match_gsplat_torch_reference():
    from gsplat.cuda import _torch_impl as ref
    from gsplat.cuda._wrapper import fully_fused_projection, isect_offset_encode, isect_tiles

    means, quats, scales, vm, K, W, H = _scene()
    covars, _ = ref._quat_scale_to_covar_preci(quats, scales, compute_preci=False, triu=False)
    r0, m0, d0, c0, comp0 = ref._fully_fused_projection(means, covars, vm, K, W, H, calc_compensations=True)
    r1, m1, d1, c1, comp1 = fully_fused_projection(means, None, quats, scales, vm, K, W, H, calc_compensations=True)
    vis = (r1 > 0).all(-1)
    assert torch.equal(r0, r1) and int(vis.sum()) > 40
    for a, b in ((m0, m1), (d0, d1), (c0, c1), (comp0, comp1)):
        torch.testing.assert_close(a[vis], b[vis], rtol=1e-5, atol=1e-5)
    tw, th = math.ceil(W / 16), math.ceil(H / 16)
    t0, i0, f0 = ref._isect_tiles(m1, r1, d1, 16, tw, th)
    t1, i1, f1 = isect_tiles(m1, r1, d1, 16, tw, th)
    assert torch.equal(t0, t1) and torch.equal(i0, i1) and torch.equal(f0, f1)
    assert torch.equal(ref._isect_offset_encode(i0, 1, tw, th), isect_offset_encode(i1, 1, tw, th))


def test_spherical_harmonics_match_gsplat_torch_reference():
    from gsplat.cuda._torch_impl import _spherical_harmonics
    from gsplat.cuda._wrapper import spherical_harmonics

    g = torch.Generator().manual_seed(1)
    dirs = torch.randn(50, 3, generator=g)
    coeffs = torch.randn(50, 16, 3, generator=g)
    for deg in range(4):
        d0, c0 = dirs.clone().requires_grad_(True), coeffs.clone().requires_grad_(True)
        d1, c1 = dirs.clone().requires_grad_(True), coeffs.clone().requires_grad_(True)
        y0, y1 = _spherical_harmonics(deg, d0, c0), spherical_harmonics(deg, d1, c1)
        torch.testing.assert_close(y1, y0, rtol=1e-5, atol=1e-6)
        w = torch.randn(y0.shape, generator=g)
        (y0 * w).sum().backward()
        (y1 * w).sum().backward()
        torch.testing.assert_close(c1.grad, c0.grad, rtol=1e-5, atol=1e-6)
        if deg > 0:
            torch.testing.assert_close(d1.grad, d0.grad, rtol=1e-4, atol=1e-5)


def test_emulation_marks_unwritten_outputs_and_gives_culled_gaussians_no_gradient():
    """What CUDA leaves unwritten is NaN here, and the backward pass skips culled Gaussians, like gsplat's."""
    from gsplat.cuda._wrapper import fully_fused_projection

    means, quats, scales, vm, K, W, H = _scene(n=6)
    means = means.clone()
    means[0, 2] = -4.0  # behind the camera (z = -1)
    means.requires_grad_(True)
    radii, m2d, depths, conics, _ = fully_fused_projection(means, None, quats, scales, vm, K, W, H)
    assert int(radii[0, 0].abs().sum()) == 0 and bool(torch.isnan(m2d[0, 0]).all()) and bool(torch.isnan(depths[0, 0]))
    (torch.nan_to_num(m2d).sum() + torch.nan_to_num(depths).sum()).backward()
    assert bool((means.grad[0] == 0).all()) and bool((means.grad[1:] != 0).any())


@pytest.mark.parametrize("device", DEVICES)
def test_gsplat_matches_torch(device):
    """gsplat vs our torch reference on an unsaturated scene (opacities <= sigmoid(2)): images, alpha, weight
    sums and every parameter gradient agree to float32 rounding (CPU emulation; a GPU's fast-math kernels
    are allowed 10x more)."""
    tol = 1e-5 if device == "cpu" else 1e-4
    cam = _camera(device=device)
    p = _params(device=device)
    with torch.no_grad():
        p["opacities"].clamp_(max=2.0)
    outs, grads = [], []
    for r in (GsplatRenderer(device_name=device), TorchRenderer(device_name=device)):
        q = {k: v.detach().clone().requires_grad_(True) for k, v in p.items()}
        out = r.render(q, cam, sh_degree=3, return_weights=True, retain_means2d_grad=True)
        (out.rgb * cam.image).sum().backward()
        outs.append(out)
        grads.append({k: v.grad for k, v in q.items()})
    a, b = outs
    assert torch.equal(a.visible, b.visible)
    torch.testing.assert_close(a.rgb, b.rgb, rtol=0, atol=tol)
    torch.testing.assert_close(a.alpha, b.alpha, rtol=0, atol=tol)
    torch.testing.assert_close(a.weight_sum, b.weight_sum, rtol=tol, atol=tol)
    torch.testing.assert_close(a.weight_sq_sum, b.weight_sq_sum, rtol=tol, atol=tol)
    torch.testing.assert_close(a.means2d, b.means2d, rtol=tol, atol=tol * 10)  # pixels: |x| ~ 50
    torch.testing.assert_close(a.means2d_grad, b.means2d_grad, rtol=tol, atol=tol)
    for k, gb in grads[1].items():
        ga = grads[0][k]
        assert float((ga - gb).norm() / gb.norm()) < tol, k


def test_gsplat_covariance_samples_match_torch():
    """Posterior covariance draws (``covars=``, S samples in one call) render as on the torch backend; gsplat
    reads the upper triangle of Σ, so its covariance gradient is the torch one folded onto that triangle."""
    from b3dgs.render.projection import covariance_3d

    cam, p = _camera(), _params()
    with torch.no_grad():
        p["opacities"].clamp_(max=2.0)
        cov = covariance_3d(p["quats"], p["scales"])
        cov = torch.stack([cov, cov * 1.2, cov * 0.8])  # S = 3
    outs, grads = [], []
    for r in (GsplatRenderer(device_name="cpu"), TorchRenderer(device_name="cpu")):
        c = cov.clone().requires_grad_(True)
        q = {"means": p["means"].detach(), "covars": c, "opacities": p["opacities"].detach(),
             "sh0": p["sh0"].detach(), "shN": p["shN"].detach()}
        out = r.render(q, cam, sh_degree=2, return_weights=True)
        (out.rgb * cam.image).sum().backward()
        outs.append(out)
        grads.append(c.grad)
    a, b = outs
    assert a.rgb.shape == (3, 40, 48, 3)
    torch.testing.assert_close(a.rgb, b.rgb, rtol=0, atol=1e-5)
    torch.testing.assert_close(a.weight_sum, b.weight_sum, rtol=1e-5, atol=1e-5)
    folded = grads[1] + grads[1].transpose(-1, -2) - torch.diag_embed(torch.diagonal(grads[1], dim1=-2, dim2=-1))
    triu = torch.triu(torch.ones(3, 3, dtype=torch.bool))
    assert bool((grads[0][..., ~triu] == 0).all())
    torch.testing.assert_close(grads[0][..., triu], folded[..., triu], rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("model", ["niw", "dpmm", "mcmc"])
def test_short_training_with_gsplat_on_the_cpu(tmp_path, model):
    """``renderer=gsplat renderer.device_name=cpu`` trains every model kind end to end (densification reads
    gsplat's radii and 2-D mean gradients; NIW and DPMM its weight sums; MCMC its relocation inputs)."""
    from tests.test_stiff import TINY, _check_run
    from tests.test_train import run_train

    m = run_train(tmp_path, TINY + [f"model={model}", "renderer=gsplat", "renderer.device_name=cpu"])
    _check_run(tmp_path)
    assert m["renderer"]["name"] == "gsplat" and m["renderer"]["device"] == "cpu"
    assert m["steps"] == 30 and m["psnr"] > 10.0, m["psnr"]


def test_offscreen_near_gaussian_renders_alike_in_every_backend():
    """Every backend clamps the Jacobian's linearisation point as 3DGS and gsplat do (0.15 W/fx beyond the
    image edge): a large, near Gaussian centred outside the view (x/z = 0.7; the edge is at 0.48, the clamp
    at 0.624) renders the same. With our former 0.3 W/fx margin the images differed by about 0.02."""
    from b3dgs.render.renderers import CPURenderer

    cam = _camera()
    p = {"means": torch.tensor([[0.7, 0.0, -2.0]]), "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
         "scales": torch.log(torch.tensor([[0.3, 0.3, 0.3]])), "opacities": torch.tensor([0.0]),
         "sh0": torch.tensor([[[1.0, 0.5, 0.2]]]), "shN": torch.zeros(1, 15, 3)}
    imgs = {r.name: r.render(p, cam, sh_degree=0).rgb
            for r in (TorchRenderer(device_name="cpu"), CPURenderer(), GsplatRenderer(device_name="cpu"))}
    assert float(imgs["torch"].amax()) > 0.05  # the Gaussian reaches into the image
    for name in ("cpu", "gsplat"):
        torch.testing.assert_close(imgs[name], imgs["torch"], rtol=0, atol=1e-5)
