"""Fisher (beyond the paper; FisherRF, Jiang et al. 2024): expected information gain of a view from a
diagonal Fisher over the Gaussian parameters, with greedy batch selection."""
from __future__ import annotations

from dataclasses import dataclass, field

import torch

from b3dgs.acquisition import AcquisitionPolicy, Selection

PARAMS = ("means", "sh0", "shN", "scales", "opacities")  # scales are log-scales, opacities logits


@dataclass
class FisherPolicy(AcquisitionPolicy):
    """H_v[θ] = Σ_p (Σ_c ∂I_c(p)/∂θ)² for θ in means, sh0, shN, log-scales and opacity logits (per-pixel
    squared gradients, not the square of the gradient of the image sum). Score of a candidate c:
    Σ_θ H_c[θ] / (H_train[θ] + λ); greedy batch: after each pick H_train += H_c.

    Per-pixel gradients come from backward passes over pixel sets: the pixels (y, x) with the same
    (y mod s, x mod s), s = ``pixel_stride``, share one pass (s² passes per view, one forward). It is exact
    when s >= the longest side at the scoring resolution (one pixel per pass); with a smaller s the cross
    terms of two pixels s apart that see the same Gaussian are included (a Gaussian narrower than s px
    adds none).
    """

    pixel_stride: int = 8
    lam: float = 1.0e-6
    params: list = field(default_factory=lambda: list(PARAMS))

    def check(self):
        super().check()
        if int(self.pixel_stride) < 1:
            raise ValueError(f"acquisition fisher.pixel_stride must be >= 1, got {self.pixel_stride}")
        bad = [p for p in self.params if p not in PARAMS + ("quats",)]
        if bad:
            raise ValueError(f"acquisition fisher.params: unknown parameters {bad}")

    def view_fisher(self, ctx, camera) -> torch.Tensor:
        """(P,) diagonal Fisher of one view over ``params`` (flattened in that order), float64 on the CPU."""
        p = ctx.params(requires_grad=False)
        leaves = [p[k].requires_grad_(True) for k in self.params]
        rgb = ctx.render(camera, params=p, grad=True).rgb
        H, W = rgb.shape[:2]
        s = int(self.pixel_stride)
        acc = torch.zeros(sum(x.numel() for x in leaves), dtype=torch.float64, device=rgb.device)
        mask = torch.zeros_like(rgb)
        for a in range(min(s, H)):
            for b in range(min(s, W)):
                mask.zero_()
                mask[a::s, b::s] = 1.0
                grads = torch.autograd.grad(rgb, leaves, grad_outputs=mask, retain_graph=True, allow_unused=True)
                flat = torch.cat([(torch.zeros_like(x) if g is None else g).reshape(-1) for g, x in zip(grads, leaves)])
                acc += flat.double().square()
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
