"""Builds of the C++ extension side by side: the default build against one set by environment variables.

    python -m bench.build_ab [--env B3DGS_FMA=1] [--checkpoint RUN_DIR/checkpoints/last.ckpt] [--rounds 5]

Each round renders, in one fresh process per build, 100k random Gaussians at 256x256 (bench/render.py's scene) and
the first test view of ``--checkpoint`` forward and forward+backward (``renderer=cpu``, one thread), the builds
alternating so that machine noise hits both alike. Times are the process's CPU time (``time.thread_time``): a job
beside the benchmark at lower priority changes them far less than wall time. Also reports the largest difference of
the render and of every gradient between the builds (0 = bitwise the same). Writes bench/results/<name>.{json,md};
finished rounds are kept and the run resumes.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from bench.common import RESULTS, machine, table, write_results

ROOT = Path(__file__).resolve().parents[1]

# One build's timings and outputs; prints one JSON line, saves the tensors to argv[2] for the comparison.
CHILD = r'''
import json, statistics, sys, time
import torch
torch.set_num_threads(1)
from bench.render import camera, random_gaussians  # PYTHONPATH is this checkout (run_child)
from b3dgs.render.renderers import make_renderer
r = make_renderer("cpu")
cases = {"random 100k": (random_gaussians(100_000), camera(), 3)}
if sys.argv[3]:
    from pathlib import Path
    from b3dgs.runs import load_run
    run = load_run(Path(sys.argv[3]).parent.parent, checkpoint=sys.argv[3])
    cases["trained " + run.scene.name] = ({k: v.detach() for k, v in run.module.params().items()}, run.scene.test[0],
                                           run.module.active_sh_degree())
res, saved = {}, {}
for name, (params, cam, sh) in cases.items():
    p = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    fw, fb = [], []
    for i in range(6):  # the first of each is a warm-up
        t = time.thread_time()
        with torch.no_grad():
            r.render(p, cam, sh_degree=sh)
        fw.append(time.thread_time() - t)
        for v in p.values():
            v.grad = None
        t = time.thread_time()
        out = r.render(p, cam, sh_degree=sh, retain_means2d_grad=True)
        out.rgb.sum().backward()
        fb.append(time.thread_time() - t)
    res[name] = {"fwd_ms": 1e3 * statistics.median(fw[1:]), "fwdbwd_ms": 1e3 * statistics.median(fb[1:])}
    saved[name] = {"rgb": out.rgb.detach(), **{k: v.grad for k, v in p.items()}}
torch.save(saved, sys.argv[2])
print(json.dumps(res))
'''


def run_child(env_extra: dict, ckpt: str, tensors: Path) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    for k in list(env):
        if k.startswith("B3DGS_") and k not in ("B3DGS_SHARED", "B3DGS_CACHE"):
            del env[k]  # the default build is the one without any build switch
    env.update(env_extra)
    out = subprocess.run([sys.executable, "-c", CHILD, str(ROOT), str(tensors), ckpt or ""], env=env,
                         capture_output=True, text=True, cwd=ROOT)
    if out.returncode != 0:
        raise SystemExit(f"bench/build_ab.py: the child with {env_extra or 'the default build'} failed:\n"
                         f"{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", nargs="+", default=["B3DGS_FMA=1"], help="the other build's switches, NAME=VALUE")
    ap.add_argument("--checkpoint", default=None)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--name", default="fma")
    args = ap.parse_args()
    import torch

    from b3dgs.io import write_json

    other = dict(kv.split("=", 1) for kv in args.env)
    path = RESULTS / f"{args.name}.json"
    prev = json.loads(path.read_text()) if path.exists() else {}
    same = prev.get("env") == other and prev.get("checkpoint") == args.checkpoint
    rounds = prev.get("rounds", []) if same else []
    tmp = ROOT / "outputs" / "build_ab"
    tmp.mkdir(parents=True, exist_ok=True)
    diffs = prev.get("max_abs_diff", {}) if same else {}
    for i in range(len(rounds), args.rounds):
        rnd = {}
        for label, env in (("default", {}), ("other", other)) if i % 2 == 0 else (("other", other), ("default", {})):
            rnd[label] = run_child(env, args.checkpoint, tmp / f"{label}.pt")
            print(f"round {i + 1}/{args.rounds} {label}: {json.dumps(rnd[label])}", flush=True)
        rounds.append(rnd)
        a, b = torch.load(tmp / "default.pt"), torch.load(tmp / "other.pt")
        diffs = {case: {k: float((a[case][k] - b[case][k]).abs().max()) for k in a[case]} for case in a}
        write_json(path, {"machine": machine(), "env": other, "checkpoint": args.checkpoint, "rounds": rounds,
                          "max_abs_diff": diffs})  # each finished round is kept
    rows = []
    for case in rounds[0]["default"]:
        for what in ("fwd_ms", "fwdbwd_ms"):
            old = statistics.median(r["default"][case][what] for r in rounds)
            new = statistics.median(r["other"][case][what] for r in rounds)
            rows.append({"case": case, "what": what, "default": round(old, 2), "other": round(new, 2),
                         "other/default": round(new / old, 3),
                         "max_abs_diff": max(diffs.get(case, {}).values(), default=None)})
    env_txt = " ".join(f"{k}={v}" for k, v in other.items())
    text = (f"Default extension build against `{env_txt}` (bench/build_ab.py): one thread, CPU time, medians of "
            f"{len(rounds)} interleaved rounds; max_abs_diff: the largest difference of the render and its gradients "
            f"between the builds.\n\n" + table(rows, ["case", "what", "default", "other", "other/default",
                                                       "max_abs_diff"]))
    write_results(args.name, {"machine": machine(), "env": other, "checkpoint": args.checkpoint, "rounds": rounds,
                              "max_abs_diff": diffs, "summary": rows}, text)


if __name__ == "__main__":
    main()
