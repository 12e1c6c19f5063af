"""A stiff and extreme suite (issue 9 §5): renderer and trainer cases at the edges of the input space.

Every case asserts that no NaN or Inf reaches the outputs (images, per-Gaussian weights and every
gradient; for trainer cases also the final parameters and metrics.json), and that the guards that
must fire are counted: ``b3dgs.numerics.guard_counts()`` for renderer cases (exactly the
expected ``render.*`` guards, so a new silent clamp or a spurious one both fail), and metrics.json's
``numerical_guards`` for trainer cases. Renderer cases run on both CPU backends (C++ and pure torch)
and on gsplat: on the CPU through the emulation of its kernels (``tests/gsplat_cpu.py``), and on a GPU
where CUDA and gsplat exist. gsplat runs behind the same counted guards, so the same guards must fire.
"""
from __future__ import annotations

import functools
import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Callable, NamedTuple, Optional

import numpy as np
import pytest
import torch

from b3dgs.errors import B3dgsError
from b3dgs.numerics import guard_counts
from b3dgs.render.renderers import CPURenderer, GsplatRenderer, Renderer, TorchRenderer, gsplat_available
from b3dgs.types import Camera

NEAR = 0.01


# ------------------------------------------------------------------------------------------------
# renderer cases
# ------------------------------------------------------------------------------------------------
def _camera(W: int = 32, H: int = 32, fov_deg: float = 60.0) -> Camera:
    """A pinhole camera at the origin looking down +z, horizontal field of view ``fov_deg``."""
    f = 0.5 * W / math.tan(math.radians(fov_deg) / 2)
    K = torch.tensor([[f, 0.0, W / 2], [0.0, f, H / 2], [0.0, 0.0, 1.0]])
    return Camera("stiff", K, torch.eye(4), W, H)


def _params(n: int = 4, seed: int = 0, **over) -> dict:
    """n anisotropic Gaussians around (0, 0, 3); ``over`` replaces a tensor (or maps it, if callable)."""
    g = torch.Generator().manual_seed(seed)
    p = {
        "means": torch.tensor([0.0, 0.0, 3.0]) + 0.4 * (torch.rand(n, 3, generator=g) - 0.5),
        "quats": torch.randn(n, 4, generator=g),
        "scales": torch.log(torch.tensor([0.15, 0.05, 0.02])).expand(n, 3).clone(),
        "opacities": torch.randn(n, generator=g),
        "sh0": 0.5 * torch.randn(n, 1, 3, generator=g),
        "shN": 0.2 * torch.randn(n, 15, 3, generator=g),
    }
    for k, v in over.items():
        p[k] = v(p[k]) if callable(v) else torch.as_tensor(v, dtype=torch.float32)
    return p


def _at(*means) -> dict:
    return _params(len(means), means=torch.tensor(means, dtype=torch.float32))


def _unit(q):
    return q / q.norm(dim=-1, keepdim=True)


class Case(NamedTuple):
    params: dict
    camera: Camera
    guards: dict  # the render.* guards this case must fire, name -> entries (exactly)
    check: Optional[Callable] = None  # extra assertions: check(out, params, renderer)
    reference: Optional[dict] = None  # params that must render the same image (rtol 1e-4)


def _culled(idx):
    def check(out, p, r):
        assert not bool(out.visible[0, idx].any()), out.radii
    return check


def _empty(out, p, r):
    assert float(out.alpha.detach().abs().max()) == 0.0 and float(out.rgb.detach().abs().max()) == 0.0


def _covers_image(out, p, r):
    assert float(out.alpha.detach().min()) > 0.3, float(out.alpha.detach().min())  # the Gaussian fills the view


def _many_on_one_tile(n: int) -> Case:
    g = torch.Generator().manual_seed(3)
    p = _params(n, means=torch.cat([0.2 * (torch.rand(n, 2, generator=g) - 0.5), 2 + torch.rand(n, 1, generator=g)], 1),
                quats=torch.randn(n, 4, generator=g), scales=torch.full((n, 3), math.log(0.02)),
                opacities=torch.full((n,), -2.0), sh0=torch.randn(n, 1, 3, generator=g), shN=torch.zeros(n, 15, 3))

    def check(out, p, r):
        assert out.radii.shape == (1, n) and int(out.visible.sum()) == n
        if out.bins is not None:
            assert out.bins.num_tiles == 1 and out.bins.num_pairs == n
    return Case(p, _camera(16, 16, 53.13), {}, check)


