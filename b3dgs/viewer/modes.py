"""What the viewer draws: one image per render mode, with a colour map on a fixed, stated scale.

Modes (:data:`MODES`): ``rgb``; ``depth`` and ``alpha`` (the renderer's own outputs); ``native_sigma`` (σ of
S posterior re-renders, ``uq=native``, for a run with posterior blocks: NIW or DPMM);
``proxy_sigma`` (σ of S position-jittered re-renders, ``uq=proxy``, any run); ``sh_sigma``
(σ of S re-renders drawing only the SH coefficients from the directional SH posterior, ``uq=sh``, any run rendered at
SH degree >= 1); and three
per-Gaussian overlays: ``dp_activity`` (E[a_k] of the DP block), ``pos_std`` (the NIW posterior's position
standard deviation √(tr Var[μ_k] / 3), log scale) and ``opacity`` (σ(o_k)).

A per-Gaussian overlay renders the Gaussians with their value as a grey colour over black, so the pixel holds
Σ_k w_k v_k and α = Σ_k w_k; the map shows v̄ = Σ_k w_k v_k / α, the compositing-weighted mean of the
values along the ray, where α ≥ :data:`MIN_ALPHA` (elsewhere the background colour). Scalar maps are never
normalised per frame: each mode has one range for the session, stated in its legend (depth's from the
scene's cameras, σ's from ``sigma_max``; the viewer sets σ's from its first frame, :func:`robust_max`), so two
views or two moments compare.

Nothing here imports viser: :class:`ModeRenderer` renders for tests and scripts as well.
"""
from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, replace
from typing import Optional

import numpy as np
import torch
from torch import Tensor

from b3dgs.errors import B3dgsError
from b3dgs.types import Camera, Scene

__all__ = ["MIN_ALPHA", "MODES", "SIGMA_MODES", "Frame", "ModeRenderer", "ModeSpec", "colorize", "colormap_lut", "robust_max"]

#: the modes that show a σ of re-renders (one fitted UQ regime each; their scale is set together)
SIGMA_MODES = ("native_sigma", "proxy_sigma", "sh_sigma")
#: pixels whose accumulated α is below this show the background colour in depth and overlay modes
MIN_ALPHA = 0.05
BACKGROUND = (24, 24, 28)  # uint8 colour of "no value" pixels


@dataclass(frozen=True)
class ModeSpec:
    """One render mode: ``kind`` rgb | pixel (a per-pixel scalar) | gaussian (a per-Gaussian overlay);
    the value range [lo, hi] (log10 applied first when ``log``) maps onto colour map ``cmap``."""

    key: str
    label: str
    kind: str
    cmap: str = "viridis"
    lo: float = 0.0
    hi: float = 1.0
    log: bool = False
    unit: str = ""
    what: str = ""

    def scale_text(self) -> str:
        """The fixed scale in words, e.g. ``"0 to 0.03 (RGB, per channel), linear, colour map inferno; fixed for the session"``."""
        if self.kind == "rgb":
            return "the rendered colour"
        scale = "log scale" if self.log else "linear"
        unit = f" {self.unit}" if self.unit else ""
        return f"{self.lo:.3g} to {self.hi:.3g}{unit}, {scale}, colour map {self.cmap}; fixed for the session"


MODES: dict[str, ModeSpec] = {m.key: m for m in (
    ModeSpec("rgb", "RGB", "rgb", what="the point-estimate render"),
    ModeSpec("depth", "Depth", "pixel", "turbo", 0.0, 1.0, unit="scene units",
             what="expected depth Σ w z / α (range: 0 to twice the farthest camera's distance from the scene centre)"),
    ModeSpec("alpha", "Alpha", "pixel", "gray", 0.0, 1.0, what="accumulated opacity α = Σ w"),
    ModeSpec("native_sigma", "Native σ", "pixel", "inferno", 0.0, 0.03, unit="(RGB, per channel)",
             what="σ = √u_p of S posterior re-renders (Eq. 4), epistemic part; needs posterior blocks (niw, dpmm)"),
    ModeSpec("proxy_sigma", "Proxy σ", "pixel", "inferno", 0.0, 0.03, unit="(RGB, per channel)",
             what="σ of S re-renders with every centre jittered by N(0, (jitter·extent)²)"),
    ModeSpec("sh_sigma", "SH σ (directional)", "pixel", "inferno", 0.0, 0.03, unit="(RGB, per channel)",
             what="σ of S re-renders drawing only each Gaussian's SH coefficients from the directional SH posterior "
                  "(uq=sh, posterior.sh; beyond the paper): high where a colour is seen from a side no training "
                  "camera looked from; needs SH degree >= 1"),
    ModeSpec("dp_activity", "DP activity E[a_k]", "gaussian", "viridis", 0.0, 1.0,
             what="the DP block's expected activity per Gaussian; needs the dp block (dpmm)"),
    ModeSpec("pos_std", "Posterior position std", "gaussian", "magma", 1e-5, 1e-2, log=True,
             unit="× scene extent", what="√(tr Var[μ_k]/3) of the NIW posterior per Gaussian; needs the niw block"),
    ModeSpec("opacity", "Opacity", "gaussian", "viridis", 0.0, 1.0, what="σ(o_k) per Gaussian"),
)}


