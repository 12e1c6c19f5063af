"""The GPU call that measures it all (issue 51): parity, the paper's protocol beside a bare gsplat loop, and 30k.

    python -m bench.device_paper [--deadline-s 480] [--scenes fox ethiopian_head]      # on a GPU (device_check.sh paper)
    python -m bench.device_paper --dry-run --work DIR                                   # the same on the CPU, tiny

In priority order, each run in this process, one after another (so timings never share the GPU):
(a) parity: standard, NIW and DPMM at the quick protocol (``experiment=study``: 256 px, 3000 steps) on gsplat, seeds
0 and 1 (seed 0 of every scene first); (b) the paper's protocol at 7k steps (``experiment=paper
trainer.max_steps=7000``: full resolution of the carried images, every 8th view held out, every SfM point): b3dgs
standard beside the bare gsplat loop of :mod:`bench.gsplat_loop` (the same loader, split, resolution and initial
points; the same metric code), then NIW and DPMM; (c) standard at 30k steps on one scene. The order is (a) seed 0,
(b) standard and loop, (a) the other seeds, (b) NIW and DPMM, (c).

Resumable: each run has its dir under ``--work`` (``runs/<part>/<scene>/<model>/s<seed>``) and a finished one
(``metrics.json``, the loop's ``loop.json``) is kept, so a second call on the same warm machine continues. A run is
started only if its estimated time (what the same kind of run took here, else standard's time per step scaled, else a
prior) fits in what is left of ``--deadline-s``; a skipped run is listed. After every run ``device_<card>.{md,json}``
are rewritten (``--results``, default bench/results, and ``--out``; card: the GPU's short name, e.g. ``h200``).
``--dry-run [cpu|torch|gsplat]``: the CPU at a tiny size (32 px, 100 initial points, 8-16 steps with every step count of
the schedules scaled down), b3dgs on that renderer (default ``cpu``: ``torch`` trained a 12-step run in 51 s against
4.4 s on this 2-core machine; ``gsplat``: gsplat's Python over the emulation), the loop on gsplat's Python over the CPU
emulation of its kernels (tests/gsplat_cpu.py); card ``cpu``, results under ``--work``.
"""
from __future__ import annotations

import argparse
import contextlib
import gc
import io
import json
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from bench.common import (ROOT, RESULTS, compose, load_file, machine, model_overrides, scene_overrides, table,
                          write_results)
from bench.device_profile import PARITY_COLUMNS, parity_ratios

LOOP = "gsplat_loop"  # the bare gsplat loop's model name in the rows
PARTS = ("parity", "paper", "long")
STEPS = {"parity": 3000, "paper": 7000, "long": 30000}
DRY_STEPS = {"parity": 8, "paper": 12, "long": 16}
# the protocols (b3dgs-train overrides); "paper" and "long" add trainer.max_steps. Training only: no logger, no renders
PROTOCOL = {"parity": ["experiment=study"],
            "paper": ["experiment=paper", "logger=none", "trainer.save_renders=false"],
            "long": ["experiment=paper", "logger=none", "trainer.save_renders=false"]}
# dry-run: tiny images and models, and every step count of the schedules scaled to the few steps, so that
# densification, the opacity reset, the SH increase and the posterior stages all happen (b3dgs and the loop alike)
DRY = {"max_side": 32, "init_points": 100, "refine_start": 2, "refine_every": 4, "reset_every": 9, "sh_every": 4}
# estimates before anything has run here: standard's seconds per step on an H200 (gsplat; quick: 20.7 s / 3000,
# device_h200.md), each model's factor on it, and the fixed cost of a run (scene, init, final evaluation, files)
PRIOR_S_PER_STEP = {"parity": 0.0075, "paper": 0.010, "long": 0.012}
FACTOR = {"standard": 1.0, "niw": 1.05, "dpmm": 1.6, LOOP: 0.7}
OVERHEAD_S = 8.0


