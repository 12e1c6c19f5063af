"""Per-pixel gradients of a render, for Fisher information (FisherRF acquisition, PUP pruning).

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
