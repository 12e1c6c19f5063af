"""Cost of S native posterior samples on one view, side by side in one run:

- ``point x S``: S separate renders of the point estimate (what "S renders" costs, no sampling);
- ``chunk 1``: S draws, each drawn and rendered on its own;
- ``chunk c``: draws of c samples rendered in one call that shares the posterior set-up, the
  projection call and the tile binning (the native regime's default is c = 10).

    python -m bench.uq_sampling [--run RUN_DIR] [--samples 50] [--chunks 1 10 25 50]

Without --run, a NIW model is initialised on the synthetic scene at 256 px. Writes
bench/results/uq_sampling.json and a table with the speed-ups.
"""
from __future__ import annotations

import argparse

import torch

from bench.common import machine, median_ms, table, write_results


def build(run: str | None):
    if run:
        from b3dgs.runs import load_run

        r = load_run(run)
        return r.module, r.scene
    from b3dgs.data import load_scene
    from b3dgs.module import SplatModule
    from b3dgs_plugins.posterior.niw import NIWBlock
    from b3dgs_plugins.strategy.default import AdaptiveDensityControl

    scene = load_scene("synthetic", None, max_side=256, resolution=256)
    m = SplatModule(strategy=AdaptiveDensityControl(), posterior={"niw": NIWBlock()}, max_steps=3000)
    m.init_from_scene(scene)
    m.states["niw"]["N"].fill_(5.0)
    m._loaded_step = 3000
    return m, scene


def main() -> None:
    from b3dgs_plugins.uq.native import NativeUQ

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", default=None)
    ap.add_argument("--samples", type=int, default=50)
    ap.add_argument("--chunks", type=int, nargs="+", default=[1, 10, 25, 50])
    args = ap.parse_args()
    module, scene = build(args.run)
    cam = scene.test[0]
    common = {"samples": args.samples, "gaussians": module.num_gaussians, "width": cam.width, "height": cam.height}

    def point_renders():
        with torch.no_grad():
            for _ in range(args.samples):
                module.render_eval(cam)

    rows = [{"mode": f"point x {args.samples}", "chunk": "-", **common,
             "ms": round(median_ms(point_renders, repeats=3, warmup=1), 1)}]
    print(rows[-1], flush=True)
    for chunk in args.chunks:
        reg = NativeUQ(samples=args.samples, chunk=chunk)
        reg.fit([module], scene)
        ms = median_ms(lambda: reg.predict(cam, torch.Generator().manual_seed(0)), repeats=3, warmup=1)
        rows.append({"mode": "native", "chunk": chunk, **common, "ms": round(ms, 1)})
        print(rows[-1], flush=True)
    point = rows[0]["ms"]
    separate = next((r["ms"] for r in rows if r["chunk"] == 1), None)
    for r in rows:
        r["speedup_vs_point_renders"] = round(point / r["ms"], 2)
        r["speedup_vs_separate_samples"] = round(separate / r["ms"], 2) if separate else None
    text = table(rows, ["mode", "samples", "chunk", "gaussians", "width", "height", "ms", "speedup_vs_point_renders",
                        "speedup_vs_separate_samples"])
    write_results("uq_sampling", {"machine": machine(), "rows": rows}, text)


if __name__ == "__main__":
    main()