@dataclass(frozen=True)
class Run:
    part: str
    scene: str
    model: str
    seed: int

    @property
    def key(self) -> str:
        return f"{self.part}/{self.scene}/{self.model}/s{self.seed}"


def plan(scenes, seeds, long_scene: str | None, parts=PARTS) -> list[Run]:
    """The runs in priority order (module docstring)."""
    parity = lambda ss: [Run("parity", sc, m, s) for s in ss for sc in scenes for m in ("standard", "niw", "dpmm")]  # noqa: E731
    runs = parity(seeds[:1]) + [Run("paper", sc, m, 0) for sc in scenes for m in ("standard", LOOP)]
    runs += parity(seeds[1:]) + [Run("paper", sc, m, 0) for sc in scenes for m in ("niw", "dpmm")]
    runs += [Run("long", long_scene, "standard", 0)] if long_scene else []
    return [r for r in runs if r.part in parts]


def steps_of(run: Run, dry: str | None) -> int:
    return (DRY_STEPS if dry else STEPS)[run.part]


def protocol_overrides(part: str, dry: str | None) -> list[str]:
    """The b3dgs-train overrides of a part's protocol, renderer included. ``dry`` (here and below): None on the GPU,
    else the dry-run's renderer for b3dgs (cpu, torch or gsplat: gsplat's Python over the CPU emulation)."""
    out = [*PROTOCOL[part], "trainer.enable_progress_bar=false"]
    if part != "parity" or dry:
        steps = (DRY_STEPS if dry else STEPS)[part]
        out += [f"trainer.max_steps={steps}", f"trainer.eval_every={steps}"]
    if not dry:
        return out + ["renderer=gsplat"]
    renderer = [f"renderer={dry}"] + ([] if dry == "cpu" else ["renderer.device_name=cpu"])
    return out + [*renderer, f"data.max_side={DRY['max_side']}",
                  f"model.init_max_points={DRY['init_points']}", f"model.init_num_random={DRY['init_points']}",
                  f"strategy.refine_start={DRY['refine_start']}", f"strategy.refine_every={DRY['refine_every']}",
                  f"strategy.reset_every={DRY['reset_every']}", f"model.sh_increase_every={DRY['sh_every']}",
                  "trainer.checkpoint_every=1000000", "trainer.checkpoint_every_s=0"]


def overrides(run: Run, dry: str | None) -> list[str]:
    """The b3dgs-train overrides of ``run`` (the loop reads its scene, split, resolution and points from them)."""
    model = "standard" if run.model == LOOP else run.model
    return [*scene_overrides(run.scene), *model_overrides(model), f"seed={run.seed}",
            *protocol_overrides(run.part, dry)]


def loop_config(run: Run, dry: str | None):
    """simple_trainer's defaults; under dry-run its schedule scaled as b3dgs's is (``DRY``)."""
    from bench.gsplat_loop import LoopConfig

    if not dry:
        return LoopConfig(steps=steps_of(run, dry))
    return LoopConfig(steps=steps_of(run, dry), sh_degree_interval=DRY["sh_every"],
                      strategy={"refine_start_iter": DRY["refine_start"], "refine_every": DRY["refine_every"],
                                "reset_every": DRY["reset_every"]})


def card_name(dry: str | None) -> str:
    """``cpu`` under dry-run; else the GPU's short name (h200, h100, a100, l40s, l4) or its whole name, sanitised."""
    if dry or not torch.cuda.is_available():
        return "cpu"
    name = torch.cuda.get_device_name(0).lower().replace("nvidia", "")
    known = next((c for c in ("h200", "h100", "a100", "l40s", "l4") if c in name.split() or name.strip() == c), None)
    return known or re.sub(r"[^a-z0-9]+", "_", name).strip("_") or "gpu"


