"""Image-quality metrics: PSNR, SSIM (:mod:`b3dgs.metrics.image`) and offline LPIPS (:mod:`b3dgs.metrics.lpips`)."""
from b3dgs.metrics.image import PSNR_CAP_DB, psnr, ssim
from b3dgs.metrics.lpips import LPIPS, find_lpips_weights, get_lpips, load_lpips

__all__ = ["PSNR_CAP_DB", "psnr", "ssim", "LPIPS", "find_lpips_weights", "get_lpips", "load_lpips"]
