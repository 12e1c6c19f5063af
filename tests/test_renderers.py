"""Renderer plugins: one contract for every backend (cpu, torch; gsplat on CUDA, and on the CPU through
the emulation of its kernels in ``tests/gsplat_cpu.py``)."""
from __future__ import annotations

import math
import warnings
from pathlib import Path

import pytest
import torch

from b3dgs.render import _ext
from b3dgs.render.gsplat_backend import weight_sums
from b3dgs.render.rasterize import bin_gaussians, rasterize
from b3dgs.render.renderers import (CPURenderer, GsplatRenderer, Renderer, RendererUnavailable, TorchRenderer,
                                    auto_renderer, first_compiler_error, gsplat_available, make_renderer)
from b3dgs.types import Camera

CUDA = torch.cuda.is_available()


def _available() -> list[Renderer]:
    out: list[Renderer] = [CPURenderer(), TorchRenderer(device_name="cpu"), GsplatRenderer(device_name="cpu")]
    if CUDA:
        out.append(TorchRenderer(device_name="cuda"))
    if gsplat_available():
        out.append(GsplatRenderer())
    return out


RENDERERS = _available()
IDS = [f"{r.name}-{r.device.type}" for r in RENDERERS]


@pytest.fixture
def renderer(request):
    """The parametrized renderer; a CPU gsplat renderer runs under the emulation of gsplat's kernels."""
    r = request.param
    if r.name == "gsplat" and r.device.type == "cpu":
        request.getfixturevalue("gsplat_cpu")
    return r


def _camera(W=48, H=40, device="cpu") -> Camera:
    K = torch.tensor([[50.0, 0, W / 2], [0, 50.0, H / 2], [0, 0, 1]])
    vm = torch.eye(4)
    vm[2, 3] = 3.0
    return Camera("c", K, vm, W, H, torch.rand(H, W, 3, generator=torch.Generator().manual_seed(1))).to(device)


def _params(n=60, device="cpu", seed=0) -> dict:
    g = torch.Generator().manual_seed(seed)
    p = {
        "means": (torch.rand(n, 3, generator=g) - 0.5) * 1.2,
        "quats": torch.randn(n, 4, generator=g),
        "scales": torch.log(0.03 + 0.08 * torch.rand(n, 3, generator=g)),
        "opacities": torch.randn(n, generator=g),
        "sh0": 0.5 * torch.randn(n, 1, 3, generator=g),
        "shN": 0.1 * torch.randn(n, 15, 3, generator=g),
    }
    return {k: v.to(device).requires_grad_(True) for k, v in p.items()}


@pytest.mark.parametrize("renderer", RENDERERS, ids=IDS, indirect=True)
def test_contract_shapes_weights_and_means2d_grad(renderer):
    dev = renderer.device
    cam, p = _camera(device=dev), _params(device=dev)
    out = renderer.render(p, cam, sh_degree=3, return_weights=renderer.supports_weights, retain_means2d_grad=True)
    assert out.rgb.shape == (40, 48, 3) and out.alpha.shape == (40, 48) and out.depth.shape == (40, 48)
    assert out.radii.shape == (1, 60) and out.means2d.shape == (1, 60, 2)
    assert out.rgb.device.type == dev.type and bool(torch.isfinite(out.rgb).all())
    loss = (1 - renderer.ssim(out.rgb, cam.image)) + out.rgb.mean()
    loss.backward()
    g = out.means2d_grad
    assert g is not None and g.shape == (1, 60, 2) and bool((g[0, out.visible[0]] != 0).any())
    assert p["means"].grad is not None and bool(torch.isfinite(p["means"].grad).all())
    if renderer.supports_weights:
        # the weights of a pixel add up to its alpha, so the sums over Gaussians add up to Σ alpha
        assert out.weight_sum.shape == (1, 60) and out.weight_sq_sum.shape == (1, 60)
        assert math.isclose(float(out.weight_sum.sum()), float(out.alpha.detach().sum()), rel_tol=1e-4)
        assert bool((out.weight_sq_sum <= out.weight_sum + 1e-6).all())