def estimate_s(run: Run, rows: list[dict], dry: str | None) -> float:
    """Seconds ``run`` should take: the slowest finished run of its part and model here, else standard's time per
    step of its part scaled by the model's factor, else the prior."""
    same = [r["wall_s"] for r in rows if r["part"] == run.part and r["model"] == run.model and r.get("wall_s")]
    if same:
        return max(same)
    std = [r["wall_s"] / r["steps"] for r in rows if r["part"] == run.part and r["model"] == "standard"
           and r.get("wall_s") and r.get("steps")]
    per_step = max(std) if std else PRIOR_S_PER_STEP[run.part]
    return (0.0 if std else OVERHEAD_S) + steps_of(run, dry) * per_step * FACTOR[run.model]


def row_of(run: Run, m: dict, wall_s: float | None) -> dict:
    blocks = sum((m.get("block_time_s") or {}).values())
    rend = m.get("renderer")
    return {"part": run.part, "scene": run.scene, "model": run.model, "seed": run.seed, "steps": m.get("steps"),
            "renderer": LOOP if run.model == LOOP else (rend.get("name") if isinstance(rend, dict) else rend),
            "psnr": m.get("psnr"), "ssim": m.get("ssim"), "lpips": m.get("lpips"),
            "num_gaussians": m.get("num_gaussians"), "train_time_s": m.get("train_time_s"),
            "wall_s": None if wall_s is None else round(wall_s, 2),
            "block_share": round(blocks / m["train_time_s"], 4) if m.get("train_time_s") else None}


def execute(run: Run, work: Path, dry: str | None, lpips_model) -> dict:
    """Train ``run`` in this process (b3dgs's ``train`` or the loop) into its run dir; returns its row."""
    from b3dgs.io import write_json
    from b3dgs.train import train
    from bench.gsplat_loop import run_from_config

    run_dir = work / "runs" / run.key
    cfg = compose("train", [*overrides(run, dry), f"trainer.default_root_dir={run_dir}", "overwrite=true"])
    t0 = time.perf_counter()
    if run.model == LOOP:
        run_dir.mkdir(parents=True, exist_ok=True)
        m = run_from_config(cfg, run_dir, loop_config(run, dry), "cpu" if dry else "cuda", lpips_model)
    else:
        m = train(cfg)
    wall = time.perf_counter() - t0
    write_json(run_dir / "wall.json", {"wall_s": wall})
    return row_of(run, m, wall)


def warm_up(scene: str, work: Path, dry: str | None) -> float:
    """A short standard run, not reported, before the first timed one: this process's first use of the GPU and of
    gsplat's kernels (CUDA context, loading the built extension) would otherwise fall inside the first run's time
    (each run used to be a process of its own, paying it once each). Returns its seconds."""
    from b3dgs.train import train

    t0 = time.perf_counter()
    steps = 5 if dry else 100
    train(compose("train", [*overrides(Run("parity", scene, "standard", 0), dry), f"trainer.max_steps={steps}",
                            f"trainer.eval_every={steps}", f"trainer.default_root_dir={work / 'warmup'}",
                            "overwrite=true"]))
    return time.perf_counter() - t0


def finished(run: Run, work: Path) -> dict | None:
    """The row of a run finished in an earlier call (its ``metrics.json``, the loop's ``loop.json``), else None."""
    run_dir = work / "runs" / run.key
    done = run_dir / ("loop.json" if run.model == LOOP else "metrics.json")
    if not done.is_file():
        return None
    wall = json.loads((run_dir / "wall.json").read_text())["wall_s"] if (run_dir / "wall.json").is_file() else None
    return row_of(run, json.loads(done.read_text()), wall)


