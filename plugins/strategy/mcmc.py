"""3DGS-MCMC (Kheradmand et al. 2024): Gaussians as samples of a Markov chain, SGLD-style position noise,
relocation of dead Gaussians and growth to a fixed cap, in place of adaptive density control."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Optional

import torch
from torch import Tensor

from b3dgs.errors import B3dgsError, check_field, field_default
from b3dgs.plugin import Plugin
from b3dgs.render.projection import quat_to_rotmat


def relocation(opacity: Tensor, scale: Tensor, copies: Tensor) -> tuple[Tensor, Tensor]:
    """Opacity and scale of each of ``copies`` Gaussians that together replace one (paper Eq. 9).

    o' = 1 - (1 - o)^(1/n) keeps the opacity at the centre: 1 - (1 - o')^n = o. The scale factor
    o / Σ_{i=1..n} Σ_{k=0..i-1} C(i-1, k) (-1)^k o'^(k+1) / √(k+1) keeps the integral of the composited
    opacity profile (exact in 1-D). ``opacity`` (M,), ``scale`` (M, 3) linear scales, ``copies`` (M,) >= 1.
    Plain torch in float64 (the alternating sum cancels); CPU and CUDA alike.
    """
    if opacity.dim() != 1 or scale.shape != (opacity.shape[0], 3) or copies.shape != opacity.shape:
        raise B3dgsError(f"relocation: opacity (M,), scale (M, 3), copies (M,); got {tuple(opacity.shape)}, "
                         f"{tuple(scale.shape)}, {tuple(copies.shape)}",
                         fix="pass opacity (M,), scale (M, 3) and copies (M,) for the same M Gaussians")
    o = opacity.double().clamp(1e-12, 1 - 1e-12)
    n = copies.double().clamp_min(1)
    o_new = 1 - torch.pow(1 - o, 1 / n)
    n_max = int(copies.max()) if copies.numel() else 1
    denom = torch.zeros_like(o)
    for i in range(1, n_max + 1):
        active = n >= i
        for k in range(i):
            term = math.comb(i - 1, k) * (-1) ** k * o_new.pow(k + 1) / math.sqrt(k + 1)
            denom = denom + torch.where(active, term, torch.zeros_like(term))
    factor = (o / denom).unsqueeze(-1)
    return o_new.to(opacity.dtype), (scale.double() * factor).to(scale.dtype)


@dataclass
class MCMCStrategy(Plugin):
    """3DGS-MCMC densification.

    - Every step: position noise μ += lr_μ · ``noise_lr`` · σ(-k (o - t)) · Σ η, η ~ N(0, I) (SGLD; k = 100,
      t = ``min_opacity``: only near-transparent Gaussians move far), Σ the Gaussian's covariance.
    - Every ``refine_every`` steps in [``refine_start``, ``refine_stop``): the dead Gaussians (opacity <=
      ``min_opacity``) are moved onto live ones drawn ∝ opacity, and the set grows by ``grow_rate`` up to
      ``cap_max`` the same way; each drawn source and its copies get the opacity and scale of :func:`relocation`,
      and their Adam moments are zeroed.
    - Regularisers ``opacity_reg`` · mean(o) + ``scale_reg`` · mean(s) in the loss (``info["loss_terms"]``).
    Draws use torch's global generator on the splats' device (seeded and checkpointed with the run).
    """

    per_gaussian_state: ClassVar[tuple[str, ...]] = ()

    cap_max: int = 50000  # the same budget as the standard strategy's quick-protocol max_gaussians at 256 px
    noise_lr: float = 5.0e5
    refine_start: int = 250
    refine_stop: int = 2500
    refine_every: int = 100
    min_opacity: float = 0.005
    grow_rate: float = 0.05
    opacity_reg: float = 0.01
    scale_reg: float = 0.01

    def validate(self, **kwargs) -> None:
        check_field(self, "strategy.cap_max", not self.cap_max < 1, ">= 1", "as a positive count of Gaussians",
                    got=True)
        if self.refine_every <= 0 or self.refine_start < 0 or self.refine_stop < self.refine_start:
            raise B3dgsError("strategy.refine_every must be > 0 and 0 <= strategy.refine_start <= strategy.refine_stop",
                             fix="pass strategy.refine_every > 0 and 0 <= strategy.refine_start <= "
                                 f"strategy.refine_stop, e.g. the defaults {field_default(self, 'refine_every')}, "
                                 f"{field_default(self, 'refine_start')} and {field_default(self, 'refine_stop')}")
        check_field(self, "strategy.min_opacity", 0 < self.min_opacity < 1, "in (0, 1)", got=True)
        if self.grow_rate < 0 or self.noise_lr < 0 or self.opacity_reg < 0 or self.scale_reg < 0:
            raise B3dgsError("strategy.grow_rate, noise_lr, opacity_reg and scale_reg must be >= 0",
                             fix="pass non-negative values, e.g. the defaults "
                                 + ", ".join(f"strategy.{k}={field_default(self, k)}"
                                             for k in ("grow_rate", "noise_lr", "opacity_reg", "scale_reg"))
                                 + " (0 turns a term off)")

    def initialize_state(self, *, splats, scene, info):
        dev = splats["means"].device
        return {"relocated": torch.zeros((), dtype=torch.long, device=dev),
                "grown": torch.zeros((), dtype=torch.long, device=dev),
                "n_init": torch.tensor(splats["means"].shape[0], device=dev)}  # the schedule's budget base

    def step_pre_backward(self, *, splats, optimizers, state, step, info):
        terms = info["loss_terms"]
        if self.opacity_reg > 0:
            terms.append(self.opacity_reg * torch.sigmoid(splats["opacities"]).mean())
        if self.scale_reg > 0:
            terms.append(self.scale_reg * torch.exp(splats["scales"]).mean())

    def step_post_backward(self, *, splats, optimizers, state, step, info):
        if "relocate" in self.periodic(step, info):
            self._relocate_and_grow(splats, state, info["ops"], info)
        self._inject_noise(splats, optimizers)

    def periodic(self, step: int, info: dict) -> tuple[str, ...]:
        """``relocate`` (dead Gaussians moved, the set grown) every ``refine_every`` steps in [refine_start, refine_stop)."""
        if self.refine_start <= step < self.refine_stop and step % self.refine_every == 0 and step > 0:
            return ("relocate",)
        return ()

    # ------------------------------------------------------------------ ops
    @torch.no_grad()
    def _replace(self, splats, ops, index: Tensor, fresh: Tensor, sources: Tensor, op: str) -> None:
        """``ops.gather(index, fresh)`` where the rows ``fresh`` are copies of ``sources``; every drawn source
        and its copies get the opacity and scale of :func:`relocation` (n = 1 + its copies), and the
        sources' Adam moments are zeroed (the copies are fresh)."""
        n_old = ops.num
        counts = torch.bincount(sources, minlength=n_old)
        uniq = torch.nonzero(counts, as_tuple=False).flatten()
        o_new, s_new = relocation(torch.sigmoid(splats["opacities"].data[uniq]).flatten(),
                                  torch.exp(splats["scales"].data[uniq]), counts[uniq] + 1)
        o_new = o_new.clamp(self.min_opacity, 1 - 1e-6)
        slot = torch.full((n_old,), -1, dtype=torch.long, device=index.device)
        slot[uniq] = torch.arange(uniq.numel(), device=index.device)
        hit = slot[index] >= 0  # the sources (at their own rows) and their copies
        opac = splats["opacities"].data[index].clone()
        scales = splats["scales"].data[index].clone()
        opac[hit] = torch.logit(o_new[slot[index[hit]]]).reshape(-1, *opac.shape[1:])
        scales[hit] = torch.log(s_new[slot[index[hit]]])
        ops.gather(index, fresh, {"opacities": opac, "scales": scales}, op=op)
        ops.reset_moments(uniq)  # sources keep their rows: relocation fills dead rows, growth appends

    def _draw(self, splats, live: Tensor, k: int) -> Tensor:
        w = torch.sigmoid(splats["opacities"].data[live]).flatten().double()
        return live[torch.multinomial(w / w.sum(), k, replacement=True)]

    @torch.no_grad()
    def _relocate_and_grow(self, splats, state, ops, info: Optional[dict] = None) -> None:
        dead = torch.sigmoid(splats["opacities"].data).flatten() <= self.min_opacity
        live = torch.nonzero(~dead, as_tuple=False).flatten()
        n_dead = int(dead.sum())
        if n_dead and live.numel():
            sources = self._draw(splats, live, n_dead)
            index = torch.arange(ops.num, device=live.device)
            index[dead] = sources
            self._replace(splats, ops, index, dead.clone(), sources, "mcmc_relocate")
            state["relocated"] += n_dead
            ops.added["mcmc_relocate"] += n_dead
            ops.removed["mcmc_dead"] += n_dead
        n = ops.num
        cap = self.scheduled_cap(int(self.cap_max), int(state.get("n_init", n)), info or {})
        n_add = max(0, min(int(cap), int(math.floor(n * (1 + self.grow_rate)))) - n)
        live = torch.nonzero(torch.sigmoid(splats["opacities"].data).flatten() > self.min_opacity, as_tuple=False).flatten()
        if n_add and live.numel():
            sources = self._draw(splats, live, n_add)
            index = torch.cat([torch.arange(n, device=live.device), sources])
            fresh = torch.zeros(index.numel(), dtype=torch.bool, device=live.device)
            fresh[n:] = True
            self._replace(splats, ops, index, fresh, sources, "mcmc_grow")
            state["grown"] += n_add
            ops.added["mcmc_grow"] += n_add

    @torch.no_grad()
    def _inject_noise(self, splats, optimizers) -> None:
        if self.noise_lr <= 0:
            return
        lr = next(g["lr"] for opt in optimizers.values() for g in opt.param_groups if g.get("name") == "means")
        means = splats["means"]
        o = torch.sigmoid(splats["opacities"].data).reshape(-1, 1)
        gate = torch.sigmoid(-100.0 * (o - self.min_opacity))  # ~1 for transparent, ~0 for opaque Gaussians
        R = quat_to_rotmat(splats["quats"].data)
        S2 = torch.exp(2 * splats["scales"].data)
        cov = (R * S2.unsqueeze(-2)) @ R.transpose(-1, -2)
        eta = torch.randn(means.shape, dtype=means.dtype, device=means.device)
        means.data += (cov @ eta.unsqueeze(-1)).squeeze(-1) * gate * (lr * self.noise_lr)