@pytest.mark.parametrize("renderer", RENDERERS, ids=IDS, indirect=True)
def test_samples_equal_single_renders(renderer):
    dev = renderer.device
    cam = _camera(device=dev)
    p = {k: v.detach() for k, v in _params(device=dev).items()}
    S = 3
    shift = torch.linspace(-0.05, 0.05, S, device=dev).view(S, 1, 1)
    batched = dict(p, means=p["means"].unsqueeze(0) + shift)
    with torch.no_grad():
        out = renderer.render(batched, cam, sh_degree=2, return_weights=renderer.supports_weights)
        assert out.rgb.shape == (S, 40, 48, 3)
        for s in range(S):
            one = renderer.render(dict(p, means=batched["means"][s]), cam, sh_degree=2,
                                  return_weights=renderer.supports_weights)
            # shared binning (a union of footprints) changes no pixel
            assert torch.allclose(out.rgb[s], one.rgb, atol=1e-5)
            if renderer.supports_weights:
                assert torch.allclose(out.weight_sum[s], one.weight_sum[0], atol=1e-5)


def _brute_force_pairs(means2d, conics, opac, depths, W, H, max_alpha):
    """Every composited (Gaussian, pixel) pair, front to back per pixel, by the per-pixel rules."""
    order = torch.argsort(depths, stable=True).tolist()
    g_ids, p_ids = [], []
    for py in range(H):
        for px in range(W):
            T = 1.0
            for k in order:
                dx = float(means2d[k, 0]) - (px + 0.5)
                dy = float(means2d[k, 1]) - (py + 0.5)
                a, b, c = (float(v) for v in conics[k])
                sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                alpha = min(max_alpha, float(opac[k]) * math.exp(-sigma))
                if sigma < 0 or alpha < 1.0 / 255.0:
                    continue
                if T * (1 - alpha) < 1e-4:
                    break
                g_ids.append(k)
                p_ids.append(py * W + px)
                T *= 1 - alpha
    return torch.tensor(g_ids, dtype=torch.long), torch.tensor(p_ids, dtype=torch.long)


def test_weight_sums_from_pixel_pairs_match_our_rasterizer():
    """The gsplat weight-sum path (pairs + segmented log-space product) against the torch rasterizer, float64."""
    g = torch.Generator().manual_seed(3)
    N, W, H = 25, 20, 18
    means2d = torch.stack([torch.rand(N, generator=g) * W, torch.rand(N, generator=g) * H], -1).double()
    A = torch.randn(N, 2, 2, generator=g).double() * 0.4
    cov = A @ A.transpose(-1, -2) + 2.0 * torch.eye(2, dtype=torch.float64)
    inv = torch.linalg.inv(cov)
    conics = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1)
    opac = (0.3 + 0.69 * torch.rand(N, generator=g)).double()
    depths = torch.rand(N, generator=g).double() + 1
    gids, pids = _brute_force_pairs(means2d, conics, opac, depths, W, H, max_alpha=0.99)
    ws, wq = weight_sums(gids, pids, torch.zeros_like(gids), means2d[None], conics[None], opac[None], W, H,
                         max_alpha=0.99)
    radii = torch.full((1, N), 50.0, dtype=torch.float64)
    bins = bin_gaussians(means2d[None], radii, depths[None], W, H, backend="torch")
    ref = rasterize(means2d[None], conics[None], torch.rand(1, N, 3, dtype=torch.float64), opac[None], depths[None],
                    bins, W, H, torch.zeros(3, dtype=torch.float64), backend="torch", return_weights=True)
    assert torch.allclose(ws, ref.weight_sum, rtol=1e-10, atol=1e-12)
    assert torch.allclose(wq, ref.weight_sq_sum, rtol=1e-10, atol=1e-12)


