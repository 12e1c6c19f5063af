"""Topology ops: clone, split, prune and opacity reset.

They re-index every Gaussian parameter, the optimizer's moments and every plugin's per-Gaussian state (the
state keys it declares in ``per_gaussian_state``; every tensor whose first dimension is N for a plugin that
declares none), and keep a stable id and the parent's id for every Gaussian.
"""
from __future__ import annotations

from collections import Counter
from typing import Callable, Optional

import torch
from torch import Tensor, nn

from b3dgs.errors import B3dgsError
from b3dgs.host_sync import scope
from b3dgs.numerics import guard
from b3dgs.render.projection import quat_to_rotmat


#: the per-Gaussian keys of the core's own state (``states["core"]``)
CORE_PER_GAUSSIAN = ("ids", "parent_ids")


def _reindex_keys(state: dict, keys, index: Tensor, n_old: int, owner: str) -> dict:
    """``state`` with the declared per-Gaussian ``keys`` re-indexed along their first dimension."""
    out = dict(state)
    for k in keys:
        v = state.get(k)
        if v is None:
            continue  # not created yet
        if not isinstance(v, Tensor) or v.dim() < 1 or v.shape[0] != n_old:
            shape = tuple(v.shape) if isinstance(v, Tensor) else type(v).__name__
            raise B3dgsError(f"{owner}: state[{k!r}] is declared per-Gaussian (per_gaussian_state) but is {shape}, "
                             f"not ({n_old}, ...)", f"make it one row per Gaussian, or drop {k!r} from per_gaussian_state")
        out[k] = v[index]
    return out


def _reindex_tree(obj, index: Tensor, n_old: int):
    if isinstance(obj, Tensor):
        return obj[index] if obj.dim() >= 1 and obj.shape[0] == n_old else obj
    if isinstance(obj, dict):
        return {k: _reindex_tree(v, index, n_old) for k, v in obj.items()}
    return obj


def find_param_state(optimizer: torch.optim.Optimizer, param: Tensor):
    for group in optimizer.param_groups:
        for i, p in enumerate(group["params"]):
            if p is param:
                return group, i
    return None, None