def paper_tables(rows: list[dict], part: str) -> tuple[list[dict], list[dict]]:
    """Per scene, the runs of ``part`` side by side with the loop's (time and PSNR against it); and the check of
    b3dgs standard against the loop (PSNR within 0.1 dB or above it, at <= 1.3x its training time)."""
    side, checks = [], []
    for scene in sorted({r["scene"] for r in rows if r["part"] == part}):
        here = [r for r in rows if r["part"] == part and r["scene"] == scene]
        loop = next((r for r in here if r["model"] == LOOP), None)
        for r in sorted(here, key=lambda r: [LOOP, "standard", "niw", "dpmm"].index(r["model"])):
            x = dict(r)
            if loop and loop["train_time_s"]:
                x["x_loop_time"] = round(r["train_time_s"] / loop["train_time_s"], 3)
                x["dpsnr_vs_loop"] = round(r["psnr"] - loop["psnr"], 3)
            side.append(x)
        std = next((r for r in here if r["model"] == "standard"), None)
        if loop and std:
            dp, xt = std["psnr"] - loop["psnr"], std["train_time_s"] / loop["train_time_s"]
            checks.append({"scene": scene, "psnr_loop": round(loop["psnr"], 3), "psnr_standard": round(std["psnr"], 3),
                           "dpsnr": round(dp, 3), "x_loop_time": round(xt, 3), "target": "dpsnr >= -0.1, x <= 1.3",
                           "met": dp >= -0.1 and xt <= 1.3})
    return side, checks


RUN_COLS = ["scene", "model", "seed", "steps", "psnr", "ssim", "lpips", "num_gaussians", "train_time_s", "wall_s",
            "block_share"]
SIDE_COLS = ["scene", "model", "psnr", "ssim", "lpips", "num_gaussians", "train_time_s", "wall_s", "x_loop_time",
             "dpsnr_vs_loop"]


def report(rows: list[dict], skipped: list[dict], args, card: str, elapsed_s: float, quiet: bool = True) -> None:
    """``device_<card>.{json,md}`` from the rows so far, in ``args.results`` and ``args.out`` (rewritten after every
    run; ``quiet``: without printing the tables)."""
    parity = [r for r in rows if r["part"] == "parity"]
    ratios = parity_ratios(parity)
    for r in ratios:  # which seeds each scene's pairs came from
        if r["scene"] != "mean over scenes":
            r["seed_list"] = sorted({p["seed"] for p in parity if p["scene"] == r["scene"] and p["model"] == r["model"]})
    side, checks = paper_tables(rows, "paper")
    long_rows = [r for r in rows if r["part"] == "long"]
    m = machine()
    what = "CPU dry-run (tiny: not a measurement)" if args.dry else f"NVIDIA {card.upper()}"
    payload = {"card": card, "dry_run": bool(args.dry), "machine": m, "elapsed_s": round(elapsed_s, 1),
               "command": "bash scripts/device_check.sh paper" + (" --dry-run" if args.dry else ""),
               "protocols": {p: protocol_overrides(p, args.dry) for p in PARTS},
               "ratios": ratios, "paper_7k": side, "paper_checks": checks, "long_30k": long_rows,
               "runs": rows, "skipped": skipped}
    lines = [f"# The paper's protocol on the GPU, beside a bare gsplat loop: {what} (issue 51)", "",
             f"Machine: {m.get('cuda_device') or m.get('processor') or m.get('machine')}, torch {m.get('torch')}, "
             f"Python {m.get('python')}. Command: `{payload['command']}` (the device tool, `carry: [\".device\"]`); "
             f"{len(rows)} runs, this call {elapsed_s:.0f} s.", "",
             "## (a) Training time against standard (quick protocol, gsplat; seed means)", "",
             table(ratios, PARITY_COLUMNS), "",
             "## (b) The paper's protocol at 7k steps: b3dgs beside the bare gsplat loop (bench/gsplat_loop.py)", "",
             "The same loader, split (every 8th view held out), full resolution of the carried images and initial "
             "points; the same metric code. `x_loop_time`: training time over the loop's; `dpsnr_vs_loop`: PSNR minus "
             "the loop's.", "", table(side, SIDE_COLS), "", "Target: b3dgs standard within 0.1 dB of the loop at "
             "<= 1.3x its time.", "", table(checks, ["scene", "psnr_loop", "psnr_standard", "dpsnr", "x_loop_time",
                                                    "met"]), "",
             "## (c) Standard at 30k steps", "", table(long_rows, RUN_COLS) if long_rows else "not run", "",
             "## Every run", "", table(rows, ["part", *RUN_COLS]), ""]
    if skipped:
        lines += ["## Not run in this call (resume: run the same command again on the warm machine)", "",
                  table(skipped, ["run", "reason"]), ""]
    for root in dict.fromkeys(r for r in (args.results, args.out) if r):
        with contextlib.redirect_stdout(io.StringIO()) if quiet else contextlib.nullcontext():
            write_results(f"device_{card}", payload, "\n".join(lines), root=Path(root))
        quiet = True  # the tables once