def test_weight_sums_handle_several_images_and_shuffled_pixels():
    g = torch.Generator().manual_seed(4)
    I, N, W, H = 2, 6, 5, 4
    means2d = torch.rand(I, N, 2, generator=g).double() * 4
    conics = torch.tensor([0.5, 0.0, 0.5], dtype=torch.float64).expand(I, N, 3).contiguous()
    opac = torch.full((I, N), 0.6, dtype=torch.float64)
    depths = torch.arange(N, dtype=torch.float64)
    per_img = [_brute_force_pairs(means2d[i], conics[i], opac[i], depths, W, H, 0.999) for i in range(I)]
    gids = torch.cat([p[0] for p in per_img])
    pids = torch.cat([p[1] for p in per_img])
    iids = torch.cat([torch.full_like(p[0], i) for i, p in enumerate(per_img)])
    ws, wq = weight_sums(gids, pids, iids, means2d, conics, opac, W, H)
    # pixels listed in another order (gsplat groups them by tile): same sums
    perm = torch.argsort(pids * 7 % 11 + iids * 100, stable=True)
    ws2, wq2 = weight_sums(gids[perm], pids[perm], iids[perm], means2d, conics, opac, W, H)
    assert torch.allclose(ws, ws2) and torch.allclose(wq, wq2)
    assert ws.shape == (I, N) and bool((ws > 0).any()) and bool((ws[0] != ws[1]).any())


def test_make_renderer_and_errors():
    assert isinstance(make_renderer("cpu"), CPURenderer)
    assert isinstance(make_renderer("torch"), TorchRenderer)
    r = TorchRenderer()
    assert make_renderer(r) is r
    with pytest.raises(ValueError, match="unknown renderer 'vulkan'.*fix"):
        make_renderer("vulkan")
    with pytest.raises(ValueError, match="renderer.near"):
        CPURenderer(near=0.0)
    if not CUDA:
        with pytest.raises(RendererUnavailable, match="needs a CUDA GPU.*fix"):
            GsplatRenderer().check_available()
    # gsplat on the CPU only under the test suite's emulation of its kernels
    with pytest.raises(RendererUnavailable, match="renderer.device_name=cpu.*emulation.*fix: renderer=cpu"):
        GsplatRenderer(device_name="cpu").check_available()
    with pytest.raises(ValueError, match="renderer=gsplat needs float32 CUDA.*fix"):
        GsplatRenderer(device_name="cpu").render(_params(), _camera())


def test_auto_picks_the_cpp_backend_without_cuda():
    if CUDA:
        pytest.skip("a CUDA machine picks gsplat or the C++ backend by what is installed")
    r = auto_renderer()
    assert isinstance(r, CPURenderer) and r.device.type == "cpu"


def test_failed_cpp_build_warns_once_and_falls_back(monkeypatch):
    def broken(verbose=False):
        raise RuntimeError("Error building extension 'b3dgs':\nkernels.h:241:56: error: uninitialized 'const s'\n")

    monkeypatch.setattr(_ext, "load_extension", broken)
    monkeypatch.setattr("b3dgs.render.renderers.gsplat_available", lambda: False)
    monkeypatch.setattr(_ext, "_WARNED", set())
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        r1 = auto_renderer()
        r2 = auto_renderer()
    assert isinstance(r1, TorchRenderer) and isinstance(r2, TorchRenderer)
    msgs = [str(w.message) for w in rec if issubclass(w.category, RuntimeWarning)]
    assert len(msgs) == 1
    assert "error: uninitialized 'const s'" in msgs[0] and "renderer=torch" in msgs[0]


def test_niw_sampler_fallback_is_loud(monkeypatch):
    from b3dgs_plugins.posterior.niw import NIWBlock

    monkeypatch.setattr(_ext, "load_extension", lambda verbose=False: (_ for _ in ()).throw(
        RuntimeError("x.cpp:1:1: error: no compiler")))
    monkeypatch.setattr(_ext, "_WARNED", set())
    with pytest.warns(RuntimeWarning, match="error: no compiler.*torch path"):
        assert NIWBlock(sampler_backend="auto")._sampling_extension(torch.device("cpu")) is None
    # on a non-CPU device auto never tries the C++ sampler
    assert NIWBlock(sampler_backend="auto")._sampling_extension(torch.device("meta")) is None


def test_first_compiler_error():
    assert first_compiler_error("ninja: build stopped\nfoo.h:3:4: error: bad thing\nmore") == "error: bad thing"
    assert first_compiler_error("no such file\nsecond") == "no such file"


