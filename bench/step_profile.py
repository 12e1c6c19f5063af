"""Where a training step's time goes: per-step milliseconds by phase, and the kernels' ns per pixel–Gaussian pair.

    python -m bench.step_profile [--scenes ethiopian_head fox] [--steps 1500] [--models standard]
                                 [--code DIR --label NAME]   # profile another checkout (e.g. a git worktree)

Each case trains in a subprocess (``PYTHONPATH=--code``, default this checkout) through ``b3dgs.train.train``
with the phases' functions wrapped by wall-clock timers; nothing in the package is changed. Phases:
projection fwd/bwd (preprocess), binning, rasterize fwd/bwd, SSIM fwd/bwd, checks (input validation and the
renderer's guards, where they exist as separate passes), optimizer (Adam step), strategy (densification
hooks), posterior blocks, and "rest" = the step's wall time minus all of them (Lightning, the loss, Python).
``ns/pair`` is rasterize fwd+bwd time over (tile pairs x pixels per tile), the pairs the kernels walk.

Writes bench/results/step_profile.json and .md (rows keyed by label, scene, model; a row already there is
kept, so the benchmark resumes; ``--force`` re-measures).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from bench.common import QUICK, RESULTS, machine, model_overrides, scene_overrides, table, write_results

ROOT = Path(__file__).resolve().parents[1]
PHASES = ("projection_fwd", "projection_bwd", "binning", "raster_fwd", "raster_bwd", "ssim_fwd", "ssim_bwd",
          "checks", "optimizer", "strategy", "posterior")

# The child: wraps the phases' functions of whatever checkout is on PYTHONPATH, trains, prints one JSON line.
CHILD = r'''
import json, sys, time, importlib
from collections import defaultdict
T = defaultdict(float); C = defaultdict(int); PAIRS = [0, 0]

def wrap(owner, attr, phase, static=False):
    fn = getattr(owner, attr, None)
    if fn is None:
        return False
    def timed(*a, **k):
        t0 = time.perf_counter()
        try:
            return fn(*a, **k)
        finally:
            T[phase] += time.perf_counter() - t0
            C[phase] += 1
    setattr(owner, attr, staticmethod(timed) if static else timed)
    return True

def mod(name):
    try:
        return importlib.import_module(name)
    except ImportError:
        return None

pre, ras, img = mod("b3dgs.render.preprocess"), mod("b3dgs.render.rasterize"), mod("b3dgs.metrics.image")
wrap(pre._PreprocessCPU, "forward", "projection_fwd", static=True)
wrap(pre._PreprocessCPU, "backward", "projection_bwd", static=True)
wrap(ras._RasterizeCPU, "forward", "raster_fwd", static=True)
wrap(ras._RasterizeCPU, "backward", "raster_bwd", static=True)
wrap(img._SSIMFused, "forward", "ssim_fwd", static=True)
wrap(img._SSIMFused, "backward", "ssim_bwd", static=True)
for attr in ("_check_inputs",):
    wrap(ras, attr, "checks")
for attr in ("guarded_params",):
    wrap(pre, attr, "checks")
_bin = ras._BIN_BACKENDS["cpu"]
def bin_counted(*a, **k):
    t0 = time.perf_counter()
    b = _bin(*a, **k)
    T["binning"] += time.perf_counter() - t0
    PAIRS[0] += b.num_pairs * b.tile_size * b.tile_size
    PAIRS[1] += 1
    return b
ras._BIN_BACKENDS["cpu"] = bin_counted
import torch
wrap(torch.optim.Adam, "step", "optimizer")
module = importlib.import_module("b3dgs.module")
_hooks = module.SplatModule._call_hooks
def call_hooks(self, hook, optimizers, step, info):
    for name in list(self.posterior.keys()) + ["strategy"]:
        plugin = self.plugins[name]
        t0 = time.perf_counter()
        getattr(plugin, hook)(splats=self.splats, optimizers=optimizers, state=self.states[name], step=step, info=info)
        dt = time.perf_counter() - t0
        T["strategy" if name == "strategy" else "posterior"] += dt
        if name in self.block_time_s:
            self.block_time_s[name] += dt
module.SplatModule._call_hooks = call_hooks
from hydra import compose, initialize_config_dir
from b3dgs import train as tr
with initialize_config_dir(config_dir=tr.CONF_DIR, version_base="1.3"):
    cfg = compose("train", overrides=sys.argv[1:])
t0 = time.perf_counter()
m = tr.train(cfg)
steps = m["steps"]
ms = {k: 1000.0 * T[k] / steps for k in T}
total = 1000.0 * m["train_time_s"] / steps
out = {"steps": steps, "train_time_s": m["train_time_s"], "psnr": m["psnr"], "num_gaussians": m["num_gaussians"],
       "step_ms": total, "phase_ms": ms, "rest_ms": total - sum(ms.values()),
       "ns_per_pair": 1e9 * (T["raster_fwd"] + T["raster_bwd"]) / max(PAIRS[0], 1) if PAIRS[1] else None,
       "pairs_per_step": PAIRS[0] / max(PAIRS[1], 1)}
print("STEP_PROFILE " + json.dumps(out), flush=True)
'''


def run_case(code: Path, scene: str, model: str, steps: int, threads: int | None) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        overrides = scene_overrides(scene) + QUICK + [*model_overrides(model), f"trainer.max_steps={steps}",
                                                      "renderer=cpu", f"trainer.default_root_dir={tmp}/run",
                                                      "trainer.eval_every=100000"]
        if threads:
            overrides.append(f"threads={threads}")
        env = dict(os.environ, PYTHONPATH=str(code))
        res = subprocess.run([sys.executable, "-c", CHILD, *overrides], env=env, capture_output=True, text=True,
                             cwd=tmp)
    line = [ln for ln in res.stdout.splitlines() if ln.startswith("STEP_PROFILE ")]
    if res.returncode != 0 or not line:
        raise RuntimeError(f"profiling {scene}/{model} with {code} failed:\n{res.stderr[-3000:]}")
    return json.loads(line[-1][len("STEP_PROFILE "):])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["ethiopian_head", "fox"])
    ap.add_argument("--models", nargs="+", default=["standard"])
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--code", type=Path, default=ROOT, help="checkout whose b3dgs is profiled")
    ap.add_argument("--label", default="current")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--name", default="step_profile")
    ap.add_argument("--force", action="store_true")
    args = ap.parse_args()
    path = RESULTS / f"{args.name}.json"
    rows = json.loads(path.read_text())["rows"] if path.exists() else []
    for scene in args.scenes:
        for model in args.models:
            key = (args.label, scene, model, args.steps)
            if not args.force and any((r["label"], r["scene"], r["model"], r["steps"]) == key for r in rows):
                continue
            prof = run_case(args.code.resolve(), scene, model, args.steps, args.threads)
            row = {"label": args.label, "scene": scene, "model": model, **prof}
            rows = [r for r in rows if (r["label"], r["scene"], r["model"], r["steps"]) != key] + [row]
            print(json.dumps(row), flush=True)
            write_results(args.name, {"machine": machine(), "rows": rows}, render_table(rows))


def render_table(rows: list[dict]) -> str:
    flat = []
    for r in rows:
        f = {"label": r["label"], "scene": r["scene"], "model": r["model"], "steps": r["steps"],
             "step_ms": r["step_ms"]}
        f.update({k: r["phase_ms"].get(k, 0.0) for k in PHASES})
        f["rest"] = r["rest_ms"]
        f["ns/pair"] = r["ns_per_pair"]
        flat.append(f)
    cols = ["label", "scene", "model", "steps", "step_ms", *PHASES, "rest", "ns/pair"]
    return ("Per-step wall time (ms) by phase, averaged over the run's steps (rest: Lightning, loss, Python).\n\n"
            + table(flat, cols))


if __name__ == "__main__":
    main()
