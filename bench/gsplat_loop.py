"""A bare gsplat training loop: gsplat's ``examples/simple_trainer.py`` (1.5.3) at its defaults, without the rest.

    python -m bench.gsplat_loop --out DIR scene=fox experiment=paper trainer.max_steps=7000   # on a GPU

The yardstick b3dgs's trainer is compared with (issue 51, ``bench.device_paper``): ``gsplat.rasterization``
(``packed=False``, classic mode) and gsplat's ``DefaultStrategy()`` at its defaults, one Adam per parameter at
simple_trainer's learning rates (means ``1.6e-4 x scene_scale`` decayed to 1 % over the run), loss
``0.8 L1 + 0.2 (1 - SSIM)``, SH degree +1 every 1000 steps, one random training view per step. The scene, its split,
its resolution and the initial points come from b3dgs (the overrides select them as for ``b3dgs-train``): the same
loader, and the points b3dgs's own init draws for that seed; from them, simple_trainer's init (scales from the 3
nearest neighbours, random quaternions, opacity 0.1). The test views are scored by b3dgs's metric code
(:func:`b3dgs.metrics.views.evaluate_views`). Where it differs from simple_trainer: SSIM is b3dgs's separable SSIM
(the same 11-tap Gaussian window and valid padding as simple_trainer's ``fused_ssim``, which the GPU machine lacks),
``scene_scale`` is the scene's ``extent`` (already 1.1 x the camera radius, as simple_trainer's), views come
from memory, not a data loader, and the opacity reset every 3000 steps happens: gsplat 1.5.3's ``DefaultStrategy``
never resets (its test ``step % reset_every == 0 & step > 0`` is always false; fixed upstream in gsplat #776), so
where the installed gsplat has that test the loop resets as the fix does (``loop.json`` ``opacity_reset_fix``).
"""
from __future__ import annotations

import argparse
import inspect
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.nn.functional as F

SH_C0 = 0.28209479177387814


@dataclass
class LoopConfig:
    """simple_trainer's defaults (gsplat 1.5.3); ``strategy``: keyword arguments of ``DefaultStrategy`` (none: its own)."""

    steps: int = 30_000
    sh_degree: int = 3
    sh_degree_interval: int = 1000
    ssim_lambda: float = 0.2
    init_opa: float = 0.1
    init_scale: float = 1.0
    near_plane: float = 0.01
    far_plane: float = 1e10
    lrs: dict = field(default_factory=lambda: {"means": 1.6e-4, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2,
                                               "sh0": 2.5e-3, "shN": 2.5e-3 / 20})
    strategy: dict = field(default_factory=dict)


def knn_dist(points: torch.Tensor, k: int = 3, chunk: int = 4096) -> torch.Tensor:
    """simple_trainer's initial size: sqrt of the mean squared distance to the k nearest other points."""
    out = []
    for i in range(0, points.shape[0], chunk):
        d = torch.cdist(points[i:i + chunk], points)
        out.append(d.topk(min(k + 1, points.shape[0]), largest=False).values[:, 1:])
    return torch.cat(out).square().mean(-1).sqrt()


def init_splats(points: torch.Tensor, rgbs: torch.Tensor, lc: LoopConfig, scene_scale: float, device):
    """simple_trainer's ``create_splats_with_optimizers`` from given points and colours."""
    n = points.shape[0]
    scales = torch.log(knn_dist(points) * lc.init_scale).unsqueeze(-1).repeat(1, 3)
    colors = torch.zeros(n, (lc.sh_degree + 1) ** 2, 3)
    colors[:, 0] = (rgbs - 0.5) / SH_C0
    params = {"means": points, "scales": scales, "quats": torch.rand(n, 4),
              "opacities": torch.logit(torch.full((n,), lc.init_opa)), "sh0": colors[:, :1], "shN": colors[:, 1:]}
    splats = torch.nn.ParameterDict({k: torch.nn.Parameter(v.contiguous()) for k, v in params.items()}).to(device)
    lr = dict(lc.lrs, means=lc.lrs["means"] * scene_scale)
    optimizers = {k: torch.optim.Adam([{"params": splats[k], "lr": lr[k], "name": k}], eps=1e-15, fused=True)
                  for k in splats}
    return splats, optimizers


def rasterize(splats, cam, sh_degree: int, lc: LoopConfig):
    from gsplat import rasterization

    colors = torch.cat([splats["sh0"], splats["shN"]], 1)
    img, _, info = rasterization(
        means=splats["means"], quats=splats["quats"], scales=torch.exp(splats["scales"]),
        opacities=torch.sigmoid(splats["opacities"]), colors=colors, viewmats=cam.viewmat[None], Ks=cam.K[None],
        width=cam.width, height=cam.height, sh_degree=sh_degree, near_plane=lc.near_plane, far_plane=lc.far_plane,
        packed=False, absgrad=False, sparse_grad=False, rasterize_mode="classic")
    return img[0], info


