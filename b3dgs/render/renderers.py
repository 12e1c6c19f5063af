"""Renderer plugins: one object per backend, selected with ``renderer=auto|cpu|torch|gsplat``.

Every renderer offers the same contract, so the trainer, the posterior blocks, the UQ regimes and
the benchmarks never ask which backend they hold:

- ``render(params, camera, sh_degree=, background=, return_weights=, retain_means2d_grad=)``
  returns a :class:`~b3dgs.render.render.RenderOutput` ((S, N) per-Gaussian tensors; images
  (H, W, …), or (S, H, W, …) when a parameter carries a sample dimension S);
- ``ssim(pred, gt)``: the differentiable SSIM it prefers for the training loss;
- ``device``: where the splats must live;
- the capabilities it declares (``supports_weights``, ``supports_means2d_grad``, ``supports_samples``).

``CPURenderer`` runs our C++/OpenMP kernels, ``TorchRenderer`` the pure-PyTorch reference (any
device), ``GsplatRenderer`` gsplat's CUDA rasterizer. :func:`auto_renderer` picks gsplat when CUDA
and gsplat are present, else the C++ backend, else torch, and says which and why.
"""
from __future__ import annotations

import importlib.util
import logging
from dataclasses import dataclass
from typing import Any, ClassVar, Mapping, Optional

import torch
from torch import Tensor

from b3dgs.errors import B3dgsError
from b3dgs.render._ext import RendererUnavailable, first_compiler_error
from b3dgs.render.gsplat_backend import gsplat_emulated
from b3dgs.render.render import RenderOutput, render
from b3dgs.schema import is_int, is_number
from b3dgs.types import Camera

log = logging.getLogger(__name__)


def _check_device(name: Any, options: str) -> None:
    """Refuse a ``renderer.device_name`` that torch cannot parse as a device."""
    try:
        torch.device(str(name))
    except (RuntimeError, TypeError):
        raise B3dgsError(f"renderer.device_name={name} is not a device", f"pass renderer.device_name={options}") from None


@dataclass
class Renderer:
    """Base of the renderer plugins. ``near``: near-plane depth (scene units) below which Gaussians are culled."""

    near: float = 0.01

    name: ClassVar[str] = "base"
    supports_weights: ClassVar[bool] = True  # per-Gaussian Σ_p w_kp and Σ_p w_kp² on request
    supports_means2d_grad: ClassVar[bool] = True  # gradient of the 2-D means (densification)
    supports_samples: ClassVar[bool] = True  # parameters with a leading sample dimension S
    max_alpha: ClassVar[float] = 0.99  # the compositing cap of α
    cpu_seconds_per_step: ClassVar[Optional[float]] = None  # stated training cost on the CPU (a long run is warned of)

    def __post_init__(self) -> None:
        self.validate()  # wherever it is built: Hydra's instantiate, make_renderer, auto_renderer, code

    def validate(self, **kwargs: Any) -> None:
        """Check this renderer's own field values; raise :class:`B3dgsError` naming the key and the fix. Called when
        the renderer is built (``__post_init__``); a subclass with fields of its own extends it (``super().validate()``
        first). ``kwargs``: nothing yet (accepted for what later versions pass)."""
        if not (is_number(self.near) and self.near > 0):
            raise B3dgsError(f"renderer.near={self.near} is invalid: it must be a positive number",
                             "pass renderer.near=0.01, and data.normalize=true so that the scene's extent is 1")

    @property
    def device(self) -> torch.device:
        raise NotImplementedError  # protocol: an abstract method (subclasses implement it)

    def check_available(self) -> None:
        """Raise :class:`RendererUnavailable` (naming the fix) if this renderer cannot run here."""

    def render(self, params: Mapping[str, Tensor], camera: Camera, *, sh_degree: int = 3,
               background: Optional[Tensor] = None, return_weights: bool = False,
               retain_means2d_grad: bool = False) -> RenderOutput:
        raise NotImplementedError  # protocol: an abstract method (subclasses implement it)

    def ssim(self, pred: Tensor, gt: Tensor) -> Tensor:
        from b3dgs.render.ssim import ssim_separable

        return ssim_separable(pred, gt)

    def describe(self) -> dict[str, Any]:
        """What metrics.json records about the renderer."""
        return {"name": self.name, "device": str(self.device), "near": self.near, "max_alpha": self.max_alpha}


