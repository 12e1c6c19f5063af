"""The GPU-parity profile (issue 43): torch.profiler's top ops of a DPMM step, and the device report.

    python -m bench.device_profile profile [--device cuda] [--steps 200] [--models standard niw dpmm]
    python -m bench.device_profile report [--card h200]                     # bench/results/device_<card>.{md,json}

``profile`` trains each model on fox with every block staged from step 0 (DPMM: ``t_dp = t_noise = t_post = 0``) and
records steps ``--at`` .. ``--at + --window`` with ``torch.profiler`` (CPU and CUDA activities): the top 15 ops by
device time and by host time, per step, to bench/results/step_profile_<device>.json (model -> profile). ``report`` joins what the device stage wrote
(train_cuda.json: wall clock and in-run block shares; host_syncs_cuda.json: CUDA's own sync count; the profile) into
one table per question: NIW and DPMM training time against standard (seed means per scene, and over scenes), the
in-run block share beside the wall-clock excess, syncs per ordinary step by scope, and the top ops.
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

import lightning as L

from bench.common import RESULTS, model_overrides, read_json, scene_overrides, table, write_results


def _ms(ev, *names: str) -> float:
    for n in names:
        v = getattr(ev, n, None)
        if v is not None:
            return float(v) / 1000.0  # profiler times are in microseconds
    return 0.0


class StepProfiler(L.Callback):
    """torch.profiler over training steps [at, at + window): the top ops by device and host time, per step, to ``out``."""

    def __init__(self, out: str, at: int = 100, window: int = 50, top: int = 15) -> None:
        super().__init__()
        self.out, self.at, self.window, self.top = out, at, window, top
        self.prof = None
        self.t0 = None

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        import time

        import torch

        step = int(pl_module.global_step)
        if step == self.at and self.prof is None:
            acts = [torch.profiler.ProfilerActivity.CPU]
            if torch.cuda.is_available() and pl_module.device.type == "cuda":
                acts.append(torch.profiler.ProfilerActivity.CUDA)
                torch.cuda.synchronize()
            self.prof = torch.profiler.profile(activities=acts)
            self.prof.__enter__()
            self.t0 = time.perf_counter()
        elif step == self.at + self.window and self.prof is not None:
            if pl_module.device.type == "cuda":
                torch.cuda.synchronize()
            wall = time.perf_counter() - self.t0
            self.prof.__exit__(None, None, None)
            self._write(self.prof, wall, pl_module)
            self.prof = None

    def _write(self, prof, wall_s: float, pl_module) -> None:
        from b3dgs.io import write_json

        evs = [e for e in prof.key_averages() if not e.key.startswith("ProfilerStep")]
        n = float(self.window)

        def row(e):
            return {"op": e.key[:60], "calls_per_step": round(e.count / n, 2),
                    "device_ms_per_step": round(_ms(e, "self_device_time_total", "self_cuda_time_total") / n, 4),
                    "host_self_ms_per_step": round(_ms(e, "self_cpu_time_total") / n, 4)}

        # each range appears twice (the host range and its device-side annotation): one row per scope
        scopes: dict[str, dict] = {}
        for e in evs:
            if e.key.startswith("b3dgs::"):
                r = scopes.setdefault(e.key[len("b3dgs::"):], {"scope": e.key[len("b3dgs::"):], "calls_per_step": 0.0,
                                                               "host_ms_per_step": 0.0, "device_ms_per_step": 0.0})
                r["calls_per_step"] = max(r["calls_per_step"], round(e.count / n, 2))
                r["host_ms_per_step"] = max(r["host_ms_per_step"], round(_ms(e, "cpu_time_total") / n, 4))
                r["device_ms_per_step"] = max(r["device_ms_per_step"],
                                              round(_ms(e, "device_time_total", "cuda_time_total") / n, 4))
        scopes = list(scopes.values())
        evs = [e for e in evs if not e.key.startswith("b3dgs::")]
        by_dev = sorted(evs, key=lambda e: -_ms(e, "self_device_time_total", "self_cuda_time_total"))[: self.top]
        by_host = sorted(evs, key=lambda e: -_ms(e, "self_cpu_time_total"))[: self.top]
        dev_total = sum(_ms(e, "self_device_time_total", "self_cuda_time_total") for e in evs) / n
        write_json(Path(self.out), {
            "steps": [self.at, self.at + self.window], "wall_ms_per_step": round(1000 * wall_s / n, 3),
            "device_busy_ms_per_step": round(dev_total, 3), "device": str(pl_module.device),
            "num_gaussians": pl_module.num_gaussians, "blocks": list(pl_module.posterior),
            "scopes": sorted(scopes, key=lambda r: -r["host_ms_per_step"]),
            "by_device_time": [row(e) for e in by_dev], "by_host_time": [row(e) for e in by_host]})


#: every block of the model active from step 0, so the profiled window holds each block's per-step work
STAGES_FROM_0 = {"standard": [], "niw": [],
                 "dpmm": ["posterior.dp.t_dp=0", "posterior.noise.t_noise=0", "posterior.opacity.t_post=0",
                          "posterior.color.t_post=0"]}


def profile(args) -> None:
    """One profiled run per model; results/step_profile_<device>.json maps model -> its profile (a model already
    there is kept: the stage resumes)."""
    from b3dgs.io import write_json

    out = Path(args.results) / f"step_profile_{args.device}.json"
    done = read_json(out, {})
    renderer = {"cpu": "cpu", "cuda": "gsplat"}[args.device]
    for model in args.models:
        if model in done:
            continue
        one = Path(args.out) / f"profile_{model}_{args.device}.json"
        run_dir = Path(args.out) / f"profile_{model}_{args.device}"
        cmd = [sys.executable, "-m", "b3dgs.train", *scene_overrides(args.scene), "experiment=study",
               "trainer.enable_progress_bar=false",  # as profiled before experiment=study showed the bar
               *model_overrides(model), f"renderer={renderer}", f"trainer.max_steps={args.steps}",
               f"trainer.eval_every={args.steps}", *STAGES_FROM_0[model],
               "+callbacks.prof._target_=bench.device_profile.StepProfiler", f"+callbacks.prof.out={one}",
               f"+callbacks.prof.at={args.at}", f"+callbacks.prof.window={args.window}",
               f"hydra.run.dir={run_dir}", "overwrite=true"]
        proc = subprocess.run(cmd, text=True)
        if proc.returncode != 0 or not one.exists():
            raise SystemExit(f"device_profile: the profiled {model} run failed (rc {proc.returncode})")
        done[model] = json.loads(one.read_text())
        write_json(out, done)
        print(model, json.dumps(done[model], indent=1)[:3000], flush=True)


def parity_ratios(rows: list[dict]) -> list[dict]:
    """NIW's and DPMM's training time against standard's of the same scene and seed: one row per scene and model
    (seed means; ``seeds``: how many pairs), then the mean over scenes against the targets (NIW <= 1.05x, DPMM
    <= 1.15x). ``rows``: runs with scene, model, seed, train_time_s, psnr and optionally block_share."""
    ratios = []
    for scene in sorted({r["scene"] for r in rows}):
        for model in ("niw", "dpmm"):
            pairs = [(r, next((b for b in rows if b["scene"] == scene and b["seed"] == r["seed"]
                               and b["model"] == "standard"), None))
                     for r in rows if r["scene"] == scene and r["model"] == model]
            pairs = [(r, b) for r, b in pairs if b is not None]
            if not pairs:
                continue
            t = statistics.mean(r["train_time_s"] for r, _ in pairs)
            tb = statistics.mean(b["train_time_s"] for _, b in pairs)
            share = statistics.mean((r.get("block_share") or 0.0) for r, _ in pairs)
            ratios.append({"scene": scene, "model": model, "seeds": len(pairs), "standard_s": round(tb, 2),
                           "model_s": round(t, 2), "x_standard": round(t / tb, 4),
                           "excess_pct": round(100 * (t / tb - 1), 2), "in_run_block_share_pct": round(100 * share, 2),
                           "psnr_model": round(statistics.mean(r["psnr"] for r, _ in pairs), 3),
                           "psnr_standard": round(statistics.mean(b["psnr"] for _, b in pairs), 3)})
    for model, limit in (("niw", 1.05), ("dpmm", 1.15)):
        rs = [r for r in ratios if r["model"] == model]
        if rs:
            x = statistics.mean(r["x_standard"] for r in rs)
            ratios.append({"scene": "mean over scenes", "model": model, "seeds": sum(r["seeds"] for r in rs),
                           "x_standard": round(x, 4), "excess_pct": round(100 * (x - 1), 2),
                           "target": f"<= {limit}", "met": x <= limit})
    return ratios


#: the parity table's columns (bench/results/device_<card>.md)
PARITY_COLUMNS = ["scene", "model", "seeds", "standard_s", "model_s", "x_standard", "excess_pct",
                  "in_run_block_share_pct", "psnr_standard", "psnr_model", "target", "met"]


def report(args) -> None:
    res = Path(args.results)
    train = read_json(res / "train_cuda.json")
    syncs = read_json(res / "host_syncs_cuda.json")
    prof = read_json(res / "step_profile_cuda.json")
    lines = [f"# GPU parity on an NVIDIA {args.card.upper()} (issue 43)", ""]
    payload: dict = {"card": args.card}
    if train:
        payload["machine"] = train.get("machine")
        m = train.get("machine") or {}
        lines += [f"Machine: {m.get('cuda_device')}, torch {m.get('torch')}, Python {m.get('python')}. "
                  "Command: `bash scripts/device_check.sh profile` (the device tool, `carry: [.device]`).", ""]
        rows = train["rows"]
        ratios = parity_ratios(rows)
        payload["ratios"] = ratios
        lines += ["## Training time against standard (quick protocol, gsplat; seed means)", "",
                  table(ratios, PARITY_COLUMNS), "",
                  "`in_run_block_share_pct`: the posterior blocks' hooks' share of the training time by the in-run "
                  "timer (host wall clock around each hook, `metrics.json` `block_time_s`); `excess_pct`: the "
                  "wall-clock excess over standard in the same run set.", "", "### Every run", "",
                  table(rows, ["scene", "model", "seed", "psnr", "num_gaussians", "train_time_s", "time_vs_standard",
                               "block_share"]), ""]
    if syncs:
        payload["host_syncs"] = syncs["rows"]
        lines += ["## Host syncs per step on the GPU (`torch.cuda.set_sync_debug_mode`, fox)", "",
                  table(syncs["rows"], ["model", "step", "steps", "total"] + sorted(
                      {k for r in syncs["rows"] for k in r} - {"model", "path", "step", "steps", "total"})), ""]
    cols = ["op", "calls_per_step", "device_ms_per_step", "host_self_ms_per_step"]
    for model, p in (prof or {}).items():
        payload.setdefault("profile", {})[model] = p
        lines += [f"## torch.profiler, {model} step (every block active; steps {p['steps'][0]}-{p['steps'][1]}, "
                  f"{p['num_gaussians']} Gaussians)", "",
                  f"Wall {p['wall_ms_per_step']} ms per step, device busy {p['device_busy_ms_per_step']} ms.", "",
                  "Host time by scope (inclusive; `b3dgs.host_sync.scope` ranges):", "",
                  table(p.get("scopes", []), ["scope", "calls_per_step", "host_ms_per_step", "device_ms_per_step"]), "",
                  "Top ops by device time:", "", table(p["by_device_time"], cols), "",
                  "Top ops by host time:", "", table(p["by_host_time"], cols), ""]
    write_results(f"device_{args.card}", payload, "\n".join(lines), root=res)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=["profile", "report"])
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cuda")
    ap.add_argument("--scene", default="fox")
    ap.add_argument("--models", nargs="+", default=["standard", "niw", "dpmm"], choices=list(STAGES_FROM_0))
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--at", type=int, default=100)
    ap.add_argument("--window", type=int, default=50)
    ap.add_argument("--card", default="gpu")
    ap.add_argument("--out", default="outputs/bench")
    ap.add_argument("--results", default=str(RESULTS))
    args = ap.parse_args()
    profile(args) if args.what == "profile" else report(args)


if __name__ == "__main__":
    main()
