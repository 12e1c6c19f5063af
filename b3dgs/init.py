"""Initial Gaussian sets: from SfM points where present, at random inside the scene bounds otherwise."""
from __future__ import annotations

import logging
from typing import Optional

import torch
from torch import Tensor

from b3dgs.errors import B3dgsError
from b3dgs.render.projection import rgb_to_sh0
from b3dgs.types import Scene

log = logging.getLogger(__name__)


def knn_mean_dist(points: Tensor, k: int = 3) -> Tensor:
    """Mean distance to the k nearest other points (:mod:`b3dgs.neighbours`, float64; the same values, bit
    for bit, as the brute-force distances used before on the shared scenes and on 50k random points)."""
    from b3dgs.neighbours import nearest_other_distances

    n = points.shape[0]
    if n <= 1:
        return torch.ones(n, dtype=points.dtype)
    d = nearest_other_distances(points.detach().double().cpu().numpy(), min(k, n - 1))
    return torch.from_numpy(d.mean(-1)).to(points.dtype)


def init_gaussians(
    scene: Scene,
    sh_degree: int = 3,
    max_points: Optional[int] = None,
    num_random: int = 20000,
    init_opacity: float = 0.1,
    init_scale: float = 1.0,
    generator: Optional[torch.Generator] = None,
) -> dict[str, Tensor]:
    """Gaussian parameters (means, quats, scales, opacities, sh0, shN) for ``scene``.

    SfM points (capped at ``max_points``, subsampled with ``generator``) give means and colours;
    without points, ``num_random`` means are drawn uniformly in the scene bounds with random colours.
    Scales are the mean distance to the 3 nearest neighbours (x ``init_scale``), isotropic.
    """
    if scene.points is not None and scene.points.shape[0] > 0:
        pts = scene.points.float()
        cols = scene.point_colors.float() if scene.point_colors is not None else torch.full_like(pts, 0.5)
        if max_points is not None and pts.shape[0] > max_points:
            idx = torch.randperm(pts.shape[0], generator=generator)[:max_points].sort().values
            pts, cols = pts[idx], cols[idx]
    else:
        n = num_random if max_points is None else min(num_random, max_points)
        lo, hi = scene.bounds_min.float(), scene.bounds_max.float()
        pts = lo + (hi - lo) * torch.rand(n, 3, generator=generator)
        cols = torch.rand(n, 3, generator=generator)
        log.info("No SfM points: %d random Gaussians inside the scene bounds", n)
    if not torch.isfinite(pts).all():
        raise B3dgsError("Initial points contain NaN/Inf; check the scene's points3D / bounds",
                         fix="repair or drop the non-finite points of the scene's points3D (COLMAP) / ply_file_path, "
                             "or check that its poses are finite")
    n = pts.shape[0]
    dist = knn_mean_dist(pts).clamp_min(1e-7 * max(scene.extent, 1e-12))
    scales = torch.log(dist * init_scale).unsqueeze(-1).repeat(1, 3)
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    opac = torch.logit(torch.full((n,), float(init_opacity)))
    sh0 = rgb_to_sh0(cols.clamp(0, 1)).unsqueeze(1)
    shN = torch.zeros(n, (sh_degree + 1) ** 2 - 1, 3)
    return {"means": pts.clone().contiguous(), "quats": quats, "scales": scales, "opacities": opac, "sh0": sh0, "shN": shN}