def _case(name: str) -> Case:
    n = 4
    if name == "near_plane_exact":  # z == near is culled (strictly z > near is drawn)
        return Case(_at([0, 0, NEAR], [0.001, 0, NEAR], [0, 0, 1.0]), _camera(), {}, _culled([0, 1]))
    if name == "near_plane_just_inside":  # 1.5 near: a Gaussian about to be drawn with a huge Jacobian
        return Case(_at([0, 0, 1.5 * NEAR], [0.002, 0.001, 1.01 * NEAR]), _camera(), {})
    if name == "behind_near_plane":
        return Case(_at([0, 0, -1.0], [0, 0, 0.0], [0, 0, 0.5 * NEAR], [0.1, 0.1, -1e6]), _camera(), {},
                    lambda out, p, r: (_culled([0, 1, 2, 3])(out, p, r), _empty(out, p, r)))
    if name == "on_image_border":  # centres exactly on the edges and corners (x, y = 0 or W at z = 3)
        e = 3.0 * math.tan(math.radians(30))
        return Case(_at([-e, -e, 3], [e, e, 3], [0, e, 3], [e, 0, 3], [-e, 0, 3]), _camera(), {})
    if name == "far_outside_frustum":
        return Case(_at([1e6, 0, 3], [0, -1e7, 3], [0, 0, 1e7], [1e30, 1e30, 3], [0, 0, 3]), _camera(), {},
                    _culled([0, 1, 3]))
    if name == "scale_1e-10":  # of the extent 1: the 0.3 px blur keeps the 2-D covariance invertible
        return Case(_params(n, scales=torch.full((n, 3), math.log(1e-10))), _camera(), {})
    if name == "scale_1e4":
        return Case(_params(n, scales=torch.full((n, 3), math.log(1e4))), _camera(), {}, _covers_image)
    if name == "scale_overflow":  # 1e20: Sigma overflows float32 -> capped by render.scale_clamp
        return Case(_params(n, scales=torch.full((n, 3), math.log(1e20))), _camera(), {"render.scale_clamp": 3 * n},
                    _covers_image)
    if name == "scale_mixed_1e4_1e-10":  # a needle of extreme anisotropy
        return Case(_params(n, scales=torch.tensor([[math.log(1e4), math.log(1e-10), math.log(1e-10)]] * n)),
                    _camera(), {})
    if name == "quat_zero":  # rendered with the identity rotation, counted
        ident = torch.tensor([[1.0, 0, 0, 0]] * n)
        return Case(_params(n, quats=torch.zeros(n, 4)), _camera(), {"render.quat_zero": n},
                    reference=_params(n, quats=ident))
    if name in ("quat_norm_1e-20", "quat_norm_1e20"):  # the same rotation as the unit quaternion
        s = 1e-20 if name.endswith("-20") else 1e20
        return Case(_params(n, quats=lambda q: s * _unit(q)), _camera(), {"render.quat_rescale": n},
                    reference=_params(n, quats=_unit))
    if name == "opacity_logit_+80":
        return Case(_params(n, opacities=torch.full((n,), 80.0)), _camera(), {},
                    lambda out, p, r: (float(out.alpha.detach().max()) <= 1.0) or pytest.fail("alpha > 1"))
    if name == "opacity_logit_-80":
        return Case(_params(n, opacities=torch.full((n,), -80.0)), _camera(), {}, _empty)
    if name == "sh_coeffs_1e6":
        return Case(_params(n, sh0=torch.full((n, 1, 3), 1e6), shN=torch.full((n, 15, 3), -1e6)), _camera(), {})
    if name == "one_gaussian":
        return Case(_params(1), _camera(), {}, lambda out, p, r: out.radii.shape == (1, 1) or pytest.fail("shape"))
    if name == "many_on_one_tile":
        return _many_on_one_tile(2_000)  # with SH degree 3; 1e6 below
    if name == "image_1x1":
        return Case(_params(n), _camera(1, 1), {}, lambda out, p, r: out.rgb.shape == (1, 1, 3) or pytest.fail("shape"))
    if name == "image_1x4096":  # W = 4096, H = 1
        return Case(_params(n), _camera(4096, 1), {})
    if name == "image_4096x1":  # W = 1, H = 4096
        return Case(_params(n), _camera(1, 4096), {})
    if name == "fov_1deg":
        return Case(_params(n), _camera(fov_deg=1.0), {})
    if name == "fov_170deg":
        return Case(_params(n), _camera(fov_deg=170.0), {})
    if name == "camera_inside_gaussian":  # the camera sits 0.05 from a Gaussian of scale 1
        return Case(_params(2, means=torch.tensor([[0, 0, 0.05], [0.1, 0, 2.0]]), scales=torch.zeros(2, 3)),
                    _camera(), {}, _covers_image)
    raise KeyError(name)


