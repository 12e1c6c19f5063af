"""Old against new code, side by side: quick-protocol training time and the renderer's fwd+bwd, one invocation.

    git worktree add --detach ../b3dgs-base <commit before the change>
    python -m bench.speed_ab --base ../b3dgs-base [--scenes ethiopian_head fox] [--rounds 3] [--threads 1]

Round r trains seed r of every scene with both checkouts at the same time, one process each with
``threads=1`` (one core each: the machine's conditions hit both alike, and the campaigns run this way,
``--jobs 2 --threads 1``). The render benchmark then times 100k random Gaussians at 256x256 (fwd and fwd+bwd,
``renderer=cpu``, both threads) alternating the checkouts for ``--render-rounds`` rounds. Medians and new/old ratios;
the PSNR of every run pair shows whether the change kept results bit for bit. Writes
bench/results/speed_ab.json and .md; finished training runs are reused (resumable), ``--force`` redoes them.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from bench.common import QUICK, machine, plain_overrides, scene_overrides, table, write_results

ROOT = Path(__file__).resolve().parents[1]

# Child for the render timing: bench/render.py's random scene and camera (they use only b3dgs.types.Camera, which
# both checkouts have) rendered with the checkout on PYTHONPATH; prints one JSON line.
RENDER_CHILD = r'''
import importlib.util, json, statistics, sys, time, torch
spec = importlib.util.spec_from_file_location("bench_render", sys.argv[3])  # this checkout's bench/render.py
render = importlib.util.module_from_spec(spec)
spec.loader.exec_module(render)
camera, random_gaussians = render.camera, render.random_gaussians
from b3dgs.render.renderers import make_renderer
n, reps = int(sys.argv[1]), int(sys.argv[2])
p = {k: v.clone().requires_grad_(True) for k, v in random_gaussians(n).items()}
cam, r = camera(), make_renderer("cpu")
def fwd():
    with torch.no_grad():
        return r.render(p, cam, sh_degree=3)
def fwdbwd():
    out = r.render(p, cam, sh_degree=3, retain_means2d_grad=True)
    out.rgb.sum().backward()
def med(fn):
    fn()
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter(); fn(); ts.append(time.perf_counter() - t0)
    return 1000 * statistics.median(ts)
out = {"fwd_ms": med(fwd), "fwdbwd_ms": med(fwdbwd), "pairs": int(fwd().bins.num_pairs)}
print("RENDER " + json.dumps(out), flush=True)
'''


def train_pair(base: Path, new: Path, out: Path, scene: str, seed: int, threads: int, force: bool) -> dict:
    """Both checkouts train ``scene`` seed ``seed`` at the same time; returns {label: metrics}."""
    procs, dirs = {}, {}
    for label, code in (("old", base), ("new", new)):
        run_dir = out / label / scene / f"s{seed}"
        dirs[label] = run_dir
        if (run_dir / "metrics.json").exists() and not force:
            continue
        cmd = [sys.executable, "-m", "b3dgs.train", *plain_overrides([*scene_overrides(scene), *QUICK]), "model=standard",
               "renderer=cpu", f"seed={seed}", f"threads={threads}", f"hydra.run.dir={run_dir}",
               "overwrite=true" if force else "resume=auto"]
        procs[label] = subprocess.Popen(cmd, env=dict(os.environ, PYTHONPATH=str(code)), cwd=str(code),
                                        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    for label, proc in procs.items():
        _, err = proc.communicate()
        if proc.returncode != 0:
            raise RuntimeError(f"{label} {scene} s{seed} failed:\n{err[-3000:]}")
    return {label: json.loads((d / "metrics.json").read_text()) for label, d in dirs.items()}


def render_once(code: Path, n: int, reps: int) -> dict:
    res = subprocess.run([sys.executable, "-c", RENDER_CHILD, str(n), str(reps),
                          str(Path(__file__).resolve().parent / "render.py")],
                         capture_output=True, text=True,
                         env=dict(os.environ, PYTHONPATH=str(code)), cwd=str(code))
    line = [ln for ln in res.stdout.splitlines() if ln.startswith("RENDER ")]
    if res.returncode != 0 or not line:
        raise RuntimeError(f"render timing with {code} failed:\n{res.stderr[-3000:]}")
    return json.loads(line[-1][len("RENDER "):])


def ratio(a: float, b: float) -> float:
    return round(a / b, 3) if b else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", type=Path, required=True, help="checkout of the old code (a git worktree)")
    ap.add_argument("--new", type=Path, default=ROOT, help="checkout of the new code (default: this one)")
    ap.add_argument("--scenes", nargs="+", default=["ethiopian_head", "fox"])
    ap.add_argument("--rounds", type=int, default=3, help="training rounds (seeds 0 .. rounds - 1)")
    ap.add_argument("--render-rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("outputs/speed_ab"))
    ap.add_argument("--render-n", type=int, default=100_000)
    ap.add_argument("--skip-train", action="store_true")
    ap.add_argument("--force", action="store_true")
    args = ap.parse_args()
    base, new, out = args.base.resolve(), args.new.resolve(), args.out.resolve()
    for code in (base, new):
        if not (code / "b3dgs" / "train.py").exists():
            sys.exit(f"speed_ab: {code} is not a b3dgs checkout (fix: pass --base/--new a checkout's root)")
    runs = []
    if not args.skip_train:
        for seed in range(args.rounds):
            for scene in args.scenes:
                pair = train_pair(base, new, out, scene, seed, args.threads, args.force)
                for label, m in pair.items():
                    runs.append({"scene": scene, "seed": seed, "code": label, "train_time_s": m["train_time_s"],
                                 "psnr": m["psnr"], "num_gaussians": m["num_gaussians"]})
                print(json.dumps(runs[-2:]), flush=True)
    renders = []
    for rnd in range(args.render_rounds):
        for label, code in (("old", base), ("new", new)):
            r = render_once(code, args.render_n, reps=5)
            r.update(code=label, round=rnd)
            r["ns_per_pair"] = 1e6 * r["fwdbwd_ms"] / max(r["pairs"] * 256, 1)
            renders.append(r)
            print(json.dumps(r), flush=True)

    summary = []
    for scene in args.scenes:
        rs = [r for r in runs if r["scene"] == scene]
        if not rs:
            continue
        t = {c: statistics.median(r["train_time_s"] for r in rs if r["code"] == c) for c in ("old", "new")}
        p = {c: statistics.mean(r["psnr"] for r in rs if r["code"] == c) for c in ("old", "new")}
        same = all(a["psnr"] == b["psnr"] and a["num_gaussians"] == b["num_gaussians"]
                   for a in rs if a["code"] == "old" for b in rs if b["code"] == "new" and b["seed"] == a["seed"])
        summary.append({"what": f"train {scene} (median of {len(rs) // 2} seeds, threads={args.threads})",
                        "old": round(t["old"], 1), "new": round(t["new"], 1), "new/old": ratio(t["new"], t["old"]),
                        "psnr_old": round(p["old"], 3), "psnr_new": round(p["new"], 3), "identical_runs": same})
    for key in ("fwd_ms", "fwdbwd_ms", "ns_per_pair"):
        m = {c: statistics.median(r[key] for r in renders if r["code"] == c) for c in ("old", "new")}
        summary.append({"what": f"render {args.render_n // 1000}k 256px {key} (median of {args.render_rounds})",
                        "old": round(m["old"], 3), "new": round(m["new"], 3), "new/old": ratio(m["new"], m["old"])})
    text = ("Old and new code side by side (bench/speed_ab.py); trainings of a seed ran at the same time, one core "
            "each.\n\n" + table(summary, ["what", "old", "new", "new/old", "psnr_old", "psnr_new", "identical_runs"])
            + ("\n\nRuns:\n\n" + table(runs, ["scene", "seed", "code", "train_time_s", "psnr", "num_gaussians"])
               if runs else ""))
    write_results("speed_ab", {"machine": machine(), "base": str(base), "new": str(new), "runs": runs,
                               "renders": renders, "summary": summary}, text)


if __name__ == "__main__":
    main()