@dataclass
class CPURenderer(Renderer):
    """Our C++/OpenMP kernels (projection + SH, binning, rasterizer, fused SSIM), deterministic for any
    thread count. Compiled on first use into ``~/.cache/b3dgs/ext``."""

    name: ClassVar[str] = "cpu"

    @property
    def device(self) -> torch.device:
        return torch.device("cpu")

    def check_available(self) -> None:
        from b3dgs.render._ext import load_extension

        try:
            load_extension()
        except RuntimeError as e:
            raise RendererUnavailable(f"renderer=cpu: the C++ extension did not build ({first_compiler_error(str(e))})",
                                      "renderer=torch, or install a C++ compiler with OpenMP") from e

    def render(self, params, camera, *, sh_degree=3, background=None, return_weights=False,
               retain_means2d_grad=False) -> RenderOutput:
        return render(params, camera, sh_degree=sh_degree, background=background, backend="cpu",
                      return_weights=return_weights, retain_means2d_grad=retain_means2d_grad, near=self.near)

    def ssim(self, pred: Tensor, gt: Tensor) -> Tensor:
        from b3dgs.render.ssim import ssim_fused

        return ssim_fused(pred, gt)


@dataclass
class TorchRenderer(Renderer):
    """The pure-PyTorch reference (float64 ``gradcheck``-able), on the CPU or a CUDA device.
    ``device``: ``auto`` (CUDA when available), ``cpu``, ``cuda`` or ``cuda:N``."""

    device_name: str = "auto"  # auto (CUDA when available) | cpu | cuda | cuda:N
    name: ClassVar[str] = "torch"
    cpu_seconds_per_step: ClassVar[Optional[float]] = 1.0  # at 256 px on 2 cores (renderer=cpu: ~40x less)

    def validate(self, **kwargs: Any) -> None:
        super().validate(**kwargs)
        if self.device_name != "auto":
            _check_device(self.device_name, "auto, cpu, cuda or cuda:N")

    @property
    def device(self) -> torch.device:
        if self.device_name == "auto":
            return torch.device("cuda" if torch.cuda.is_available() else "cpu")
        return torch.device(self.device_name)

    def check_available(self) -> None:
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise RendererUnavailable(f"renderer=torch: device {self.device_name} requested but CUDA is not available",
                                      "renderer.device_name=cpu or auto")

    def render(self, params, camera, *, sh_degree=3, background=None, return_weights=False,
               retain_means2d_grad=False) -> RenderOutput:
        return render(params, camera, sh_degree=sh_degree, background=background, backend="torch",
                      return_weights=return_weights, retain_means2d_grad=retain_means2d_grad, near=self.near)


def gsplat_available() -> bool:
    return torch.cuda.is_available() and importlib.util.find_spec("gsplat") is not None


