"""What a NIW count (or the SH posterior) costs a training run: its pass over the training views, against the run.

    python -m bench.count_cost --runs '/work/counts_s12/*/niw/s1'          # trained NIW runs (with checkpoints)
    python -m bench.count_cost --table-only

A count other than the paper's (``posterior.niw.count=weight|fisher|fisher3``) and ``posterior.sh`` are computed once,
from one pass over the training views after training (:meth:`b3dgs.module.SplatModule.prepare_posterior`); during
training the NIW block then skips its per-step EMA. So on a trained paper-count NIW run, the share a count's run gives
its blocks is at most (the paper block's in-run time + the pass) / (training time + the pass): the pass is timed
here, on the trained model (1 thread), for each count in turn. New runs record the same pass in metrics.json
(``posterior_pass_s``) and the report's block share includes it. Resumable: a finished (run, count) is skipped.

The run's training time was measured when it trained and the pass now, so that ratio ("clock") is only as fair as the
two machine loads are alike. The verdict uses a ratio measured side by side instead: the same process times a render's
forward and backward through every parameter on the run's training views right before and right after each pass (a
training step does that and more: loss, SSIM, Adam, densification), so (the paper block's in-run share) + pass /
(pass + steps × that time) bounds the share from above under any steady load ("side by side").

Output: bench/results/count_cost.{json,md}.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import time
from pathlib import Path

import numpy as np

from bench.common import RESULTS, machine, median_ms

COUNTS = ["weight", "fisher", "fisher3", "sh"]
BOUND = 5.0  # issue 29: the NIW block's share of the training time stays <= 5 %


def _blocks(module, count: str) -> list:
    """(name, block, state) triples that a run trained with this count would prepare after training."""
    from b3dgs_plugins.posterior.sh import SHPosteriorBlock
    from b3dgs_plugins.uq.native import NativeUQ

    if count == "sh":  # posterior=[niw,sh] with the paper count: only the SH block asks for a pass
        return NativeUQ(add={"sh": SHPosteriorBlock()}, model_blocks=False)._blocks(module)
    return NativeUQ(count=count)._blocks(module)


def render_step_s(module, cameras, views: int = 6) -> float:
    """Median seconds of one render's forward and backward through every parameter, cycling over up to ``views``
    training views (after one warm-up): the renderer's part of a training step, timed beside the passes."""
    import itertools

    import torch

    sp = module.params()
    cams = itertools.cycle(list(cameras)[:views])

    def step() -> None:
        params = {k: v.detach().requires_grad_(True) for k, v in sp.items()}
        with torch.enable_grad():
            ro = module.render_camera(next(cams), params=params, sh_degree=module.active_sh_degree())
            torch.autograd.grad(ro.rgb.sum(), list(params.values()), allow_unused=True)

    return round(median_ms(step, repeats=views, warmup=1) / 1000, 5)


def measure(run_dir: Path, counts: list[str], done: dict) -> dict:
    """{count: {pass_s, train_time_s, block_s, share_pct}} for one run (counts in ``done`` are kept)."""
    import torch

    from b3dgs.runs import load_run

    todo = [c for c in counts if c not in done]
    if not todo:
        return done
    torch.set_num_threads(1)
    run = load_run(run_dir)
    m, metrics = run.module, run.metrics or {}
    train_s, block_s = float(metrics["train_time_s"]), float(sum(metrics.get("block_time_s", {}).values()))
    steps = int(metrics["steps"])
    out = dict(done)
    for c in todo:
        blocks = _blocks(m, c)
        before = render_step_s(m, run.scene.train)
        t0 = time.perf_counter()
        ran = m.prepare_posterior(run.scene.train, blocks=blocks)
        pass_s = round(time.perf_counter() - t0, 3)
        step_s = round((before + render_step_s(m, run.scene.train)) / 2, 5)  # timed right before and right after
        if not ran:
            raise SystemExit(f"bench/count_cost.py: count {c} asked for no pass on {run_dir} (fix: a NIW run)")
        out[c] = {"pass_s": pass_s, "train_time_s": train_s, "block_s": block_s,
                  "views": len(run.scene.train), "gaussians": int(m.num_gaussians),
                  "share_pct": 100.0 * (block_s + pass_s) / (train_s + pass_s),
                  "steps": steps, "render_step_s": step_s,
                  "share_side_pct": 100.0 * (block_s / train_s + pass_s / (pass_s + steps * step_s))}
        print(f"{run_dir} {c}: pass {pass_s:.1f} s, share <= {out[c]['share_pct']:.2f} % (clock), "
              f"{out[c]['share_side_pct']:.2f} % (side by side)", flush=True)
    return out


