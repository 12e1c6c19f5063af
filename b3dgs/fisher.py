"""Fisher information of a render: per-pixel gradients (FisherRF acquisition, PUP pruning) and the Hutchinson
estimate of the centres' Fisher (:class:`FisherAccumulator`: NIW's ``fisher`` counts, info_gain's geometry term).

The Fisher approximation of a squared-error Hessian needs Σ_p ∇θ I(p) ∇θ I(p)ᵀ: per-pixel gradients, not the
gradient of the image sum. Backward passes over pixel sets give them: the pixels (y, x) with the same
(y mod s, x mod s) share one pass (s² passes per view and per channel group, one forward). It is exact when
s >= the longest side (one pixel per pass); with a smaller s the cross terms of two pixels s apart that see the
same Gaussian are included (a Gaussian narrower than s px adds none). Written here because a per-pixel
Jacobian (torch.func.jacrev) of a rasteriser holds H·W·P values; the passes hold one gradient at a time.
"""
from __future__ import annotations

from typing import Iterator, Sequence

import torch
from torch import Tensor

from b3dgs.errors import B3dgsError
from b3dgs.plugin import ViewAccumulator


def pixel_set_grads(rgb: Tensor, leaves: Sequence[Tensor], stride: int,
                    per_channel: bool = False) -> Iterator[list[Tensor]]:
    """Yield, for every pixel set of ``stride`` (and every channel when ``per_channel``), the gradients of
    that set's pixel values (summed over channels unless ``per_channel``) with respect to ``leaves``
    (zeros for a leaf the render does not use). ``rgb``: (H, W, C) with its autograd graph."""
    if rgb.dim() != 3:
        raise B3dgsError(f"pixel_set_grads: rgb must be (H, W, C), got {tuple(rgb.shape)}",
                         fix="pass the rendered image of one camera, shape (H, W, C) with its autograd graph "
                             "(e.g. an unbatched render(...).rgb)")
    s = int(stride)
    if s < 1:
        raise B3dgsError(f"pixel stride must be >= 1, got {stride}", fix="pass stride >= 1 (1 uses every pixel)")
    H, W, C = rgb.shape
    mask = torch.zeros_like(rgb)
    channels = [slice(c, c + 1) for c in range(C)] if per_channel else [slice(0, C)]
    for ch in channels:
        for a in range(min(s, H)):
            for b in range(min(s, W)):
                mask.zero_()
                mask[a::s, b::s, ch] = 1.0
                grads = torch.autograd.grad(rgb, list(leaves), grad_outputs=mask, retain_graph=True, allow_unused=True)
                yield [torch.zeros_like(x) if g is None else g for g, x in zip(grads, leaves)]


class FisherAccumulator(ViewAccumulator):
    """Σ_views Σ_p Σ_c ∇_μk C_pc ∇_μk C_pcᵀ (``fisher``, (N, 3, 3)): the Fisher information of each centre under a
    unit-variance pixel likelihood (FisherRF's quantity; divided by σ² it is the Laplace precision), estimated with
    ``probes`` Rademacher probes per view: E_z[(Σ_p z_p ∇C_p)(Σ_p z_p ∇C_p)ᵀ] = Σ_p ∇C_p ∇C_pᵀ for independent ±1
    z_p (Hutchinson), one backward pass of the renderer per probe instead of one per pixel, on every backend;
    unbiased, relative error ~ √(2 / (probes · views seeing k)). :func:`pixel_set_grads` is the exact
    reference. The probes are drawn on the CPU from ``seed``, so every device draws the same."""

    key = "fisher"
    needs_means_grad = True

    def __init__(self, probes: int):
        if isinstance(probes, bool) or not isinstance(probes, int) or probes < 1:
            raise B3dgsError(f"FisherAccumulator: probes must be an integer >= 1, got {probes!r}",
                             "use the block's fisher_probes (4 by default)")
        self.probes = probes

    def merge(self, other: ViewAccumulator) -> ViewAccumulator:
        return self if self.probes >= getattr(other, "probes", 0) else other

    def start(self, *, params, sh_degree, seed):
        n = params["means"].shape[0]
        self.fisher = torch.zeros(n, 3, 3, dtype=torch.float64, device=params["means"].device)
        self.generator = torch.Generator(device="cpu").manual_seed(int(seed))

    def add(self, *, camera, render, params, sh_degree):
        means, dev = params["means"], params["means"].device
        for m in range(self.probes):
            z = (torch.randint(0, 2, render.rgb.shape, generator=self.generator) * 2 - 1).to(render.rgb.dtype).to(dev)
            (gm,) = torch.autograd.grad(render.rgb, means, grad_outputs=z, retain_graph=m < self.probes - 1)
            gm = gm.double()
            self.fisher += (gm.unsqueeze(-1) * gm.unsqueeze(-2)) / self.probes

    def result(self):
        return {"fisher": self.fisher}