RENDER_CASES = [
    "near_plane_exact", "near_plane_just_inside", "behind_near_plane", "on_image_border", "far_outside_frustum",
    "scale_1e-10", "scale_1e4", "scale_overflow", "scale_mixed_1e4_1e-10", "quat_zero", "quat_norm_1e-20",
    "quat_norm_1e20", "opacity_logit_+80", "opacity_logit_-80", "sh_coeffs_1e6", "one_gaussian", "many_on_one_tile",
    "image_1x1", "image_1x4096", "image_4096x1", "fov_1deg", "fov_170deg", "camera_inside_gaussian",
]

BACKENDS = [
    pytest.param("cpu", id="cpu"),
    pytest.param("torch", id="torch"),
    pytest.param("gsplat-cpu", id="gsplat-cpu"),
    pytest.param("gsplat", id="gsplat", marks=[pytest.mark.cuda, pytest.mark.skipif(
        not gsplat_available(), reason="gsplat needs CUDA and pip install -e '.[cuda]'")]),
]


@pytest.fixture
def backend(request):
    """The parametrized backend name; ``gsplat-cpu`` runs under the emulation of gsplat's kernels."""
    if request.param == "gsplat-cpu":
        request.getfixturevalue("gsplat_cpu")
    return request.param


def _renderer(backend: str) -> Renderer:
    return {"cpu": lambda: CPURenderer(near=NEAR), "torch": lambda: TorchRenderer(near=NEAR, device_name="cpu"),
            "gsplat-cpu": lambda: GsplatRenderer(near=NEAR, device_name="cpu"),
            "gsplat": lambda: GsplatRenderer(near=NEAR)}[backend]()


def _finite(name: str, t: Optional[torch.Tensor]) -> None:
    assert t is not None, f"{name} is missing"
    bad = ~torch.isfinite(t.detach())
    assert not bool(bad.any()), f"{name}: {int(bad.sum())} non-finite entries"


def _render_case(backend: str, case: Case, sh_degree: int = 3):
    r = _renderer(backend)
    dev = r.device
    cam = case.camera.to(dev)
    p = {k: v.detach().clone().to(dev).requires_grad_(True) for k, v in case.params.items()}
    before = guard_counts()
    out = r.render(p, cam, sh_degree=sh_degree, return_weights=r.supports_weights, retain_means2d_grad=True)
    fired = {k: v - before.get(k, 0) for k, v in guard_counts().items() if v != before.get(k, 0)}
    for name in ("rgb", "alpha", "depth", "means2d", "radii"):
        _finite(name, getattr(out, name))
    if r.supports_weights:
        _finite("weight_sum", out.weight_sum)
        _finite("weight_sq_sum", out.weight_sq_sum)
    target = torch.rand(out.rgb.shape, generator=torch.Generator().manual_seed(0)).to(dev)
    loss = ((out.rgb - target) ** 2).sum() + out.alpha.sum() + 1e-3 * out.depth.sum()
    loss.backward()
    for k, v in p.items():
        if k != "shN" or sh_degree > 0:  # degree 0 never reads shN
            _finite(f"grad of {k}", v.grad)
    if out.means2d_grad is not None:
        _finite("means2d grad", out.means2d_grad)
    return r, out, p, fired