def install_cpu_gsplat() -> None:
    """gsplat's Python over the CPU emulation of its kernels (tests/gsplat_cpu.py), for the dry-run's loop."""
    emu = load_file(ROOT / "tests" / "gsplat_cpu.py")
    sys.modules[emu.__name__] = emu  # install() hands gsplat this module by its name
    emu.install()


def default_scenes(dry: str | None) -> list[str]:
    """fox and ethiopian_head; under dry-run, the embedded synthetic scene where their folders are missing."""
    from b3dgs import data_root

    scenes = ["fox", "ethiopian_head"]
    if dry and not all((Path(data_root()) / s).is_dir() for s in scenes):
        print(f"device_paper: no {' and '.join(scenes)} under {data_root()}: the dry-run trains the synthetic scene",
              flush=True)
        return ["synthetic"]
    return scenes


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=None, help="default: fox ethiopian_head (default_scenes)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--long-scene", default=None, help="(c)'s scene (default: the last of --scenes; 'none': no 30k)")
    ap.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS))
    ap.add_argument("--deadline-s", type=float, default=480.0, help="start no run that would end after this")
    ap.add_argument("--work", default="outputs/device/paper", help="run dirs (kept: a second call resumes)")
    ap.add_argument("--results", default=None, help="device_<card>.{md,json} (default bench/results; dry-run: WORK/results)")
    ap.add_argument("--out", default=None, help="also write device_<card>.{md,json} here (the device tool's $OUT)")
    ap.add_argument("--dry-run", dest="dry", nargs="?", const="cpu", default=None, choices=["cpu", "torch", "gsplat"],
                    help="the CPU at a tiny size, b3dgs on this renderer (default cpu; module docstring)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    work = Path(args.work)
    args.results = args.results or str(work / "results" if args.dry else RESULTS)
    card = card_name(args.dry)
    if args.dry:
        install_cpu_gsplat()
    from b3dgs.metrics.lpips import get_lpips

    lpips_model = get_lpips()[0]
    scenes = args.scenes or default_scenes(args.dry)
    long_scene = None if args.long_scene == "none" else (args.long_scene or scenes[-1])
    rows, skipped, warm = [], [], False
    for run in plan(scenes, args.seeds, long_scene, args.parts):
        row = finished(run, work)
        if row is None:
            left = args.deadline_s - (time.perf_counter() - t0)
            need = estimate_s(run, rows, args.dry)
            if need > left:
                skipped.append({"run": run.key, "reason": f"needs ~{need:.0f} s, {max(left, 0):.0f} s left"})
                print(f"device_paper: skip {run.key} (needs ~{need:.0f} s, {left:.0f} s left)", flush=True)
                continue
            if not warm:
                print(f"device_paper: warm-up {warm_up(run.scene, work, args.dry):.1f} s", flush=True)
                warm = True
            print(f"device_paper: {run.key} (~{need:.0f} s, {left:.0f} s left)", flush=True)
            row = execute(run, work, args.dry, lpips_model)
            gc.collect()
            if torch.cuda.is_available():
                torch.cuda.empty_cache()
        rows.append(row)
        report(rows, skipped, args, card, time.perf_counter() - t0)
        print(f"device_paper: {run.key} PSNR {row['psnr']:.3f}, {row['num_gaussians']} Gaussians, train "
              f"{row['train_time_s']:.1f} s, wall {row['wall_s'] or float('nan'):.1f} s", flush=True)
    report(rows, skipped, args, card, time.perf_counter() - t0, quiet=False)
    print(f"device_paper: {len(rows)} runs done, {len(skipped)} skipped, {time.perf_counter() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
