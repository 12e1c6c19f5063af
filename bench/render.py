"""Renderer benchmark: forward and forward+backward of the full render (projection, binning,
rasterization) for every renderer plugin available here, side by side in one run, at 256x256.

    python -m bench.render [--sizes 10000 50000 100000] [--renderers cpu torch gsplat]
                           [--checkpoint RUN_DIR/checkpoints/last.ckpt]

Writes bench/results/render.json (rows {renderer, device, n, width, height, fwd_ms, fwdbwd_ms, pairs})
and a table. Medians after warm-up (CUDA synchronised); renderers are interleaved per size so machine
noise hits all alike. gsplat rows appear when CUDA and gsplat are present.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch

from bench.common import machine, median_ms, table, write_results

from b3dgs.render.renderers import Renderer, gsplat_available, make_renderer  # noqa: E402
from b3dgs.types import Camera  # noqa: E402


def random_gaussians(n: int, seed: int = 0) -> dict:
    """Gaussians spread in front of the camera with screen radii of a few pixels at 256x256."""
    g = torch.Generator().manual_seed(seed)
    means = torch.empty(n, 3)
    means[:, :2] = (torch.rand(n, 2, generator=g) - 0.5) * 2.0
    means[:, 2] = 3.0 + torch.rand(n, generator=g)
    return {"means": means, "quats": torch.randn(n, 4, generator=g),
            "scales": torch.log(0.004 + 0.012 * torch.rand(n, 3, generator=g)),
            "opacities": torch.logit(0.05 + 0.9 * torch.rand(n, generator=g)),
            "sh0": torch.randn(n, 1, 3, generator=g) * 0.5, "shN": torch.zeros(n, 15, 3)}


def camera(width: int = 256, height: int = 256) -> Camera:
    f = 0.5 * width / math.tan(math.radians(25))
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    return Camera("bench", K, torch.eye(4), width, height)


def time_case(params: dict, cam: Camera, renderer: Renderer, sh_degree: int) -> dict:
    dev = renderer.device
    p = {k: v.to(dev).clone().requires_grad_(True) for k, v in params.items()}
    cam = cam.to(dev)
    fwd = lambda: renderer.render(p, cam, sh_degree=sh_degree)  # noqa: E731

    def fwdbwd():
        out = renderer.render(p, cam, sh_degree=sh_degree, retain_means2d_grad=True)
        out.rgb.sum().backward()

    reps = 3 if renderer.name == "torch" else 7
    with torch.no_grad():
        f_ms = median_ms(fwd, repeats=reps, warmup=1, device=dev)
    fb_ms = median_ms(fwdbwd, repeats=reps, warmup=1, device=dev)
    with torch.no_grad():
        bins = fwd().bins
    return {"backend": renderer.name, "device": str(dev), "n": int(params["means"].shape[0]), "width": cam.width,
            "height": cam.height, "fwd_ms": round(f_ms, 2), "fwdbwd_ms": round(fb_ms, 2),
            "pairs": None if bins is None else int(bins.num_pairs)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 50_000, 100_000])
    ap.add_argument("--renderers", "--backends", nargs="+", default=None,
                    help="renderer options (default: cpu, torch, and gsplat when CUDA and gsplat are present)")
    ap.add_argument("--checkpoint", type=str, default=None, help="also time a trained checkpoint's test views")
    ap.add_argument("--name", default="render")
    args = ap.parse_args()
    names = args.renderers or (["cpu", "torch"] + (["gsplat"] if gsplat_available() else []))
    renderers = [make_renderer(n) for n in names]
    for r in renderers:
        r.check_available()
    rows = []
    cam = camera()
    for n in args.sizes:
        params = random_gaussians(n)
        for renderer in renderers:
            row = time_case(params, cam, renderer, sh_degree=3)
            row["scene"] = "random"
            rows.append(row)
            print(row, flush=True)
    if args.checkpoint:
        from b3dgs.runs import load_run

        run = load_run(Path(args.checkpoint).parent.parent, checkpoint=args.checkpoint)
        params = {k: v.detach() for k, v in run.module.params().items()}
        tcam = run.scene.test[0]
        for renderer in renderers:
            row = time_case(params, tcam, renderer, sh_degree=run.module.active_sh_degree())
            row["scene"] = f"trained:{run.scene.name}"
            rows.append(row)
            print(row, flush=True)
    ratios = []  # speed-up of each renderer over the pure-torch reference on the CPU, same size, same run
    for n in args.sizes:
        ref = [r for r in rows if r["n"] == n and r["backend"] == "torch" and r["device"] == "cpu"
               and r["scene"] == "random"]
        for r in rows:
            if ref and r["n"] == n and r["scene"] == "random" and r is not ref[0]:
                ratios.append({"n": n, "renderer": f"{r['backend']}@{r['device']}",
                               "fwd_speedup": round(ref[0]["fwd_ms"] / r["fwd_ms"], 2),
                               "fwdbwd_speedup": round(ref[0]["fwdbwd_ms"] / r["fwdbwd_ms"], 2)})
    text = table(rows, ["scene", "backend", "device", "n", "width", "height", "pairs", "fwd_ms", "fwdbwd_ms"])
    if ratios:
        text += "\n\n" + table(ratios, ["n", "renderer", "fwd_speedup", "fwdbwd_speedup"])
    write_results(args.name, {"machine": machine(), "rows": rows, "speedups": ratios}, text)


if __name__ == "__main__":
    main()
