"""Full-reference image metrics: PSNR and SSIM.

Conventions shared by :func:`psnr`, :func:`ssim` and :class:`b3dgs.metrics.lpips.LPIPS`:

* images are float tensors laid out channels-last, ``(H, W, 3)`` or ``(B, H, W, 3)``, with
  values in ``[0, 1]`` (values are not clamped; data range is taken as 1);
* ``pred`` and ``gt`` must have the same shape; they are compared on ``pred``'s device;
* the result has the batch shape of the input: a 0-d tensor for one image (so ``float(psnr(a, b))``
  works) and a ``(B,)`` tensor for a batch (one value per image; reduce it yourself);
* the functions are differentiable.

PSNR is capped at :data:`PSNR_CAP_DB` = 100 dB (reached when the MSE is 1e-10 or less, e.g. identical
images): an infinite value would not survive JSON (``metrics.json``), and 100 dB is far above any
float32 rendering error, so the cap never affects a real comparison.
"""
from __future__ import annotations

import kornia
import torch
from torch import Tensor

# the renderers' SSIM losses live with the renderers (metrics import render, never the reverse)
from b3dgs.errors import B3dgsError, B3dgsTypeError
from b3dgs.render.ssim import SSIM_SIGMA, SSIM_WINDOW, ssim_fused, ssim_separable  # noqa: F401

__all__ = ["PSNR_CAP_DB", "SSIM_WINDOW", "SSIM_SIGMA", "psnr", "ssim", "ssim_separable", "ssim_fused", "check_images"]

#: Upper bound returned by :func:`psnr` (dB). Equivalent to clamping the MSE at 1e-10.
PSNR_CAP_DB = 100.0
_MSE_FLOOR = 10.0 ** (-PSNR_CAP_DB / 10.0)


def check_images(pred: Tensor, gt: Tensor, name: str = "metric") -> tuple[Tensor, Tensor, bool]:
    """Validate a pair of images and return them as ``(B, H, W, 3)`` plus a flag "input was batched".

    Raises ``TypeError`` for non-tensors / non-float dtypes and ``ValueError`` for bad shapes or
    non-finite values.
    """
    if not isinstance(pred, Tensor) or not isinstance(gt, Tensor):
        raise B3dgsTypeError(f"{name}: pred and gt must be torch tensors, got {type(pred).__name__}, "
                             f"{type(gt).__name__}", "pass torch tensors (torch.as_tensor)")
    if pred.shape != gt.shape:
        raise B3dgsError(f"{name}: pred and gt shapes differ: {tuple(pred.shape)} vs {tuple(gt.shape)}",
                         fix="pass the render and the ground truth at the same size and layout, e.g. both (H, W, 3)")
    if pred.dim() not in (3, 4) or pred.shape[-1] != 3:
        raise B3dgsError(f"{name}: expected images of shape (H, W, 3) or (B, H, W, 3), got {tuple(pred.shape)}",
                         fix="pass RGB images as float tensors of shape (H, W, 3) or (B, H, W, 3); drop an alpha "
                             "channel with [..., :3]")
    if pred.numel() == 0:
        raise B3dgsError(f"{name}: empty images of shape {tuple(pred.shape)}",
                         fix="pass images with at least one pixel")
    if not pred.is_floating_point() or not gt.is_floating_point():
        raise B3dgsTypeError(f"{name}: images must be floating point in [0, 1], got {pred.dtype} and {gt.dtype}",
                             "pass float images in [0, 1] (e.g. uint8 / 255.0)")
    gt = gt.to(device=pred.device)
    batched = pred.dim() == 4
    if not batched:
        pred, gt = pred.unsqueeze(0), gt.unsqueeze(0)
    if not bool(torch.isfinite(pred).all()) or not bool(torch.isfinite(gt).all()):
        raise B3dgsError(f"{name}: images contain NaN or Inf",
                         fix="pass finite images; a NaN render means training diverged: lower the learning rates "
                             "(e.g. model.lr_means)")
    return pred, gt, batched


def psnr(pred: Tensor, gt: Tensor) -> Tensor:
    """Peak signal-to-noise ratio in dB for images in [0, 1] (data range 1), capped at 100 dB.

    ``psnr = -10 log10(max(mse, 1e-10))`` with the MSE taken over all pixels and channels of each
    image (accumulated in float64). Returns a 0-d tensor for ``(H, W, 3)`` input and ``(B,)`` for
    ``(B, H, W, 3)``, in the inputs' floating dtype.
    """
    p, g, batched = check_images(pred, gt, "psnr")
    out_dtype = torch.promote_types(p.dtype, g.dtype)
    mse = (p.double() - g.double()).square().mean(dim=(1, 2, 3))
    val = -10.0 * torch.log10(mse.clamp_min(_MSE_FLOOR))
    val = val.to(out_dtype)
    return val if batched else val[0]


def ssim(pred: Tensor, gt: Tensor) -> Tensor:
    """Structural similarity (Wang et al. 2004) for images in [0, 1].

    Gaussian window 11x11 with sigma 1.5, C1 = (0.01)^2, C2 = (0.03)^2 (data range 1), computed per
    channel by ``kornia.metrics.ssim`` with ``padding='valid'`` (only windows fully inside the image,
    as in the paper's reference code and scikit-image's ``structural_similarity(gaussian_weights=True,
    sigma=1.5, use_sample_covariance=False, data_range=1)``) and no extra epsilon, so identical images
    score exactly 1. The SSIM map is averaged over pixels and channels of each image.

    Images must be at least 11x11. Returns a 0-d tensor for ``(H, W, 3)`` input and ``(B,)`` for
    ``(B, H, W, 3)``.
    """
    p, g, batched = check_images(pred, gt, "ssim")
    h, w = p.shape[1:3]
    if h < SSIM_WINDOW or w < SSIM_WINDOW:
        raise B3dgsError(f"ssim: images must be at least {SSIM_WINDOW}x{SSIM_WINDOW}, got {h}x{w}",
                         fix=f"evaluate at a larger size (at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels: raise "
                             "data.max_side), or skip SSIM for such tiny views")
    dtype = torch.promote_types(p.dtype, g.dtype)
    a, b = (t.to(dtype).permute(0, 3, 1, 2) for t in (p, g))
    smap = kornia.metrics.ssim(a, b, window_size=SSIM_WINDOW, max_val=1.0, eps=0.0, padding="valid")
    val = smap.mean(dim=(1, 2, 3))
    return val if batched else val[0]
