"""DPMM's pair-sum cadence, paired: the paper's every-step usage and Σ w² EMAs (``every1``, the default) against
reading the renderer's pair sums on every k-th step only (``every<k>``: ``posterior.dp.pair_sums_every=k
posterior.color.pair_sums_every=k``), over the seven scenes at the quick protocol (256 px, 3000 steps), on the CPU.

    python -m bench.dp_cadence                                  # 7 scenes x seeds 0 1 2, every1 and every4, 2 jobs
    python -m bench.dp_cadence --scenes fox --seeds 0 --jobs 1  # one pair
    python -m bench.dp_cadence --every 4 8                      # more cadences (each against every1)

The grid is bench/schedule.py's (variants of a scene-seed interleaved; finished runs reused and their small files
archived to bench/results/dp_cadence_runs, so it resumes across sessions; paired differences over scenes with
bootstrap CIs and sign-flip p); any other of its arguments passes through. Writes bench/results/dp_cadence.{json,md,png}.
On the CPU the sums come out of the rasterizer's forward pass almost free, so the time column says little: the cost
this cadence removes is gsplat's second pass over the pixel-pair list (``b3dgs.render.gsplat_backend.weight_sums``).
What this table judges is quality (PSNR, SSIM, LPIPS, #Gaussians): whether k > 1 may be the GPU's setting.
"""
from __future__ import annotations

import argparse
from typing import Optional

from bench.common import RESULTS
from bench.schedule import main as schedule_main


def variants(every: list[int]) -> list[str]:
    """``--variant`` arguments of bench/schedule.py: ``every1`` (the reference) and one ``every<k>`` per k > 1."""
    out = ["every1="]
    for k in every:
        if k < 1:
            raise SystemExit(f"bench/dp_cadence.py: --every {k} is not >= 1 (fix: pass cadences such as 4 8)")
        if k > 1:
            out.append(f"every{k}=posterior.dp.pair_sums_every={k} posterior.color.pair_sums_every={k}")
    return out


def main(argv: Optional[list[str]] = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], add_help=False)
    ap.add_argument("--every", type=int, nargs="+", default=[4], help="cadences k > 1 paired against every step")
    args, rest = ap.parse_known_args(argv)
    grid = ["--models", "dpmm", "--name", "dp_cadence", "--archive", str(RESULTS / "dp_cadence_runs"),
            "--out", "outputs/bench_dp_cadence", "--title", "DPMM pair-sum cadences side by side"]
    if "--variant" not in rest:
        for v in variants(args.every):
            grid += ["--variant", v]
    schedule_main(grid + rest)  # later arguments win: the caller's --name, --out, ... replace these


if __name__ == "__main__":
    main()
