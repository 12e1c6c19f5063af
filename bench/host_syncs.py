"""Host syncs per training step, by scope (core, render, each posterior block, strategy, loop) and kind of step.

    python -m bench.host_syncs [--scene fox] [--steps 600] [--models standard niw dpmm niw_sh]
    python -m bench.host_syncs --device cuda            # on a GPU: renderer=gsplat, CUDA's own sync count

Each model trains ``--steps`` steps of the quick protocol (``experiment=study`` with ``trainer.max_steps`` = steps, so
the staged blocks, densification and the posterior refreshes all happen) with :class:`b3dgs.host_sync.HostSyncCallback`,
which counts every operation that waits for the device (CPU: at torch's dispatch hooks; CUDA:
``torch.cuda.set_sync_debug_mode``). Steps are grouped by the periodic work the plugins declare for them
(:meth:`b3dgs.plugin.Plugin.periodic`): ``ordinary`` steps declare none. Writes bench/results/host_syncs.{json,md}
(``host_syncs_cuda`` on a GPU); resumable: a model whose count exists is not trained again.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from bench.common import RESULTS, machine, model_overrides, scene_overrides, table, write_results

from b3dgs.host_sync import summarise

MODELS = {"standard": model_overrides("standard"), "niw": model_overrides("niw"), "dpmm": model_overrides("dpmm"),
          "niw_sh": ["model=niw", "posterior=[niw,sh]"]}
SCOPE_ORDER = ("core", "render", "niw", "dp", "noise", "opacity", "color", "sh", "strategy", "loop")


def count(model: str, scene: str, steps: int, device: str, out: Path, seed: int = 0, path: str = "device") -> dict:
    """Train ``model`` with the counter (unless ``out`` exists) and return its JSON."""
    if out.exists():
        return json.loads(out.read_text())
    run_dir = out.parent / f"run_{out.stem}"
    renderer = {"cpu": "cpu", "cuda": "gsplat"}[device]
    # no progress bar: its metric reads are host syncs of their own (experiment=study shows it since issue 44)
    cmd = [sys.executable, "-m", "b3dgs.train", *scene_overrides(scene), "experiment=study", *MODELS[model],
           "trainer.enable_progress_bar=false", f"trainer.max_steps={steps}", f"seed={seed}", f"renderer={renderer}", f"trainer.eval_every={steps}",
           "+callbacks.host_sync._target_=b3dgs.host_sync.HostSyncCallback", f"+callbacks.host_sync.out={out}",
           f"+callbacks.host_sync.device_path={path == 'device'}", f"hydra.run.dir={run_dir}", "overwrite=true"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0 or not out.exists():
        raise SystemExit(f"host_syncs: {model} failed (rc {proc.returncode}):\n{proc.stderr[-3000:]}")
    return json.loads(out.read_text())


def rows_of(model: str, result: dict, path: str) -> list[dict]:
    rows = []
    for kind, r in summarise(result).items():
        scopes = {s: round(v, 3) for s, v in r.items() if s != "steps"}
        rows.append({"model": model, "path": path, "step": kind, "steps": r["steps"], "total": round(sum(scopes.values()), 3),
                     **scopes})
    order = {"ordinary": 0}
    return sorted(rows, key=lambda r: (order.get(r["step"], 1), r["step"]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="fox")
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--models", nargs="+", default=list(MODELS), choices=list(MODELS))
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    ap.add_argument("--paths", nargs="+", default=["device", "host"], choices=["device", "host"],
                    help="device: the blocks' device path (what a GPU pays; forced on CPU tensors); host: the CPU build's "
                         "own path, which reads values on the host (its bits)")
    ap.add_argument("--out", default="outputs/bench/host_syncs")
    ap.add_argument("--results", default=str(RESULTS))
    args = ap.parse_args()
    suffix = "" if args.device == "cpu" else f"_{args.device}"
    root = Path(args.out)
    root.mkdir(parents=True, exist_ok=True)
    results, rows = {}, []
    paths = args.paths if args.device == "cpu" else ["device"]
    for path in paths:
        for model in args.models:
            name = f"{args.scene}_{model}{suffix}" + ("" if path == "device" else "_host")
            res = count(model, args.scene, args.steps, args.device, root / f"{name}.json", path=path)
            results[(model, path)] = res
            rows += rows_of(model, res, path)
            print(rows_of(model, res, path)[0], flush=True)
    scopes = [s for s in SCOPE_ORDER if any(s in r for r in rows)]
    scopes += sorted({k for r in rows for k in r} - set(scopes) - {"model", "path", "step", "steps", "total"})
    cols = ["model", "path", "step", "steps", "total", *scopes]
    # where the remaining syncs of ordinary steps come from (file:line, kind), per scope, over all models
    sites: dict[str, dict[str, int]] = {}
    for (model, path), res in results.items():
        if path != "device":
            continue
        for sc, hits in res.get("sites", {}).items():
            for site, n in hits.items():
                sites.setdefault(sc, {})
                sites[sc][site] = sites[sc].get(site, 0) + n
    text = [f"# Host syncs per training step ({args.device}, {args.scene}, {args.steps} steps of the quick protocol)", "",
            f"Command: `python -m bench.host_syncs --device {args.device} --scene {args.scene} --steps {args.steps}`. "
            "Mean syncs per step, by scope; a step's kind is the periodic work the plugins declared for it "
            "(`ordinary`: none; `log`: the core's logging interval). `path=device`: the blocks' device path, what a GPU run "
            "pays (forced on CPU tensors here); `path=host`: the CPU build's own path, which reads values on the host "
            "and keeps the archived runs' bits. `render` is the CPU renderer's own reads, which the CUDA path (gsplat) "
            "does not run. Counter: " + next(iter(results.values()))["backend"] + ".", "",
            table(rows, cols), "", "## Where the device path's syncs are (all models, all steps; file:line, kind, count)", ""]
    for sc in scopes:
        if sc in sites:
            top = sorted(sites[sc].items(), key=lambda kv: -kv[1])[:12]
            text.append(f"- **{sc}**: " + "; ".join(f"`{s}` {n}" for s, n in top))
    write_results(f"host_syncs{suffix}", {"machine": machine(), "scene": args.scene, "steps": args.steps,
                                            "device": args.device, "rows": rows, "sites": sites},
                  "\n".join(text), root=Path(args.results))


if __name__ == "__main__":
    main()