@pytest.mark.parametrize("backend", BACKENDS, indirect=True)
@pytest.mark.parametrize("name", RENDER_CASES)
def test_renderer_extreme_input(name, backend):
    case = _case(name)
    r, out, p, fired = _render_case(backend, case)
    # our guards (gsplat renders behind the same ones): exactly the expected ones fire, each counted
    assert {k: v for k, v in fired.items() if k.startswith("render.")} == case.guards
    if case.check is not None:
        case.check(out, p, r)
    if case.reference is not None:
        ref = r.render({k: v.to(r.device) for k, v in case.reference.items()}, case.camera.to(r.device), sh_degree=3)
        torch.testing.assert_close(out.rgb.detach(), ref.rgb, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("backend", BACKENDS, indirect=True)
def test_renderer_very_many_gaussians_on_one_tile(backend):
    """1e6 Gaussians on one 16x16 tile: about 3 s forward + backward on the C++ backend (2 shared cores).
    The pure-torch rasterizer (and the CPU emulation of gsplat's) materialises (Gaussians x 256 pixels)
    tensors per tile, so 1e6 would need about 20 GB there; they run 1e4, within a few seconds."""
    n = 10_000 if backend in ("torch", "gsplat-cpu") else 1_000_000
    _render_case(backend, _many_on_one_tile(n), sh_degree=0)


# ------------------------------------------------------------------------------------------------
# trainer cases
# ------------------------------------------------------------------------------------------------
TINY = ["data.max_side=32", "+data.n_views=8", "+data.n_points=300", "trainer.max_steps=30",
        "trainer.eval_every=30", "trainer.checkpoint_every=1000", "trainer.save_renders=false", "logger=none",
        "trainer.enable_progress_bar=false", "strategy.refine_start=10", "strategy.refine_every=10",
        "strategy.refine_stop=25"]


def _walk_numbers(obj, path="metrics"):
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _walk_numbers(v, f"{path}.{k}")
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            yield from _walk_numbers(v, f"{path}[{i}]")
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
        yield path, float(obj)


def _check_run(run_dir: Path) -> dict:
    """metrics.json finite and its guards well-formed; every tensor of the final checkpoint finite."""
    metrics = json.loads((run_dir / "metrics.json").read_text())
    bad = [p for p, v in _walk_numbers(metrics) if not math.isfinite(v)]
    assert not bad, bad
    guards = metrics["numerical_guards"]
    assert isinstance(guards, dict) and all(isinstance(v, int) and v > 0 for v in guards.values()), guards
    ck = torch.load(run_dir / "checkpoints" / "last.ckpt", weights_only=False, map_location="cpu")
    for k, v in ck["state_dict"].items():
        if torch.is_tensor(v) and v.is_floating_point():
            _finite(f"final {k}", v)
    assert metrics["num_gaussians"] >= 1
    assert metrics["psnr"] is not None and math.isfinite(metrics["psnr"])
    return metrics


def _patch_synthetic(monkeypatch, scale: float = 1.0, view_image: Optional[float] = None) -> None:
    """Make ``data=synthetic`` load the procedural scene scaled by ``scale`` (poses and points) and,
    with ``view_image``, the first training view's image filled with that value."""
    import b3dgs.data.synthetic as syn

    original = syn.load_synthetic

    @functools.wraps(original)  # the same signature: config validation reads the loader's keywords
    def load(**kw):
        raw = original(**kw)
        cams = []
        for i, c in enumerate(raw.cameras):
            vm = c.viewmat.clone()
            vm[:3, 3] *= scale
            img = c.image
            if view_image is not None and i == 1:  # view 0 is a test view (test_every=8)
                img = torch.full_like(img, view_image)
            cams.append(replace(c, viewmat=vm, image=img))
        raw.cameras = cams
        if raw.points is not None:
            raw.points = np.asarray(raw.points) * scale
        return raw

    monkeypatch.setattr(syn, "load_synthetic", load)


@pytest.fixture
def run_train():
    from test_train import run_train

    return run_train


@pytest.mark.parametrize("renderer", ["cpu", "torch", pytest.param("gsplat-cpu", marks=pytest.mark.slow)])
@pytest.mark.parametrize("value", [0.0, 1.0], ids=["all_black_view", "all_white_view"])
def test_trainer_constant_training_view(tmp_path, monkeypatch, request, run_train, value, renderer):
    _patch_synthetic(monkeypatch, view_image=value)
    if renderer == "gsplat-cpu":
        request.getfixturevalue("gsplat_cpu")
    run_train(tmp_path, TINY + (["renderer=gsplat", "renderer.device_name=cpu"] if renderer == "gsplat-cpu"
                                else [f"renderer={renderer}"]))
    _check_run(tmp_path)


def test_trainer_dp_prunes_every_gaussian_in_one_step(tmp_path, run_train):
    """prune_activity > 1 makes every activity gate fall below the threshold at the first CAVI step:
    DP prunes all Gaussians at once; the topology op keeps one, and says so in numerical_guards."""
    run_train(tmp_path, TINY + ["renderer=cpu", "posterior=[dp]", "posterior.dp.t_dp=5", "posterior.dp.cavi_every=5",
                                "posterior.dp.prune_activity=2.0"])
    m = _check_run(tmp_path)
    assert m["numerical_guards"].get("ops.prune_keep_one", 0) >= 1, m["numerical_guards"]
    assert m["removed"].get("dp", 0) >= 250, m["removed"]  # about all of the ~290 initial Gaussians


@pytest.mark.parametrize("normalize", [True, False], ids=["normalized", "raw"])
@pytest.mark.parametrize("scale", [1e6, 1e-6], ids=["scene_x1e6", "scene_x1e-6"])
def test_trainer_scaled_scene(tmp_path, monkeypatch, run_train, scale, normalize):
    _patch_synthetic(monkeypatch, scale=scale)
    over = TINY + ["renderer=cpu", f"data.normalize={str(normalize).lower()}"]
    if scale < 1 and not normalize:
        # extent ~4e-6: everything inside the near plane 0.01; refused before training, with the fix named
        with pytest.raises(B3dgsError, match="near plane") as e:
            run_train(tmp_path, over)
        assert "normalize=true" in str(e.value)
        return
    run_train(tmp_path, over)
    m = _check_run(tmp_path)
    assert m["psnr"] > 8.0, m["psnr"]  # it rendered something, not a black image from culled Gaussians