class TopologyOps:
    """Structural edits of a Gaussian set. One instance per training run; plugins reach it as ``info["ops"]``."""

    def __init__(self, splats: nn.ParameterDict, optimizers: dict[str, torch.optim.Optimizer], states: dict[str, dict],
                 plugins: dict[str, object], on_change: Optional[Callable[[], None]] = None) -> None:
        self.splats = splats
        self.optimizers = optimizers
        self.states = states  # name -> plugin state (includes "core": ids, parent_ids)
        self.plugins = plugins  # name -> plugin (for on_topology)
        self.removed: Counter[str] = Counter()
        self.added: Counter[str] = Counter()
        self.step = 0
        self.on_change = on_change
        # this step's per-Gaussian render data, (S, N, ...) tensors; re-indexed along N by every
        # topology change so that plugins running later in the step see aligned values
        self.per_gaussian: dict[str, Tensor] = {}

    @property
    def num(self) -> int:
        return int(self.splats["means"].shape[0])

    # ------------------------------------------------------------------ primitive
    def gather(self, index: Tensor, fresh: Tensor, overrides: Optional[dict[str, Tensor]] = None, op: str = "gather") -> None:
        """Replace the set by rows ``index`` of the old one; rows flagged ``fresh`` are new children
        (zeroed optimizer moments, new ids with the source row's id as parent). ``overrides`` maps a
        parameter name to its full new (N', ...) tensor."""
        n_old = self.num
        index = index.long()
        if index.dim() != 1 or fresh.shape != index.shape:
            raise B3dgsError("gather: index and fresh must be 1-D and of equal length",
                             fix="pass index (N',) of source rows and fresh (N',) bool flags of the same length")
        overrides = overrides or {}
        for name in list(self.splats.keys()):
            old = self.splats[name]
            new_data = overrides[name].detach() if name in overrides else old.data[index]
            new = nn.Parameter(new_data.contiguous(), requires_grad=old.requires_grad)
            for opt in self.optimizers.values():
                group, i = find_param_state(opt, old)
                if group is None:
                    continue
                st = opt.state.pop(old, None)
                if st:
                    for key, v in list(st.items()):
                        if isinstance(v, Tensor) and v.dim() >= 1 and v.shape[0] == n_old:
                            v = v[index].clone()
                            v[fresh] = 0
                            st[key] = v
                    opt.state[new] = st
                group["params"][i] = new
            self.splats[name] = new
        core = self.states["core"]
        parent_src = core["ids"][index]
        for name, st in self.states.items():
            keys = CORE_PER_GAUSSIAN if name == "core" else getattr(self.plugins.get(name), "per_gaussian_state", None)
            new_st = _reindex_tree(st, index, n_old) if keys is None else _reindex_keys(st, keys, index, n_old, name)
            st.clear()
            st.update(new_st)  # keep dict identity so plugins holding a reference stay valid
        for key, v in list(self.per_gaussian.items()):
            if isinstance(v, Tensor) and v.dim() >= 2 and v.shape[1] == n_old:
                v = v[:, index].clone()
                v[:, fresh] = 0
                self.per_gaussian[key] = v
        n_fresh = int(fresh.sum())
        if n_fresh:
            start = int(core["next_id"])
            core["ids"][fresh] = torch.arange(start, start + n_fresh, dtype=torch.long, device=core["ids"].device)
            core["parent_ids"][fresh] = parent_src[fresh]
            core["next_id"] = torch.tensor(start + n_fresh, device=core["ids"].device)
        info = {"op": op, "index": index, "fresh": fresh, "parent_ids": parent_src, "n_old": n_old}
        for name, plugin in self.plugins.items():
            with scope(name):
                plugin.on_topology(splats=self.splats, optimizers=self.optimizers, state=self.states[name], step=self.step,
                                   info=info)
        if self.on_change is not None:
            self.on_change()

    # ------------------------------------------------------------------ 3DGS ops
    def clone(self, mask: Tensor, reason: str = "densify") -> int:
        """Duplicate the Gaussians in ``mask`` (3DGS clone of small, under-reconstructed Gaussians)."""
        sel = torch.nonzero(mask, as_tuple=False).flatten()
        if sel.numel() == 0:
            return 0
        n = self.num
        index = torch.cat([torch.arange(n, device=sel.device), sel])
        fresh = torch.zeros(index.shape[0], dtype=torch.bool, device=sel.device)
        fresh[n:] = True
        self.gather(index, fresh, op="clone")
        self.added[reason] += sel.numel()
        return sel.numel()

    def split(self, mask: Tensor, n_children: int = 2, reason: str = "densify", scale_div: float = 1.6) -> int:
        """Replace each Gaussian in ``mask`` by ``n_children`` children sampled from it, scales / ``scale_div``."""
        sel = torch.nonzero(mask, as_tuple=False).flatten()
        if sel.numel() == 0:
            return 0
        keep = torch.nonzero(~mask, as_tuple=False).flatten()
        src = sel.repeat(n_children)
        index = torch.cat([keep, src])
        fresh = torch.zeros(index.shape[0], dtype=torch.bool, device=sel.device)
        fresh[keep.numel():] = True
        sp = self.splats
        scales = torch.exp(sp["scales"].data[src])
        R = quat_to_rotmat(sp["quats"].data[src])
        offset = (R @ (torch.randn_like(scales) * scales).unsqueeze(-1)).squeeze(-1)
        means = torch.cat([sp["means"].data[keep], sp["means"].data[src] + offset])
        log_scales = torch.cat([sp["scales"].data[keep], torch.log(scales / scale_div)])
        self.gather(index, fresh, {"means": means, "scales": log_scales}, op="split")
        self.added[reason] += src.numel()
        self.removed[reason + "_split_parent"] += sel.numel()
        return sel.numel()

    def prune(self, mask: Tensor, reason: str) -> int:
        """Remove the Gaussians in ``mask``; at least one Gaussian is always kept."""
        n = self.num
        if mask.shape != (n,):
            raise B3dgsError(f"prune: mask must have shape ({n},), got {tuple(mask.shape)}",
                             fix=f"pass a bool mask with one entry per current Gaussian, shape ({n},) (rebuild it "
                                 "after any earlier densify or prune of this step)")
        mask = mask.clone()
        if bool(mask.all()):
            # keep the most opaque Gaussian so the model never becomes empty (a floor: counted)
            mask[torch.argmax(self.splats["opacities"].data)] = False
            guard("ops.prune_keep_one", 1)
        k = int(mask.sum())
        if k == 0:
            return 0
        keep = torch.nonzero(~mask, as_tuple=False).flatten()
        self.gather(keep, torch.zeros(keep.numel(), dtype=torch.bool, device=keep.device), op="prune")
        self.removed[reason] += k
        return k

    def reset_moments(self, index: Tensor) -> None:
        """Zero the optimizer moments of the Gaussians ``index`` for every parameter (e.g. MCMC relocation sources)."""
        for p in self.splats.values():
            for opt in self.optimizers.values():
                st = opt.state.get(p)
                if st:
                    for v in st.values():
                        if isinstance(v, Tensor) and v.dim() >= 1 and v.shape[0] == p.shape[0]:
                            v[index] = 0

    def reset_opacity(self, value: float) -> None:
        """Clamp opacities to at most ``value`` and zero their optimizer moments (3DGS opacity reset)."""
        p = self.splats["opacities"]
        logit = torch.logit(torch.tensor(value, dtype=torch.float64))
        with torch.no_grad():
            p.data.clamp_(max=float(logit))
        for opt in self.optimizers.values():
            st = opt.state.get(p)
            if st:
                for key, v in st.items():
                    if isinstance(v, Tensor) and v.shape == p.shape:
                        v.zero_()
