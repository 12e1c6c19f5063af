"""Test-set evaluation of a trained SplatModule: PSNR, SSIM, LPIPS, render FPS, PNG renders."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Optional, Sequence

import torch

from b3dgs.device import timed_clock
from b3dgs.errors import B3dgsError
from b3dgs.metrics.image import SSIM_WINDOW, psnr, ssim
from b3dgs.metrics.lpips import _MIN_SIZE as LPIPS_MIN_SIDE
from b3dgs.types import Camera

log = logging.getLogger(__name__)


@torch.no_grad()
def evaluate_views(module, cameras: Sequence[Camera], lpips_model=None, render_dir: Optional[Path] = None,
                   with_ssim: bool = True) -> dict:
    """Render every camera and score it; returns scene means and per-view values.

    ``render_fps`` times the forward render alone (no metrics, no I/O) over all views.
    """
    per_view = []
    render_s = 0.0
    for cam in cameras:
        if cam.image is None:
            raise B3dgsError(f"evaluate: camera {cam.name!r} has no ground-truth image",
                             fix="pass cameras loaded with their ground-truth images (the scene's test views), not "
                                 "image-less poses")
        t0 = timed_clock(module.device)
        pred = module.render_eval(cam)
        render_s += timed_clock(module.device) - t0
        pred = pred.cpu()
        gt = cam.image
        row = {"name": cam.name, "psnr": float(psnr(pred, gt))}
        if with_ssim and min(gt.shape[:2]) >= SSIM_WINDOW:
            row["ssim"] = float(ssim(pred, gt))
        if lpips_model is not None and min(gt.shape[:2]) >= LPIPS_MIN_SIDE:
            row["lpips"] = float(lpips_model(pred, gt))
        per_view.append(row)
        if render_dir is not None:
            from b3dgs.data.images import save_png

            save_png(Path(render_dir) / f"{Path(cam.name).stem}.png", torch.cat([pred, gt], dim=1))
    out: dict = {"num_views": len(per_view), "per_view": per_view}
    for key in ("psnr", "ssim", "lpips"):
        vals = [r[key] for r in per_view if key in r]
        if vals:
            out[key] = float(sum(vals) / len(vals))
    out["render_fps"] = len(per_view) / render_s if render_s > 0 else None
    if lpips_model is not None and "lpips" not in out and per_view:
        out["lpips_reason"] = f"test views smaller than {LPIPS_MIN_SIDE}x{LPIPS_MIN_SIDE} (AlexNet needs that much)"
    return out