class _Eval:
    """What :func:`b3dgs.metrics.views.evaluate_views` asks of a model: ``device`` and ``render_eval(camera)``."""

    def __init__(self, splats, lc: LoopConfig):
        self.splats, self.lc, self.device = splats, lc, splats["means"].device

    def render_eval(self, cam):
        return rasterize(self.splats, cam.to(self.device), self.lc.sh_degree, self.lc)[0].clamp(0, 1)


def train_loop(scene, points, rgbs, lc: LoopConfig, seed: int, device, lpips_model=None) -> dict:
    """Train on ``scene.train`` from ``points``/``rgbs``; returns the metrics of ``scene.test`` and the loop's time."""
    from gsplat import DefaultStrategy
    from gsplat.strategy.ops import reset_opa

    from b3dgs.device import timed_clock
    from b3dgs.metrics.views import evaluate_views
    from b3dgs.render.ssim import ssim_separable

    torch.manual_seed(seed)
    scene_scale = float(scene.extent)
    splats, optimizers = init_splats(points.float().cpu(), rgbs.float().cpu(), lc, scene_scale, device)
    strategy = DefaultStrategy(**lc.strategy)
    strategy.check_sanity(splats, optimizers)
    state = strategy.initialize_state(scene_scale=scene_scale)
    reset_fix = "reset_every == 0 & step" in inspect.getsource(DefaultStrategy.step_post_backward)
    sched = torch.optim.lr_scheduler.ExponentialLR(optimizers["means"], gamma=0.01 ** (1.0 / lc.steps))
    cams = [c.to(device) for c in scene.train]
    gen = torch.Generator().manual_seed(seed)
    order: list[int] = []
    t0 = timed_clock(device)
    for step in range(lc.steps):
        if not order:  # a shuffled pass over the training views, as simple_trainer's DataLoader
            order = torch.randperm(len(cams), generator=gen).tolist()
        cam = cams[order.pop()]
        img, info = rasterize(splats, cam, min(step // lc.sh_degree_interval, lc.sh_degree), lc)
        strategy.step_pre_backward(params=splats, optimizers=optimizers, state=state, step=step, info=info)
        loss = (1 - lc.ssim_lambda) * F.l1_loss(img, cam.image) + lc.ssim_lambda * (1 - ssim_separable(img, cam.image))
        loss.backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        sched.step()
        strategy.step_post_backward(params=splats, optimizers=optimizers, state=state, step=step, info=info,
                                    packed=False)
        if reset_fix and 0 < step < strategy.refine_stop_iter and step % strategy.reset_every == 0:
            reset_opa(params=splats, optimizers=optimizers, state=state, value=strategy.prune_opa * 2.0)
    train_s = timed_clock(device) - t0
    ev = evaluate_views(_Eval(splats, lc), scene.test, lpips_model=lpips_model)
    return {"psnr": ev.get("psnr"), "ssim": ev.get("ssim"), "lpips": ev.get("lpips"), "steps": lc.steps,
            "num_gaussians": int(splats["means"].shape[0]), "train_time_s": round(train_s, 3),
            "render_fps": ev["render_fps"], "opacity_reset_fix": reset_fix, "per_view": ev["per_view"]}


def run_from_config(cfg, out: Path, lc: LoopConfig, device, lpips_model=None) -> dict:
    """The loop on the scene, split, resolution and initial points of b3dgs config ``cfg``; ``out/loop.json``
    (the comparator's record; ``metrics.json`` is a b3dgs run's)."""
    from b3dgs.init import init_gaussians
    from b3dgs.io import write_json
    from b3dgs.lifecycle import data_module, seed_run

    seed_run(int(cfg.seed))
    scene = data_module(cfg.data).scene
    m = cfg.model
    init = init_gaussians(scene, int(m.sh_degree), m.init_max_points, int(m.init_num_random), float(m.init_opacity),
                          float(m.init_scale), generator=torch.Generator().manual_seed(int(cfg.seed)))
    metrics = train_loop(scene, init["means"], init["sh0"][:, 0] * SH_C0 + 0.5, lc, int(cfg.seed), device,
                         lpips_model)
    metrics.update(method="gsplat_loop", scene=scene.name, seed=int(cfg.seed), num_initial=int(init["means"].shape[0]),
                   num_train_views=len(scene.train), num_test_views=len(scene.test))
    write_json(Path(out) / "loop.json", metrics)
    return metrics


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("overrides", nargs="*", help="b3dgs-train overrides selecting scene and protocol")
    args = ap.parse_args()
    from b3dgs.metrics.lpips import get_lpips

    from bench.common import compose

    cfg = compose("train", [*args.overrides, "trainer.default_root_dir=."])
    t = time.perf_counter()
    m = run_from_config(cfg, Path(args.out), LoopConfig(steps=int(cfg.trainer.max_steps)), args.device, get_lpips()[0])
    print({k: v for k, v in m.items() if k != "per_view"}, f"wall {time.perf_counter() - t:.1f} s")


if __name__ == "__main__":
    main()
