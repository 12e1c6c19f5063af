"""COVER (Chen, Dai, Adang, Gao, Schwager, CVPR 2026, arXiv 2604.05259): pick the views that see geometry the
training cameras have covered worst, the paper's tractable stand-in for the Fisher information gain of a view."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from b3dgs.acquisition import AcquisitionPolicy, Selection, top_k
from b3dgs.errors import B3dgsError
from b3dgs.numerics import guard

VISIBILITY = ("frustum", "weights")
AGGREGATE = ("mean", "sum")


def sphere_directions(n: int, device) -> Tensor:
    """(n, 3) unit vectors spread evenly over the sphere (Fibonacci lattice)."""
    i = torch.arange(n, dtype=torch.float64, device=device)
    z = 1.0 - 2.0 * (i + 0.5) / n
    r = (1.0 - z * z).clamp_min(0.0).sqrt()
    phi = 2.0 * math.pi * torch.frac(i * (math.sqrt(5.0) - 1.0) / 2.0)
    return torch.stack([r * phi.cos(), r * phi.sin(), z], -1).float()


@dataclass
class CoverPolicy(AcquisitionPolicy):
    """Each Gaussian k keeps the set S_k of direction bins u_b (``bins`` Fibonacci directions) from which a
    training camera c saw it, b = argmax_b <d_ck, u_b>, d_ck = (μ_k − o_c)/‖μ_k − o_c‖. Its coverage seen from
    view v is C_k(v) = max_{b∈S_k} (1 + <d_vk, u_b>)/2 (0 when S_k is empty). The view's metric is the rendered
    coverage image, through the per-Gaussian compositing weights W_vk = Σ_p w_kp of the candidate's render:
    ``mean``: s_v = Σ_k W_vk (1 − C_k(v)) / Σ_k W_vk (1 − the coverage averaged over what v renders);
    ``sum``: s_v = Σ_k W_vk (1 − C_k(v)) / (H·W) (under-covered area, as a share of the image). Higher s_v =
    acquire first (the paper picks the lowest coverage). Greedy batch (the paper's next-best-view loop): after
    each pick its directions join the S_k and the rest are re-scored.

    Choices the paper (abstract, project page) leaves open, taken from the authors' release where it had one:
    geometry = the Gaussian means, all of them; a training camera sees k when k lies in its frustum
    (``visibility=frustum``: the renderer's radii > 0, projection only, no transmittance, as in the paper), or
    ``weights``: when k's weight sum there is >= ``min_weight`` px (occlusion-aware); the angular kernel is
    (1 + cos)/2 to the nearest seen bin (width set by ``bins``: 128 as released); bin counts are not used
    beyond "seen"; normalising by Σ W (not by the pixel count with α > 0 as released) keeps faint fringes out.
    """

    selects_batch: ClassVar[bool] = True  # its select builds the batch (only batch=topk applies)

    bins: int = 128  # Fibonacci directions per Gaussian that record from where it was seen (128 as released)
    visibility: str = "frustum"  # frustum: in a training camera's frustum (the paper's) | weights: sum >= min_weight
    min_weight: float = 0.05  # visibility=weights: Σ_p w_kp (px at the scoring size) for a Gaussian to count as seen
    aggregate: str = "mean"  # mean: 1 - coverage averaged over what the view renders | sum: under-covered area / image

    def validate(self, **kwargs):
        super().validate(**kwargs)
        if isinstance(self.bins, bool) or int(self.bins) != self.bins or int(self.bins) < 1:
            raise B3dgsError(f"acquisition cover.bins={self.bins!r} must be an integer >= 1",
                             "pass acquisition cover.bins=128 (directions per Gaussian)")
        if self.visibility not in VISIBILITY:
            raise B3dgsError(f"acquisition cover.visibility={self.visibility!r} is not one of {VISIBILITY}",
                             "pass visibility=frustum (the paper's) or visibility=weights")
        if not (math.isfinite(float(self.min_weight)) and float(self.min_weight) >= 0):
            raise B3dgsError(f"acquisition cover.min_weight={self.min_weight!r} must be finite and >= 0",
                             "pass min_weight=0.05 (pixels of compositing weight)")
        if self.aggregate not in AGGREGATE:
            raise B3dgsError(f"acquisition cover.aggregate={self.aggregate!r} is not one of {AGGREGATE}",
                             "pass aggregate=mean or aggregate=sum")

    # ---------------------------------------------------------------- geometry
    def _means(self, ctx) -> Tensor:
        if ctx.num_members < 1:
            raise B3dgsError("acquisition cover needs the phase-1 model's Gaussians; the context has no model",
                             "score with a ScoringContext built on the phase-1 model")
        means = ctx.params()["means"].float()
        if means.shape[0] == 0:
            raise B3dgsError("acquisition cover: the phase-1 model has no Gaussians",
                             "train phase 1 longer or loosen its pruning so that Gaussians remain")
        return means

    def _view(self, ctx, cam, means):
        """(centre (3,), W (N,) weight sums, seen-by-the-rule mask (N,), pixel count) of one view."""
        if not (torch.isfinite(cam.viewmat).all() and torch.isfinite(cam.K).all()):
            raise B3dgsError(f"acquisition cover: camera {cam.name!r} has a non-finite pose or intrinsics",
                             "fix or drop that camera in the scene")
        out = ctx.render(cam, return_weights=True)
        w = out.weight_sum.reshape(-1).to(means.device, torch.float64)
        sees = out.radii.reshape(-1).to(means.device) > 0
        if self.visibility == "weights":
            sees &= (w > 0) & (w >= float(self.min_weight))
        small = ctx.camera(cam)
        return cam.center.to(means.device, torch.float32), w, sees, small.width * small.height

    @staticmethod
    def _dirs(means: Tensor, centre: Tensor) -> Tensor:
        d = means - centre
        n = d.norm(dim=-1, keepdim=True)
        guard("cover.zero_direction", n == 0)
        return d / n.clamp_min(1e-12)

    def _scores(self, W: Tensor, C: Tensor, area: Tensor) -> Tensor:
        under = (W * (1.0 - C.double())).sum(1)
        if self.aggregate == "sum":
            return under / area
        tot = W.sum(1)
        guard("cover.empty_view", tot == 0)  # a view that renders nothing scores 0
        return torch.where(tot > 0, under / tot.clamp_min(1e-300), torch.zeros_like(tot))

    @torch.no_grad()
    def _rounds(self, ctx, candidates, budget: int) -> tuple[list[int], Tensor]:
        means = self._means(ctx)
        dev, N = means.device, means.shape[0]
        U = sphere_directions(int(self.bins), dev)
        seen = torch.zeros(N, U.shape[0], dtype=torch.bool, device=dev)  # S_k as a mask over bins
        for cam in ctx.train:
            o, _, sees, _ = self._view(ctx, cam, means)
            k = sees.nonzero().squeeze(1)
            seen[k, (self._dirs(means[k], o) @ U.T).argmax(1)] = True
        views = [self._view(ctx, c, means) for c in candidates]
        O, W, sees = (torch.stack(t) for t in list(zip(*views))[:3])  # (K, 3) centres, (K, N) weights, (K, N) seen
        area = torch.tensor([float(v[3]) for v in views], dtype=torch.float64, device=dev)
        C = torch.zeros(len(candidates), N, dtype=torch.float32, device=dev)  # C_k(v), needed where W_vk > 0
        for v in range(len(candidates)):
            k = (W[v] > 0).nonzero().squeeze(1)
            if len(k):
                half = (1.0 + self._dirs(means[k], O[v]) @ U.T) / 2.0
                C[v, k] = half.masked_fill(~seen[k], 0.0).amax(1)
        first = self._scores(W, C, area).cpu()
        s, picks = first, []
        for _ in range(min(int(budget), len(candidates))):
            s = s.clone()
            s[picks] = -math.inf
            i = top_k(s, 1)[0]  # ties: the first candidate
            picks.append(i)
            k = sees[i].nonzero().squeeze(1)  # the pick now counts as a training camera
            u = U[(self._dirs(means[k], O[i]) @ U.T).argmax(1)]  # (n, 3) its bins for those Gaussians
            d = means[k].unsqueeze(0) - O.unsqueeze(1)  # (K, n, 3)
            d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            C[:, k] = torch.maximum(C[:, k], (1.0 + (d * u).sum(-1)) / 2.0)
            s = self._scores(W, C, area).cpu()
        return picks, first

    def score(self, ctx, candidates):
        """(K,) first-round metric s_v, float64 on the CPU; higher = acquire first."""
        if not len(candidates):
            return torch.zeros(0, dtype=torch.float64)
        return self._rounds(ctx, candidates, 0)[1]

    def select(self, ctx, candidates, budget):
        if not len(candidates) or int(budget) < 1:
            return Selection([], [] if not len(candidates) else None)
        picks, first = self._rounds(ctx, candidates, int(budget))
        return Selection(picks, [float(v) for v in first])