def test_accelerator_follows_the_renderer():
    from b3dgs.lifecycle import resolve_accelerator

    assert resolve_accelerator("auto", CPURenderer()) == "cpu"
    assert resolve_accelerator(None, CPURenderer()) == "cpu"
    assert resolve_accelerator("cpu", CPURenderer()) == "cpu"
    with pytest.raises(ValueError, match="does not match renderer=cpu.*fix"):
        resolve_accelerator("gpu", CPURenderer())


def test_plugin_states_and_cameras_follow_the_module():
    """States are plain dicts: they move with the module's device (here the meta device), never change dtype."""
    from b3dgs.data import load_scene
    from b3dgs.module import SplatModule
    from b3dgs_plugins.posterior.dp import DPBlock
    from b3dgs_plugins.posterior.niw import NIWBlock
    from b3dgs_plugins.strategy.default import AdaptiveDensityControl

    scene = load_scene("synthetic", None, max_side=32, n_views=8)
    m = SplatModule(strategy=AdaptiveDensityControl(), posterior={"niw": NIWBlock(), "dp": DPBlock()},
                    renderer="cpu", max_steps=100)
    m.init_from_scene(scene)
    dtypes = {(n, k): v.dtype for n, st in m.states.items() for k, v in st.items() if torch.is_tensor(v)}
    m.double()
    assert {(n, k): v.dtype for n, st in m.states.items() for k, v in st.items() if torch.is_tensor(v)} == dtypes
    m.to("meta")
    devs = {v.device.type for st in m.states.values() for v in st.values() if torch.is_tensor(v)}
    assert devs == {"meta"}
    cam = m.device_camera(scene.train[0])
    assert cam.image.device.type == "meta" and m.device_camera(scene.train[0]) is cam


@pytest.mark.cuda
@pytest.mark.slow
@pytest.mark.skipif(not CUDA, reason="needs a CUDA GPU")
@pytest.mark.parametrize("model", ["niw", "dpmm"])
def test_short_training_on_cuda(tmp_path, model):
    from tests.test_train import run_train

    m = run_train(tmp_path / model, [f"model={model}", "trainer.max_steps=200", "renderer=auto"])
    assert m["renderer"]["device"].startswith("cuda") and m["psnr"] > 15


def test_a_model_trained_on_a_gpu_comes_back_to_the_renderers_device():
    """Lightning's teardown moves a model trained on CUDA to the CPU; the final evaluation then called gsplat with
    CPU tensors (seen on an H100: "renderer=gsplat needs float32 CUDA tensors, got torch.float32 on cpu"). The
    fit helper moves it back, and every fit in the package goes through it."""
    import re
    from types import SimpleNamespace

    from b3dgs.lifecycle import fit_on_renderer_device

    class Model:  # a module that Lightning's teardown left on the CPU, its renderer on another device
        def __init__(self):
            self.device, self.moved = torch.device("cpu"), []
            self.renderer = SimpleNamespace(device=torch.device("cuda"))

        def to(self, device):
            self.moved.append(device)
            self.device = torch.device(device)

    fits = []
    trainer = SimpleNamespace(fit=lambda module, **kw: fits.append(kw))
    m = Model()
    fit_on_renderer_device(trainer, m, datamodule="dm")
    assert fits == [{"datamodule": "dm"}] and m.moved == [torch.device("cuda")]
    m = Model()
    m.renderer.device = torch.device("cpu")
    fit_on_renderer_device(trainer, m)
    assert m.moved == []  # the CPU path moves nothing
    root = Path(__file__).resolve().parents[1]
    direct = [str(p.relative_to(root)) for sub in ("b3dgs", "plugins", "bench") for p in (root / sub).rglob("*.py")
              if re.search(r"\btrainer\.fit\(", p.read_text()) and p != root / "b3dgs" / "lifecycle.py"]
    assert direct == [], f"trainer.fit outside fit_on_renderer_device: {direct}"
    assert (root / "b3dgs" / "lifecycle.py").read_text().count("trainer.fit(") == 2  # the helper and its docstring
