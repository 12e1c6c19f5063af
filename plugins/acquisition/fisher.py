"""Fisher (beyond the paper; FisherRF, Jiang et al. 2024): expected information gain of a view from a
diagonal Fisher over the Gaussian parameters, with greedy batch selection."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import torch

from b3dgs.acquisition import AcquisitionPolicy, Selection
from b3dgs.errors import B3dgsError, field_default
from b3dgs.fisher import pixel_set_grads

PARAMS = ("means", "sh0", "shN", "scales", "opacities")  # scales are log-scales, opacities logits


@dataclass
class FisherPolicy(AcquisitionPolicy):
    """H_v[θ] = Σ_p (Σ_c ∂I_c(p)/∂θ)² for θ in means, sh0, shN, log-scales and opacity logits (per-pixel
    squared gradients, not the square of the gradient of the image sum). Score of a candidate c:
    Σ_θ H_c[θ] / (H_train[θ] + λ); greedy batch: after each pick H_train += H_c.

    Per-pixel gradients come from :func:`b3dgs.fisher.pixel_set_grads` with s = ``pixel_stride`` (s² backward
    passes per view; exact when s >= the longest side at the scoring resolution).
    """

    selects_batch: ClassVar[bool] = True  # its select builds the batch (only batch=topk applies)

    pixel_stride: int = 8  # s: per-pixel squared gradients from s*s backward passes per view (exact: s >= scoring side)
    lam: float = 1.0e-6
    params: list = field(default_factory=lambda: list(PARAMS))

    def validate(self, **kwargs):
        super().validate(**kwargs)
        if int(self.pixel_stride) < 1:
            raise B3dgsError(f"acquisition fisher.pixel_stride must be >= 1, got {self.pixel_stride}",
                             fix="pass acquisition.pixel_stride as an integer >= 1, "
                                 f"e.g. the default {field_default(self, 'pixel_stride')}")
        bad = [p for p in self.params if p not in PARAMS + ("quats",)]
        if bad:
            raise B3dgsError(f"acquisition fisher.params: unknown parameters {bad}",
                             fix=f"list only known parameters in acquisition.params: "
                                 f"{', '.join(PARAMS + ('quats',))}")

    def view_fisher(self, ctx, camera) -> torch.Tensor:
        """(P,) diagonal Fisher of one view over ``params`` (flattened in that order), float64 on the CPU."""
        p = ctx.params(requires_grad=False)
        leaves = [p[k].requires_grad_(True) for k in self.params]
        rgb = ctx.render(camera, params=p, grad=True).rgb
        acc = torch.zeros(sum(x.numel() for x in leaves), dtype=torch.float64, device=rgb.device)
        for grads in pixel_set_grads(rgb, leaves, int(self.pixel_stride)):
            acc += torch.cat([g.reshape(-1) for g in grads]).double().square()
        return acc.cpu()

    def select(self, ctx, candidates, budget):
        h_train = torch.zeros(0, dtype=torch.float64)
        for cam in ctx.train:
            h = self.view_fisher(ctx, cam)
            h_train = h if h_train.numel() == 0 else h_train + h
        hc = [self.view_fisher(ctx, c).float() for c in candidates]  # float32 copies bound the memory
        if h_train.numel() == 0:
            h_train = torch.zeros_like(hc[0], dtype=torch.float64)

        def gains():
            return torch.stack([(h.double() / (h_train + self.lam)).sum() for h in hc])

        first = gains()
        picks: list[int] = []
        g = first
        for _ in range(min(int(budget), len(candidates))):
            g = g.clone()
            g[picks] = -float("inf")
            i = int(torch.argmax(g))
            picks.append(i)
            h_train = h_train + hc[i].double()
            g = gains()
        return Selection(picks, [float(v) for v in first])
