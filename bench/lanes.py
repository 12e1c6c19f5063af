"""SIMD lane occupancy of the CPU rasterizer: how many of the pixel lanes that the kernels evaluate do any work.

    python -m bench.lanes [--sizes 100000] [--checkpoint RUN_DIR/checkpoints/last.ckpt ...] [--views 4]

The kernels process each row of a Gaussian's footprint in chunks of 8 pixels (kLanes). A lane is *live* when its
pixel lies in the row interval and is not terminated, *used* when the pixel also composites the Gaussian
(alpha >= 1/255). The backward walks chunks aligned to multiples of 8 columns (each pixel in lane column mod 8, for
bitwise-fixed gradient sums), so a narrow row that crosses a multiple of 8 costs two chunks. Per case this prints
the fractions, the backward's mean row width and share of rows at most 4 wide, and two bounds on what a different
chunking could save there: unaligned chunks (ceil(width / 8) per row) and perfect packing (pixels / 8).

Runs one forward+backward per case on an instrumented build of the extension (``B3DGS_LANE_STATS=1``, a separate
build cached beside the default one; its timings are not representative, so none are reported). Writes
bench/results/lanes.{json,md}; cases already in the JSON are skipped (resumes).
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

os.environ["B3DGS_LANE_STATS"] = "1"  # before the extension is loaded: the counting build

import torch  # noqa: E402

from bench.common import RESULTS, machine, table, write_results
from bench.render import camera, random_gaussians

from b3dgs.render._ext import load_extension  # noqa: E402
from b3dgs.render.renderers import make_renderer  # noqa: E402

NAMES = ["fwd_chunks", "fwd_live", "fwd_used", "bwd_chunks", "bwd_live", "bwd_used", "bwd_rows", "bwd_row_pixels",
         "bwd_narrow_rows", "bwd_unaligned_chunks", "bwd_aligned_chunks"]  # the order of b3dgs::LaneStat


def count(params: dict, cams: list, sh_degree: int) -> dict:
    """Counters of one forward+backward of every camera (CPU renderer), as occupancy fractions."""
    ext = load_extension()
    renderer = make_renderer("cpu")
    p = {k: v.detach().clone().requires_grad_(True) for k, v in params.items()}
    ext.lane_stats(True)
    for cam in cams:
        renderer.render(p, cam, sh_degree=sh_degree, retain_means2d_grad=True).rgb.sum().backward()
    c = dict(zip(NAMES, ext.lane_stats(True)))
    if not c:
        raise RuntimeError("bench/lanes.py: the extension was built without lane counters "
                           "(fix: run with B3DGS_LANE_STATS=1 set before anything loads b3dgs.render)")
    lanes = 8
    fr = lambda a, b: round(a / b, 4) if b else None  # noqa: E731
    return {
        "fwd_chunks": c["fwd_chunks"], "fwd_live": fr(c["fwd_live"], lanes * c["fwd_chunks"]),
        "fwd_used": fr(c["fwd_used"], lanes * c["fwd_chunks"]),
        "bwd_chunks": c["bwd_chunks"], "bwd_live": fr(c["bwd_live"], lanes * c["bwd_chunks"]),
        "bwd_used": fr(c["bwd_used"], lanes * c["bwd_chunks"]),
        "bwd_row_width": fr(c["bwd_row_pixels"], c["bwd_rows"]),
        "bwd_narrow_rows": fr(c["bwd_narrow_rows"], c["bwd_rows"]),
        # chunks of the row intervals (before skipping the chunks with no live lane) under other chunkings, relative to
        # today's aligned chunks: what unaligned starts or perfect packing could save at most
        "bwd_evaluated_vs_aligned": fr(c["bwd_chunks"], c["bwd_aligned_chunks"]),
        "bwd_unaligned_vs_aligned": fr(c["bwd_unaligned_chunks"], c["bwd_aligned_chunks"]),
        "bwd_packed_vs_aligned": fr(c["bwd_row_pixels"] / lanes, c["bwd_aligned_chunks"]),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[100_000], help="random Gaussians at 256 px (bench/render.py)")
    ap.add_argument("--checkpoint", nargs="*", default=[], help="trained checkpoints: their first --views test views")
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--name", default="lanes")
    args = ap.parse_args()
    torch.set_grad_enabled(True)
    out = RESULTS / f"{args.name}.json"
    rows = json.loads(out.read_text())["rows"] if out.exists() else []
    done = {r["case"] for r in rows}
    for n in args.sizes:
        case = f"random n={n}"
        if case not in done:
            rows.append({"case": case, "gaussians": n, **count(random_gaussians(n), [camera()], sh_degree=3)})
            print(rows[-1], flush=True)
    for ck in args.checkpoint:
        from b3dgs.runs import load_run

        run = load_run(Path(ck).parent.parent, checkpoint=ck)
        case = f"trained {run.scene.name} ({Path(ck).parent.parent.name}), {args.views} test views"
        if case in done:
            continue
        params = {k: v.detach() for k, v in run.module.params().items()}
        rows.append({"case": case, "gaussians": int(params["means"].shape[0]),
                     **count(params, list(run.scene.test)[: args.views], run.module.active_sh_degree())})
        print(rows[-1], flush=True)
    cols = ["case", "gaussians", "fwd_live", "fwd_used", "bwd_live", "bwd_used", "bwd_row_width", "bwd_narrow_rows",
            "bwd_evaluated_vs_aligned", "bwd_unaligned_vs_aligned", "bwd_packed_vs_aligned"]
    text = ("Share of the evaluated 8-pixel SIMD lanes that are live / used (bench/lanes.py), and the backward's chunk "
            "count under other chunkings relative to today's aligned one.\n\n" + table(rows, cols))
    write_results(args.name, {"machine": machine(), "rows": rows}, text)


if __name__ == "__main__":
    main()
