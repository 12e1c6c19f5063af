"""The SSIM training losses the renderers offer (:meth:`b3dgs.render.renderers.Renderer.ssim`): the same SSIM as
:func:`b3dgs.metrics.image.ssim` for one ``(H, W, 3)`` pair, separable (torch) or fused with its gradient (C++)."""
from __future__ import annotations

import functools

import kornia
import torch
from torch import Tensor

from b3dgs.errors import B3dgsError

__all__ = ["SSIM_WINDOW", "SSIM_SIGMA", "ssim_separable", "ssim_fused"]

#: SSIM Gaussian window (Wang et al. 2004): 11x11 taps, sigma 1.5; constants K1=0.01, K2=0.03, L=1.
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5  # fixed inside kornia.metrics.ssim


@functools.cache
def _separable_window(device: torch.device, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """kornia's 1-D Gaussian window as the two depthwise kernels, made once per device and dtype (kornia builds it
    from a Python sigma, a host-to-device copy that synchronises a GPU at every step)."""
    k = kornia.filters.get_gaussian_kernel1d(SSIM_WINDOW, SSIM_SIGMA, device=device, dtype=dtype).reshape(-1)
    return k.view(1, 1, 1, -1).repeat(15, 1, 1, 1), k.view(1, 1, -1, 1).repeat(15, 1, 1, 1)


def ssim_separable(pred: Tensor, gt: Tensor) -> Tensor:
    """The same SSIM as :func:`b3dgs.metrics.image.ssim` for one (H, W, 3) pair, with the 11x11 Gaussian window applied as
    two 1-D passes (kornia's Gaussian kernel): about 5x cheaper, for the training loss. Differentiable."""
    if pred.shape != gt.shape or pred.dim() != 3 or pred.shape[-1] != 3:
        raise B3dgsError(f"ssim_separable: expected two (H, W, 3) images, got {tuple(pred.shape)} and {tuple(gt.shape)}",
                         fix="pass the render and the ground truth of one view as two (H, W, 3) tensors of the same "
                             "size")
    kx, ky = _separable_window(pred.device, pred.dtype)
    a = pred.permute(2, 0, 1).unsqueeze(0)
    b = gt.to(pred.dtype).permute(2, 0, 1).unsqueeze(0)
    x = torch.cat([a, b, a * a, b * b, a * b], dim=1)  # (1, 15, H, W)
    x = torch.nn.functional.conv2d(torch.nn.functional.conv2d(x, kx, groups=15), ky, groups=15)
    mu1, mu2, s11, s22, s12 = x.split(3, dim=1)
    c1, c2 = 0.01**2, 0.03**2
    mu1mu2, mu1s, mu2s = mu1 * mu2, mu1 * mu1, mu2 * mu2
    num = (2 * mu1mu2 + c1) * (2 * (s12 - mu1mu2) + c2)
    den = (mu1s + mu2s + c1) * ((s11 - mu1s) + (s22 - mu2s) + c2)
    return (num / den).mean()


class _SSIMFused(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred: Tensor, gt: Tensor) -> Tensor:
        from b3dgs.render._ext import load_extension

        value, grad = load_extension().ssim_value_grad(pred.contiguous(), gt.contiguous(), ctx.needs_input_grad[0],
                                                       torch.get_num_threads())
        ctx.save_for_backward(grad)
        return value

    @staticmethod
    def backward(ctx, g: Tensor):
        (grad,) = ctx.saved_tensors
        return g * grad, None


def ssim_fused(pred: Tensor, gt: Tensor) -> Tensor:
    """:func:`ssim_separable` computed by the C++ extension together with its gradient (one pass over
    the image instead of ~20 autograd ops; the training loss of ``renderer=cpu``). gt gets no gradient."""
    if pred.shape != gt.shape or pred.dim() != 3 or pred.shape[-1] != 3:
        raise B3dgsError(f"ssim_fused: expected two (H, W, 3) images, got {tuple(pred.shape)} and {tuple(gt.shape)}",
                         fix="pass the render and the ground truth of one view as two (H, W, 3) tensors of the same "
                             "size")
    return _SSIMFused.apply(pred, gt.to(pred.dtype).detach())
