"""3DGS adaptive density control: clone, split, prune and opacity reset (Kerbl et al. 2023)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Optional

import torch

from b3dgs.errors import B3dgsError, check_field, field_default
from b3dgs.plugin import Plugin


@dataclass
class AdaptiveDensityControl(Plugin):
    """Standard 3DGS densification.

    Gaussians whose mean view-space positional gradient (in NDC units, as in 3DGS) exceeds
    ``grad_threshold`` are cloned when small (max scale <= ``percent_dense`` x scene extent) and
    split into two when large. Low-opacity Gaussians are pruned at every refinement; after the
    first opacity reset (or after ``prune_big_after`` steps), Gaussians that are huge in world or
    screen space are pruned too.
    ``max_gaussians`` caps growth: when the candidates would exceed it, the highest-gradient
    ones are densified first; a training schedule may lower the cap early in the run
    (:meth:`b3dgs.plugin.Plugin.scheduled_cap`).
    """

    per_gaussian_state: ClassVar[tuple[str, ...]] = ("grad2d", "count", "max_radii")

    refine_start: int = 500
    refine_stop: int = 15000
    refine_every: int = 100
    grad_threshold: float = 0.0002
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    reset_every: int = 3000
    max_screen_fraction: float = 0.15
    max_world_scale: float = 0.1
    max_gaussians: Optional[int] = 1_000_000
    prune_big_after: Optional[int] = None  # step after which huge Gaussians are pruned (None: reset_every, as 3DGS)

    def validate(self, **kwargs) -> None:
        check_field(self, "strategy.refine_every", not self.refine_every <= 0, "> 0", "as a positive number of steps")
        if self.refine_start < 0 or self.refine_stop < self.refine_start:
            raise B3dgsError("strategy.refine_start must be >= 0 and <= strategy.refine_stop",
                             fix="pass 0 <= strategy.refine_start <= strategy.refine_stop, e.g. the defaults "
                                 f"{field_default(self, 'refine_start')} and {field_default(self, 'refine_stop')}")
        check_field(self, "strategy.grad_threshold", not self.grad_threshold <= 0, "> 0")
        if not 0 < self.percent_dense <= 1:
            raise B3dgsError(f"strategy.percent_dense={self.percent_dense} is invalid: it must be a fraction of the scene "
                             "extent in (0, 1]", f"pass strategy.percent_dense={field_default(self, 'percent_dense')}")
        check_field(self, "strategy.prune_opacity", 0 < self.prune_opacity < 1, "in (0, 1)")
        if self.max_gaussians is not None and self.max_gaussians < 1:
            raise B3dgsError("strategy.max_gaussians must be >= 1 or null",
                             fix="pass strategy.max_gaussians as a positive count (the default is "
                                 f"{field_default(self, 'max_gaussians')}), or null for no cap")
        if self.prune_big_after is not None and self.prune_big_after < 0:
            raise B3dgsError("strategy.prune_big_after must be >= 0 or null (null: after the first opacity reset)",
                             fix="pass strategy.prune_big_after as a step >= 0, or null")

    def initialize_state(self, *, splats, scene, info):
        n, dev = splats["means"].shape[0], splats["means"].device
        return {
            "grad2d": torch.zeros(n, device=dev),
            "count": torch.zeros(n, device=dev),
            "max_radii": torch.zeros(n, device=dev),
            "n_init": torch.tensor(n, device=dev),  # the schedule's budget grows from here (schedule=dash)
        }

    def step_post_backward(self, *, splats, optimizers, state, step, info):
        if "keep_fraction" in info and "trimmed_cap" not in state:  # schedule=dash's trim, once
            self._trim(splats, state, info)
        if step >= self.refine_stop:
            return
        pg = info["per_gaussian"]
        if "means2d_grad" not in pg:
            return
        width, height = info["width"], info["height"]
        g = pg["means2d_grad"][0].detach()
        # NDC-unit gradient norm of the visible Gaussians, accumulated with masks (no host sync; the pixel-to-NDC
        # factors are made once per image size and device: a new tensor from a list is a synchronising copy on a GPU)
        ndc = self._ndc_scale(width, height, g)
        radii = pg["radii"][0]
        vis = radii > 0
        state["grad2d"].add_(torch.where(vis, (g * ndc).norm(dim=-1), 0.0))
        state["count"].add_(vis)
        state["max_radii"].copy_(torch.where(vis, torch.maximum(state["max_radii"], radii / float(max(width, height))),
                                             state["max_radii"]))

        work = self.periodic(step, info)
        if "densify" in work:
            self._refine(splats, state, step, info)
            for k in ("grad2d", "count", "max_radii"):
                state[k].zero_()
        if "opacity_reset" in work:
            info["ops"].reset_opacity(2.0 * self.prune_opacity)

    def periodic(self, step: int, info: dict) -> tuple[str, ...]:
        """``densify`` every ``refine_every`` steps in (refine_start, refine_stop), ``opacity_reset`` every
        ``reset_every`` steps before refine_stop."""
        if step >= self.refine_stop:
            return ()
        work = ("densify",) if step > self.refine_start and step % self.refine_every == 0 else ()
        if step > 0 and step % self.reset_every == 0:
            work += ("opacity_reset",)
        return work

    def _ndc_scale(self, width: int, height: int, like: torch.Tensor) -> torch.Tensor:
        cache = self.__dict__.setdefault("_ndc_cache", {})
        key = (width, height, like.device, like.dtype)
        if key not in cache:
            cache[key] = like.new_tensor([0.5 * width, 0.5 * height])
        return cache[key]

    @torch.no_grad()
    def _trim(self, splats, state, info) -> None:
        """Keep the share ``info["keep_fraction"]`` of the Gaussians that explain the most training pixels (Σ over the
        training views of their compositing weights, ``info["view_sums"]``); the count never grows past it again."""
        n = info["ops"].num
        cap = max(1, int(n * float(info["keep_fraction"])))
        state["trimmed_cap"] = torch.tensor(cap, device=splats["means"].device)
        if n <= cap:
            return
        usage = info["view_sums"]()["weight_sum"]
        order = torch.argsort(usage, stable=True)  # least used first (ties: lower index first)
        prune = torch.zeros(n, dtype=torch.bool, device=usage.device)
        prune[order[: n - cap]] = True
        info["ops"].prune(prune, reason="budget")

    @torch.no_grad()
    def _refine(self, splats, state, step, info) -> None:
        ops = info["ops"]
        extent = info["scene_extent"]
        avg = state["grad2d"] / state["count"].clamp_min(1)
        high = avg > self.grad_threshold
        small = torch.exp(splats["scales"]).amax(dim=-1) <= self.percent_dense * extent
        clone = high & small
        split = high & ~small
        n = ops.num
        cap = self.scheduled_cap(self.max_gaussians, int(state.get("n_init", n)), info)
        if "trimmed_cap" in state:
            cap = int(state["trimmed_cap"]) if cap is None else min(cap, int(state["trimmed_cap"]))
        if cap is not None:
            budget = max(cap - n, 0)
            # a clone adds one Gaussian, a split adds one net (two children replace the parent)
            cand = torch.nonzero(clone | split, as_tuple=False).flatten()
            if cand.numel() > budget:
                order = torch.argsort(avg[cand], descending=True, stable=True)
                chosen = torch.zeros_like(high)
                chosen[cand[order[:budget]]] = True
                clone &= chosen
                split &= chosen
        n_clone = int(clone.sum())
        ops.clone(clone)
        # the clones are appended; extend the split mask accordingly
        split = torch.cat([split, torch.zeros(n_clone, dtype=torch.bool, device=split.device)])
        ops.split(split)
        prune = torch.sigmoid(splats["opacities"]) < self.prune_opacity
        if step > (self.reset_every if self.prune_big_after is None else self.prune_big_after):
            prune |= state["max_radii"] > self.max_screen_fraction
            prune |= torch.exp(splats["scales"]).amax(dim=-1) > self.max_world_scale * extent
        ops.prune(prune, reason="opacity")