@dataclass
class GsplatRenderer(Renderer):
    """gsplat's CUDA rasterizer (``pip install -e ".[cuda]"``), unpacked layout (``packed=False``).

    S posterior samples are one call with a leading batch dimension (``covars=`` for covariance
    draws). Per-Gaussian weight sums, which gsplat does not return, come from its per-pixel
    intersection list (:func:`b3dgs.render.gsplat_backend.weight_sums`) and are computed only when
    asked for. Near plane, zero quaternions and culled outputs follow our contract, and the Jacobian clamp
    is the same in every backend; gsplat's opacity-aware radii and α cap 0.999 (ours 0.99) remain, with
    their measured sizes in :mod:`b3dgs.render.gsplat_backend`. On an
    unsaturated scene it agrees with ``renderer=torch`` to 1e-5 (images, weight sums, gradients).
    ``device_name=cpu`` is accepted only under the test suite's CPU emulation of gsplat's kernels.
    """

    device_name: str = "cuda"
    tile_size: int = 16
    eps2d: float = 0.3  # the screen-space blur added to every 2-D covariance (ours: 0.3 px)
    name: ClassVar[str] = "gsplat"
    max_alpha: ClassVar[float] = 0.999

    def validate(self, **kwargs: Any) -> None:
        super().validate(**kwargs)
        _check_device(self.device_name, "cuda or cuda:N")
        if not is_int(self.tile_size, 1, 33):
            raise B3dgsError(f"renderer.tile_size={self.tile_size} is invalid: it must be an integer in [1, 32] (gsplat "
                             "runs one CUDA block of tile_size² threads per tile, at most 1024)",
                             "pass renderer.tile_size=16, gsplat's default")
        if not (is_number(self.eps2d) and self.eps2d >= 0):
            raise B3dgsError(f"renderer.eps2d={self.eps2d} is invalid: it must be a finite number >= 0 (pixels of blur "
                             "added to every 2-D covariance)", "pass renderer.eps2d=0.3, as our backends use")

    @property
    def device(self) -> torch.device:
        return torch.device(self.device_name)

    def check_available(self) -> None:
        if self.device.type == "cpu":
            if not gsplat_emulated():
                raise RendererUnavailable("renderer=gsplat renderer.device_name=cpu runs only under the test suite's "
                                          "CPU emulation of gsplat's kernels", "renderer=cpu on the CPU")
            return
        if not torch.cuda.is_available():
            raise RendererUnavailable("renderer=gsplat needs a CUDA GPU, and none is visible here",
                                      "pass renderer=cpu or renderer=auto, which picks the C++ CPU backend here")
        if importlib.util.find_spec("gsplat") is None:
            raise RendererUnavailable("renderer=gsplat: gsplat is not installed", 'pip install -e ".[cuda]"')

    def render(self, params, camera, *, sh_degree=3, background=None, return_weights=False,
               retain_means2d_grad=False) -> RenderOutput:
        from b3dgs.render.gsplat_backend import render_gsplat

        return render_gsplat(params, camera, sh_degree=sh_degree, background=background,
                             return_weights=return_weights, retain_means2d_grad=retain_means2d_grad,
                             near=self.near, tile_size=self.tile_size, eps2d=self.eps2d)


def auto_renderer(near: float = 0.01) -> Renderer:
    """gsplat when CUDA and gsplat are available, else the C++ backend, else the torch reference.

    A failed C++ build is never silent: one warning names the compiler error and the fallback.
    """
    if gsplat_available():
        chosen: Renderer = GsplatRenderer(near=near)
        reason = "CUDA and gsplat are available"
    else:
        cpu = CPURenderer(near=near)
        try:
            cpu.check_available()
            chosen, reason = cpu, ("no CUDA GPU" if not torch.cuda.is_available()
                                   else 'CUDA without gsplat (pip install -e ".[cuda]" for the fast path)')
        except RendererUnavailable as e:
            from b3dgs.render._ext import warn_fallback

            chosen = TorchRenderer(near=near)
            reason = "the C++ extension did not build"
            warn_fallback(e.__cause__ or e, "renderer=auto falls back to renderer=torch (pure PyTorch, about 40x "
                                            "slower on the CPU; fix the compiler error above for the fast path)")
    said = f"renderer=auto -> {chosen.name} on {chosen.device} ({reason})"
    if said not in _SAID:  # once per process: studies and evaluations build many renderers
        _SAID.add(said)
        log.info(said)
    return chosen


_SAID: set[str] = set()


RENDERERS = {"cpu": CPURenderer, "torch": TorchRenderer, "gsplat": GsplatRenderer, "auto": auto_renderer}


def make_renderer(spec: "str | Renderer") -> Renderer:
    """A renderer object from itself or from its option name (``auto``, ``cpu``, ``torch``, ``gsplat``)."""
    if isinstance(spec, Renderer):
        return spec
    if spec not in RENDERERS:
        raise B3dgsError(f"unknown renderer {spec!r}", f"renderer= one of {sorted(RENDERERS)}")
    return RENDERERS[spec]()