@functools.cache
def colormap_lut(name: str) -> np.ndarray:
    """(256, 3) uint8 table of a matplotlib colour map."""
    import matplotlib

    cmap = matplotlib.colormaps[name]
    return (np.asarray(cmap(np.linspace(0.0, 1.0, 256)))[:, :3] * 255.0 + 0.5).astype(np.uint8)


def normalise(values: Tensor, spec: ModeSpec) -> Tensor:
    """``values`` mapped onto [0, 1] by the mode's fixed range (clipped)."""
    v = values.double()
    lo, hi = spec.lo, spec.hi
    if spec.log:
        v, lo, hi = v.clamp_min(1e-30).log10(), math.log10(lo), math.log10(hi)
    return ((v - lo) / (hi - lo)).clamp(0.0, 1.0)


def robust_max(values: Tensor, q: float = 99.0, mask: Optional[Tensor] = None) -> Optional[float]:
    """The top of an automatic colour scale: the ``q``-th percentile of ``values`` (where ``mask``), rounded up to two
    significant digits; None when there is nothing positive to scale."""
    v = values.detach().float().cpu()
    v = v[mask.cpu()] if mask is not None else v.reshape(-1)
    v = v[torch.isfinite(v)]
    if v.numel() == 0:
        return None
    top = float(torch.quantile(v[:: max(1, v.numel() // 1_000_000)], q / 100.0))
    if not top > 0:
        return None
    exp = math.floor(math.log10(top)) - 1
    return round(math.ceil(top / 10.0 ** exp) * 10.0 ** exp, max(0, -exp))


def colorize(unit: Tensor, cmap: str, mask: Optional[Tensor] = None) -> np.ndarray:
    """(H, W) values in [0, 1] -> (H, W, 3) uint8 through ``cmap``; pixels where ``mask`` is False get
    :data:`BACKGROUND`."""
    idx = (unit.detach().cpu().double().nan_to_num(0.0).clamp(0, 1) * 255.0).round().long().numpy()
    out = colormap_lut(cmap)[idx]
    if mask is not None:
        out[~mask.detach().cpu().numpy()] = BACKGROUND
    return out


@dataclass
class Frame:
    """One rendered image: ``image`` (H, W, 3) uint8 to show; ``values`` the scalar map in the mode's units
    (None for RGB); ``mask`` the pixels that hold a value; ``seconds`` the render + colour-map time."""

    mode: ModeSpec
    image: np.ndarray
    values: Optional[Tensor]
    mask: Optional[Tensor]
    seconds: float
    samples: Optional[int] = None


class ModeRenderer:
    """Renders any :data:`MODES` entry of a trained :class:`~b3dgs.module.SplatModule` from any camera with
    the module's own renderer. The σ modes reuse the UQ regimes of ``b3dgs-eval`` (fitted once, lazily);
    per-Gaussian values come from the posterior blocks' ``export`` (:meth:`SplatModule.export_extras`)."""

    def __init__(self, module, scene: Scene, samples: int = 16, jitter: float = 0.002, sigma_max: float = 0.03,
                 depth_max: Optional[float] = None, seed: int = 0, count_scale: Optional[float] = 0.1) -> None:
        if samples < 2:
            raise B3dgsError(f"viewer samples must be >= 2 (a spread needs two draws), got {samples}",
                             fix="pass samples >= 2 (b3dgs-view samples=16 is the default)")
        if not sigma_max > 0:
            raise B3dgsError(f"viewer sigma_max must be > 0, got {sigma_max}",
                             fix="pass sigma_max > 0 (b3dgs-view sigma_max=0.03 in RGB units), or null for the "
                                 "automatic scale")
        if count_scale is not None and not (0 < float(count_scale) < float("inf")):
            raise B3dgsError(f"viewer count_scale must be a finite number > 0 or None, got {count_scale}",
                             fix="pass count_scale as a finite number > 0 (b3dgs-view count_scale=0.1, as uq=native "
                                 "uses), or null for the model's own counts")
        # native σ draws with N̂ <- count_scale·N̂, the default of uq=native (conf/uq/native.yaml), so the viewer shows
        # what b3dgs-eval scores; None: the model's own posterior
        self.count_scale = None if count_scale is None else float(count_scale)
        self.module, self.scene = module, scene
        self.samples, self.jitter, self.seed = int(samples), float(jitter), int(seed)
        self.extras = {k: v.detach().cpu() for k, v in module.export_extras().items()}
        self.extent = float(scene.extent)
        far = depth_max if depth_max is not None else default_depth_max(scene)
        self.specs = dict(MODES)
        self.specs["depth"] = replace(MODES["depth"], hi=float(far))
        self.set_sigma_max(sigma_max)
        blocks = list(module.posterior)
        if blocks:  # say what native σ draws: every block of the model (Eq. 4 is the geometry's)
            sh = " and the directional SH posterior (beyond the paper)" if "sh" in blocks else ""
            self.specs["native_sigma"] = replace(
                self.specs["native_sigma"], what=f"σ = √u_p of S posterior re-renders drawing every block of the model "
                f"({', '.join(blocks)}): Eq. 4 for the geometry{sh}; epistemic part")
        self._regimes: dict[str, object] = {}
        self._overlay_params: dict[str, dict[str, Tensor]] = {}

    # ------------------------------------------------------------------ what is available
    def unavailable(self) -> dict[str, str]:
        """Mode key -> why this run cannot show it."""
        out = {}
        if not self.module.posterior:
            out["native_sigma"] = f"model={self.module.hparams.name} has no posterior blocks (train model=niw or dpmm)"
        if self.module.active_sh_degree() < 1:
            out["sh_sigma"] = "the run renders SH degree 0 (a colour without direction); train with model.sh_degree >= 1"
        if "dp_e_a" not in self.extras:
            out["dp_activity"] = "the run has no DP block (model=dpmm has one)"
        if "niw_pos_var" not in self.extras:
            out["pos_std"] = "the run has no NIW block (model=niw and dpmm have one)"
        return out

    def available(self) -> list[str]:
        gone = self.unavailable()
        return [k for k in self.specs if k not in gone]

    def set_sigma_max(self, sigma_max: float) -> None:
        for k in SIGMA_MODES:
            self.set_scale(k, sigma_max)

    def set_scale(self, mode: str, hi: float) -> None:
        """The top of ``mode``'s colour scale (its values map onto [lo, hi])."""
        self.specs[mode] = replace(self.specs[mode], hi=float(hi))

    # ------------------------------------------------------------------ rendering
    @torch.no_grad()
    def render(self, mode: str, camera: Camera, samples: Optional[int] = None,
               generator: Optional[torch.Generator] = None) -> Frame:
        """Render ``mode`` from ``camera`` (any size and intrinsics); ``samples`` overrides the σ modes' S."""
        if mode not in self.specs:
            raise B3dgsError(f"unknown viewer mode {mode!r} (modes: {', '.join(self.specs)})",
                             fix=f"pass one of the modes: {', '.join(self.specs)} (b3dgs-view mode=...)")
        why = self.unavailable().get(mode)
        if why is not None:
            raise B3dgsError(f"mode {mode} is not available for this run: {why}",
                             fix=f"pick an available mode ({', '.join(self.available())}), or train a run that has "
                                 "this one")
        spec = self.specs[mode]
        t0 = time.perf_counter()
        m = self.module
        if spec.kind == "rgb":
            rgb = m.render_eval(camera).cpu()
            img = (rgb.numpy() * 255.0 + 0.5).astype(np.uint8)
            return Frame(spec, img, None, None, time.perf_counter() - t0)
        s = None
        if mode in ("depth", "alpha"):
            out = m.render_camera(camera)
            alpha = out.alpha.detach().cpu()
            values, mask = (alpha, None) if mode == "alpha" else (out.depth.detach().cpu(), alpha >= MIN_ALPHA)
        elif mode in SIGMA_MODES:
            s = int(samples or self.samples)
            values, mask = self.sigma(mode, camera, s, generator), None
        else:
            values, mask = self.overlay(mode, camera)
        img = colorize(normalise(values, spec), spec.cmap, mask)
        return Frame(spec, img, values, mask, time.perf_counter() - t0, s)

    def regime(self, mode: str):
        """The fitted UQ regime behind a σ mode ``<name>_sigma``: ``conf/uq/<name>.yaml`` (b3dgs-eval's
        ``uq=[<name>]``) with the viewer's S, count scale (native) and jitter (proxy); fitted on first use."""
        if mode not in self._regimes:
            from hydra.utils import instantiate

            from b3dgs.confs import compose_config

            name = mode.removesuffix("_sigma")
            node = compose_config("eval", [f"uq=[{name}]", f"uq.samples={self.samples}"]).uq[name]
            own = {"native": {"count_scale": self.count_scale}, "proxy": {"jitter": self.jitter}}.get(name, {})
            reg = instantiate(node, chunk=8, **own)
            reg.fit([self.module], self.scene)
            self._regimes[mode] = reg
        return self._regimes[mode]

    def sigma(self, mode: str, camera: Camera, samples: int, generator: Optional[torch.Generator] = None) -> Tensor:
        """(H, W) σ = √u_p (epistemic spread of ``samples`` re-renders, RGB units per channel)."""
        reg = self.regime(mode)
        reg.samples, reg.chunk = int(samples), min(int(samples), 8)
        gen = generator if generator is not None else torch.Generator().manual_seed(self.seed)
        if mode in ("native_sigma", "sh_sigma"):
            _, u = reg.spread(camera, gen)
        else:
            u = reg.predict(camera, gen).epistemic
        return u.detach().cpu().clamp_min(0).sqrt()

    def gaussian_values(self, mode: str) -> Tensor:
        """(N,) per-Gaussian values of an overlay mode in its own units."""
        if mode == "opacity":
            return torch.sigmoid(self.module.splats["opacities"].detach()).cpu()
        if mode == "dp_activity":
            return self.extras["dp_e_a"].float()
        if mode == "pos_std":
            return self.extras["niw_pos_var"].clamp_min(0).sqrt().float() / self.extent
        raise B3dgsError(f"{mode} is not a per-Gaussian mode",
                         fix="pass a per-Gaussian mode: opacity, dp_activity or pos_std")

    def _overlay(self, mode: str) -> dict[str, Tensor]:
        """The Gaussians with their normalised value as a grey SH-0 colour (cached per mode)."""
        if mode not in self._overlay_params:
            from b3dgs.render.projection import rgb_to_sh0

            m = self.module
            p = {k: v.detach() for k, v in m.params().items()}
            unit = normalise(self.gaussian_values(mode), self.specs[mode]).float().to(p["sh0"].device)
            p["sh0"] = rgb_to_sh0(unit)[:, None, None].expand(-1, 1, 3).contiguous()
            p["shN"] = torch.zeros_like(p["shN"])
            self._overlay_params[mode] = p
        return self._overlay_params[mode]

    def overlay(self, mode: str, camera: Camera) -> tuple[Tensor, Tensor]:
        """(values (H, W) in the mode's units, mask α ≥ MIN_ALPHA) of a per-Gaussian overlay."""
        m = self.module
        zero = torch.zeros(3, dtype=torch.float32, device=m.bg.device)
        out = m.renderer.render(self._overlay(mode), m.device_camera(camera), sh_degree=0, background=zero)
        alpha = out.alpha.detach().cpu()
        unit = (out.rgb[..., 0].detach().cpu() / alpha.clamp_min(1e-6)).clamp(0, 1)
        spec = self.specs[mode]
        if spec.log:
            lo, hi = math.log10(spec.lo), math.log10(spec.hi)
            values = 10.0 ** (lo + unit.double() * (hi - lo))
        else:
            values = spec.lo + unit.double() * (spec.hi - spec.lo)
        return values.float(), alpha >= MIN_ALPHA


def default_depth_max(scene: Scene) -> float:
    """Twice the largest distance of a camera centre from the scene centre (the normalised origin)."""
    cams = list(scene.train) + list(scene.test) + list(getattr(scene, "candidates", None) or [])
    if not cams:
        return 2.0 * float(scene.extent)
    d = max(float(c.center.norm()) for c in cams)
    return float(f"{2.0 * max(d, 1e-3):.2g}")