def table(res: dict) -> str:
    runs = res["runs"]
    counts = [c for c in COUNTS if any(c in v for v in runs.values())]
    lines = ["# What a count costs a training run (the pass over the training views after training)", "",
             f"Command: `python -m bench.count_cost --runs ...`; {len(runs)} trained NIW runs (quick protocol), pass "
             f"timed on 1 thread ({res.get('load', '')}). Shares are upper bounds (a count's run skips the paper's "
             "per-step EMA, whose in-run time they include). Clock: (paper block s + pass) / (train s + pass), times "
             "from two machine loads. Side by side: paper block s / train s + pass / (pass + steps × the render's "
             f"forward + backward, timed beside the pass). Bound: ≤ {BOUND:g} %.",
             "", "| run | views | Gaussians | train s | paper block s | render fwd+bwd ms | "
             + " | ".join(f"{c} pass s / share % clock / side by side" for c in counts) + " |",
             "|---" * (6 + len(counts)) + "|"]
    for r, v in sorted(runs.items()):
        any_c = next(iter(v.values()))
        cells = [f"{v[c]['pass_s']:.1f} / {v[c]['share_pct']:.2f} / {v[c]['share_side_pct']:.2f}" if c in v else "—"
                 for c in counts]
        lines.append(f"| {r} | {any_c['views']} | {any_c['gaussians']:,} | {any_c['train_time_s']:.0f} | "
                     f"{any_c['block_s']:.1f} | {1000 * any_c['render_step_s']:.0f} | " + " | ".join(cells) + " |")
    lines += ["", "| count | mean share % side by side | max | runs ≤ bound | mean share % clock | max |",
              "|---|---|---|---|---|---|"]
    for c in counts:
        side = [v[c]["share_side_pct"] for v in runs.values() if c in v]
        clock = [v[c]["share_pct"] for v in runs.values() if c in v]
        lines.append(f"| {c} | {np.mean(side):.2f} | {max(side):.2f} | {sum(x <= BOUND for x in side)}/{len(side)} | "
                     f"{np.mean(clock):.2f} | {max(clock):.2f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    from b3dgs.io import atomic_path, write_json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", nargs="+", default=[], help="run dirs or glob patterns of trained NIW runs")
    ap.add_argument("--counts", nargs="+", default=COUNTS, choices=COUNTS)
    ap.add_argument("--load", default="", help="what else ran on the machine while the passes were timed (for the table)")
    ap.add_argument("--table-only", action="store_true")
    ap.add_argument("--name", default="count_cost", help="bench/results/<name>.{json,md}")
    ap.add_argument("--results-root", default=str(RESULTS), help="where <name>.{json,md} are (default bench/results)")
    args = ap.parse_args()
    root = Path(args.results_root)
    path = root / f"{args.name}.json"
    res = json.loads(path.read_text()) if path.is_file() else {"runs": {}}
    if not args.table_only:
        dirs = sorted({Path(p) for pat in args.runs for p in (glob.glob(pat) or [pat])})
        if not dirs:
            raise SystemExit("bench/count_cost.py: no runs (fix: --runs 'DIR/*/niw/s1', trained NIW run dirs)")
        for d in dirs:
            if not (d / "checkpoints" / "last.ckpt").is_file():
                raise SystemExit(f"bench/count_cost.py: {d} has no checkpoints/last.ckpt (fix: a finished run dir)")
        res.update(machine=machine(), load=args.load or res.get("load", ""), threads=1, cpus=os.cpu_count())
        for d in dirs:
            key = f"{d.parts[-3]}/{d.parts[-2]}/{d.parts[-1]}"  # scene/method/seed
            res["runs"][key] = measure(d, args.counts, res["runs"].get(key, {}))
            write_json(path, res)  # after every run: resumable
    if not res["runs"]:
        raise SystemExit(f"bench/count_cost.py: {path} holds no runs yet (fix: pass --runs)")
    md = table(res)
    with atomic_path(root / f"{args.name}.md") as tmp:
        tmp.write_text(md)
    print(md)


if __name__ == "__main__":
    main()
