"""Training schedules side by side: ``schedule=constant`` against ``schedule=dash`` (or any other
schedule overrides), paired over scenes and seeds, at the quick protocol (256 px, 3000 steps), on one machine.

    python -m bench.schedule                                   # 7 scenes x seeds 0 1 2, both schedules, 2 jobs
    python -m bench.schedule --scenes fox fern --seeds 0 --variant dash_nolr="schedule=dash schedule.delay_lr_decay=false"
    python -m bench.schedule --models niw dpmm --seeds 0        # the posterior models under both schedules

Every (scene, seed) runs its variants back to back in one queue served by ``--jobs`` workers (one thread each), so
the variants of a scene-seed share the machine's conditions (interleaved, never one schedule first and the other
hours later). A finished run dir is reused and its small files are archived to ``--archive`` (committed), so the
grid resumes across sessions. Output: ``bench/results/schedule.json`` and ``schedule.md`` (per-run rows, paired
differences over scenes with bootstrap CIs and exact sign-flip p, the time ratio, time to 95 % of the reference's
final PSNR gain along the curves) and ``schedule.png`` (PSNR against training time per scene).

Rows trained elsewhere join a table with ``--import NAME=PATTERN`` (``{scene}``, ``{model}``, ``{seed}`` in the run-dir
pattern): they pair on the deterministic metrics (PSNR, SSIM, LPIPS, #Gaussians, block share); time pairs only rows
of one source (this table's runs, or one archive, whose rows ran side by side). A name imported twice reads the first
pattern with a run dir. ``--base-model`` adds model − base tables per variant, e.g. the posterior
models under dash against the standard model's dash rows of the grid, and against their archived constant runs:

    python -m bench.schedule --table-only --models standard niw dpmm --seeds 0 --variant dash=schedule=dash \\
        --out /tmp/m --archive bench/results/schedule_models_runs --name schedule_models --base-model standard \\
        --import "dash=bench/results/schedule_runs/{scene}/{model}/dash/s{seed}" \\
        --import "constant=bench/results/schedule_runs/{scene}/{model}/constant/s{seed}" \\
        --import "constant=bench/results/runs/{scene}/{model}/s{seed}" --reference constant
"""
from __future__ import annotations

import argparse
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Optional

import numpy as np

from bench.common import (QUICK, RESULTS, SEVEN, machine, model_overrides, pyplot, read_json, restore, scene_overrides,
                          sync_results, train_run, write_results)

#: load.json: the --jobs/--threads a row was trained under (its time is paired only with rows of the same scene-seed)
ARCHIVED = ["*/*/*/s*/config.yaml", "*/*/*/s*/metrics.json", "*/*/*/s*/curve.json", "*/*/*/s*/load.json"]
METRICS = [("psnr", True), ("ssim", True), ("lpips", False), ("num_gaussians", False), ("train_time_s", False)]


def parse_variants(items: list[str]) -> dict[str, list[str]]:
    """``name=overrides`` strings -> {name: [override, ...]}; the first variant is the reference."""
    out: dict[str, list[str]] = {}
    for it in items:
        if "=" not in it:
            raise SystemExit(f"bench/schedule.py: --variant {it!r} is not NAME=OVERRIDES (fix: e.g. dash=schedule=dash)")
        name, over = it.split("=", 1)
        out[name] = over.split()
    return out


def time_to_target(points: list[dict], target: float) -> Optional[float]:
    """Training seconds at which a curve first reaches ``target`` PSNR (linear between logged points); None if never."""
    prev = None
    for p in points:
        if p["psnr"] >= target:
            if prev is None or p["psnr"] == prev["psnr"]:
                return float(p["train_time_s"])
            w = (target - prev["psnr"]) / (p["psnr"] - prev["psnr"])
            return float(prev["train_time_s"] + w * (p["train_time_s"] - prev["train_time_s"]))
        prev = p
    return None


#: metrics that depend on the machine's load: paired only between rows of the same source (one table's interleaved runs)
TIMED = ("train_time_s", "t95_ref")


def parse_imports(items: list[str]) -> dict[str, list[str]]:
    """``NAME=PATTERN`` strings -> {name: [run-dir pattern with {scene}, {model}, {seed}, ...]}; a name given twice
    reads the first pattern whose run dir exists (e.g. the grid's standard rows, else the canonical archive's)."""
    out: dict[str, list[str]] = {}
    for it in items:
        name, _, pattern = it.partition("=")
        if not name or "{scene}" not in pattern or "{seed}" not in pattern:
            raise SystemExit(f"bench/schedule.py: --import {it!r} is not NAME=PATTERN with {{scene}} and {{seed}} "
                             "(fix: e.g. constant=bench/results/runs/{scene}/{model}/s{seed})")
        out.setdefault(name, []).append(pattern)
    return out


def import_source(pattern: str) -> str:
    """The archive an imported row comes from (the pattern's fixed prefix): rows of one archive were trained side
    by side, so their times pair."""
    return pattern.split("{", 1)[0]


def read_row(d: Path, scene: str, model: str, variant: str, seed: int, source: str) -> Optional[tuple[dict, list]]:
    """One finished run dir as a table row and its test curve; None if it has no metrics.json."""
    if not (d / "metrics.json").is_file():
        return None
    m, load = read_json(d / "metrics.json"), read_json(d / "load.json", {})
    pts, bt = read_json(d / "curve.json", {}).get("points", []), m.get("block_time_s") or {}
    return ({"scene": scene, "model": model, "variant": variant, "seed": seed, "source": source, "psnr": m["psnr"],
             "jobs": load.get("jobs"), "ssim": m["ssim"], "lpips": m["lpips"], "num_gaussians": m["num_gaussians"],
             "train_time_s": m["train_time_s"],
             "block_pct": round(100 * sum(bt.values()) / m["train_time_s"], 2) if bt else 0.0}, pts)


def paired(rows: list[dict], a: str, b: str, key: str, higher: bool, model: str, model_b: Optional[str] = None) -> dict:
    """Scene-level paired difference a − b of ``key`` (each scene's seed mean over seeds both have); side b is
    (variant b, ``model_b`` or ``model``). Timed keys pair only rows of the same source."""
    from b3dgs.report.stats import paired_stats

    model_b = model_b or model
    per_scene = {}
    for scene in sorted({r["scene"] for r in rows}):
        va = {r["seed"]: r for r in rows if r["scene"] == scene and r["variant"] == a and r["model"] == model}
        vb = {r["seed"]: r for r in rows if r["scene"] == scene and r["variant"] == b and r["model"] == model_b}
        d = [va[s][key] - vb[s][key] for s in sorted(va.keys() & vb.keys())
             if va[s].get(key) is not None and vb[s].get(key) is not None
             and (key not in TIMED or va[s].get("source") == vb[s].get("source"))]
        if d:
            per_scene[scene] = float(np.mean(d))
    st = paired_stats(list(per_scene.values()), higher_is_better=higher)
    return {"a": a, "b": b, "model": model, "model_b": model_b, "metric": key, "per_scene": per_scene, **st}


def macro(rows: list[dict], variant: str, key: str, model: str) -> Optional[float]:
    """Macro mean over scenes of the seed means of ``key``."""
    per = {}
    for r in rows:
        if r["variant"] == variant and r["model"] == model and r.get(key) is not None:
            per.setdefault(r["scene"], []).append(r[key])
    return float(np.mean([np.mean(v) for v in per.values()])) if per else None


def plot(curves: dict, path: Path) -> None:
    from b3dgs.io import save_figure

    plt = pyplot()
    scenes = sorted({k[0] for k in curves})
    n = len(scenes)
    cols = min(4, n)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 2.8 * rows), dpi=100, squeeze=False)
    colors = {}
    for i, scene in enumerate(scenes):
        ax = axes[i // cols][i % cols]
        for (sc, model, variant, seed), pts in sorted(curves.items()):
            if sc != scene:
                continue
            c = colors.setdefault((model, variant), f"C{len(colors)}")
            ax.plot([p["train_time_s"] for p in pts], [p["psnr"] for p in pts], "-", color=c, lw=1, alpha=0.8,
                    label=f"{model} {variant}" if seed == min(k[3] for k in curves if k[:3] == (sc, model, variant)) else None)
        ax.set_title(scene, fontsize=9)
        ax.set_xlabel("training time (s)", fontsize=8)
        ax.set_ylabel("test PSNR (dB)", fontsize=8)
        ax.tick_params(labelsize=7)
    for j in range(n, rows * cols):
        axes[j // cols][j % cols].axis("off")
    axes[0][0].legend(fontsize=7)
    fig.suptitle("Test PSNR against training time (one line per seed)", fontsize=10)
    fig.tight_layout()
    save_figure(fig, path)


def load_text(rows: list[dict]) -> str:
    """How many concurrent jobs the rows ran under, from their load.json (rows from before it was kept: not recorded)."""
    from collections import Counter

    c = Counter(r.get("jobs") for r in rows)
    parts = [f"{n} rows at {j} concurrent job(s)" for j, n in sorted((j, n) for j, n in c.items() if j is not None)]
    if c.get(None):
        parts.append(f"{c[None]} rows with the load not recorded")
    return "; ".join(parts) or "no rows"


def summarize(rows: list[dict], curves: dict, names: list[str], ref: str, models: list[str],
              base_model: Optional[str] = None) -> list[dict]:
    """Variant − reference tables per model (time ratios from rows of one source only), then, with ``base_model``,
    model − base tables per variant. Adds each row's time to 95 % of the reference's final PSNR gain (``t95_ref``)."""
    for r in rows:
        refpts = curves.get((r["scene"], r["model"], ref, r["seed"]))
        pts = curves.get((r["scene"], r["model"], r["variant"], r["seed"]))
        if refpts and pts:
            target = refpts[0]["psnr"] + 0.95 * (refpts[-1]["psnr"] - refpts[0]["psnr"])
            r["t95_ref"] = time_to_target(pts, target)
    metrics = METRICS + [("block_pct", False)]

    summary = []
    for model in models:
        for name in names:
            if name == ref or not any(r["model"] == model and r["variant"] == name for r in rows):
                continue
            # time ratios only from rows of one source
            timed = len({r.get("source") for r in rows if r["model"] == model and r["variant"] in (name, ref)}) == 1
            t_ref, t95_ref = macro(rows, ref, "train_time_s", model), macro(rows, ref, "t95_ref", model)
            t, t95 = macro(rows, name, "train_time_s", model), macro(rows, name, "t95_ref", model)
            summary.append({
                "model": model, "variant": name, "reference": ref,
                "time_ratio": (t / t_ref) if timed and t and t_ref else None,
                "t95_ratio": (t95 / t95_ref) if timed and t95 and t95_ref else None,
                "paired": {k: paired(rows, name, ref, k, hi, model) for k, hi in metrics},
            })
    if base_model:
        for name in names:
            for model in models:
                if model == base_model or not any(r["model"] == model and r["variant"] == name for r in rows):
                    continue
                summary.append({"model": model, "base_model": base_model, "variant": name, "reference": name,
                                "time_ratio": None, "t95_ratio": None,
                                "paired": {k: paired(rows, name, name, k, hi, model, base_model) for k, hi in metrics}})
    return summary


def markdown(rows: list[dict], summary: list[dict], names: list[str], ref: str, threads: int,
             imports: dict[str, list[str]], title: str = "Training schedules side by side") -> list[str]:
    lines = [f"# {title} ({', '.join(names)}; reference: {ref})", "",
             f"Quick protocol (256 px, 3000 steps), {load_text(rows)}, {threads} thread(s) per run, variants "
             "of a scene-seed interleaved. Paired differences (variant − reference): each scene's seed mean is one unit; "
             "bootstrap CI (BCa with >= 6 scenes) and exact sign-flip p.", ""]
    if imports:
        lines += ["Imported rows (trained elsewhere: they pair on PSNR, SSIM, LPIPS, #Gaussians and block share; on "
                  "time only with rows of the same archive): " + "; ".join(f"`{n}` from " + ", else ".join(f"`{p}`" for p in ps) for n, ps in imports.items()), ""]
    for s in summary:
        title = (f"## {s['variant']}: {s['model']} − {s['base_model']}" if s.get("base_model")
                 else f"## {s['model']}: {s['variant']} − {s['reference']}")
        lines += [title, ""]
        if not s.get("base_model"):
            lines += [f"- training time ratio (macro mean over scenes of seed means): **{s['time_ratio']:.3f}**"
                      if s["time_ratio"] else "- training time ratio: n/a (no rows of one source)",
                      f"- time to 95 % of the reference's final PSNR gain, ratio: **{s['t95_ratio']:.3f}**"
                      if s["t95_ratio"] else "- time-to-target ratio: n/a", ""]
        lines += ["| metric | mean Δ | 95 % CI | p (two-sided) | better / worse | scenes |", "|---|---|---|---|---|---|"]
        for k, p in s["paired"].items():
            if p["mean"] is None:
                continue
            ci = p["ci"]
            cis = f"[{ci['low']:+.4g}, {ci['high']:+.4g}]" if ci.get("low") is not None else "—"
            pp = "—" if p["p_two_sided"] is None else f"{p['p_two_sided']:.3g}"
            lines.append(f"| {k} | {p['mean']:+.4g} | {cis} | {pp} | {p['wins']} / {p['losses']} | {p['n']} |")
        lines.append("")
    lines += ["## Runs", "", "| scene | model | variant | seed | PSNR | SSIM | LPIPS | #Gaussians | train s | t95 s | block % |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: (r["model"], r["scene"], r["seed"], r["variant"])):
        t95 = "—" if r.get("t95_ref") is None else f"{r['t95_ref']:.1f}"
        lp = "—" if r["lpips"] is None else f"{r['lpips']:.4f}"
        lines.append(f"| {r['scene']} | {r['model']} | {r['variant']} | {r['seed']} | {r['psnr']:.3f} | {r['ssim']:.4f} | "
                     f"{lp} | {r['num_gaussians']} | {r['train_time_s']:.1f} | {t95} | {r['block_pct']} |")
    return lines


def main(argv: Optional[list[str]] = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=SEVEN)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--models", nargs="+", default=["standard"])
    ap.add_argument("--variant", action="append", default=None,
                    help="NAME=OVERRIDES (repeatable; the first is the reference; default constant and dash)")
    ap.add_argument("--import", dest="imports", action="append", default=[],
                    help="NAME=PATTERN: rows trained elsewhere, run dirs with {scene}, {model}, {seed} (repeatable)")
    ap.add_argument("--reference", default=None, help="the variant the others are paired against (default: the first)")
    ap.add_argument("--base-model", default=None, help="also pair every model against this one, per variant")
    ap.add_argument("--table-only", action="store_true", help="train nothing; tables of the finished rows")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="outputs/bench_schedule")
    ap.add_argument("--archive", default=str(RESULTS / "schedule_runs"))
    ap.add_argument("--name", default="schedule", help="result files bench/results/<name>.{json,md,png}")
    ap.add_argument("--results-root", default=str(RESULTS), help="where <name>.{json,md,png} go (default bench/results)")
    ap.add_argument("--extra", nargs="*", default=[], help="overrides for every run")
    ap.add_argument("--title", default="Training schedules side by side", help="the table's heading")
    args = ap.parse_args(argv)
    from b3dgs.io import write_json

    variants = parse_variants(args.variant or ["constant=schedule=constant", "dash=schedule=dash"])
    imports = parse_imports(args.imports)
    names = list(variants) + [n for n in imports if n not in variants]
    ref = args.reference or next(iter(variants))
    if ref not in names:
        raise SystemExit(f"bench/schedule.py: --reference {ref!r} is neither a --variant nor an --import "
                         f"(fix: one of {', '.join(names)})")
    if args.base_model and args.base_model not in args.models:
        raise SystemExit(f"bench/schedule.py: --base-model {args.base_model!r} is not in --models (fix: add it)")
    out, archive = Path(args.out), Path(args.archive)
    restore(archive, out, ARCHIVED)
    jobs = [(scene, model, name, seed) for seed in args.seeds for scene in args.scenes for model in args.models
            for name in variants]

    def run(job):
        scene, model, name, seed = job
        run_dir = out / scene / model / name / f"s{seed}"
        over = scene_overrides(scene) + QUICK + [*model_overrides(model), f"seed={seed}", f"threads={args.threads}",
                                                 *variants[name], *args.extra]
        try:
            fresh = not (run_dir / "metrics.json").is_file()
            m = train_run(run_dir, over, timeout_s=4 * 3600)
        except Exception as e:  # noqa: BLE001 - one failed run must not stop the grid; it is reported
            print(f"FAILED {job}: {str(e)[-400:]}", flush=True)
            return None
        if fresh:
            write_json(run_dir / "load.json", {"jobs": args.jobs, "threads": args.threads})
        sync_results(out, archive, ARCHIVED)
        print(f"{scene} {model} {name} s{seed}: PSNR {m['psnr']:.3f}, {m['num_gaussians']} Gaussians, "
              f"{m['train_time_s']:.1f} s", flush=True)
        return job

    if not args.table_only:
        with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as ex:
            list(ex.map(run, jobs))

    rows, curves = [], {}
    for seed in args.seeds:
        for scene in args.scenes:
            for model in args.models:
                for name in names:  # a row of this table's own runs wins over an imported one
                    got = (read_row(out / scene / model / name / f"s{seed}", scene, model, name, seed, "run")
                           if name in variants else None)
                    for pattern in imports.get(name, []) if got is None else []:
                        d = Path(pattern.format(scene=scene, model=model, seed=seed))
                        if (got := read_row(d, scene, model, name, seed, import_source(pattern))) is not None:
                            break
                    if got is not None:
                        rows.append(got[0])
                        curves[(scene, model, name, seed)] = got[1]
    summary = summarize(rows, curves, names, ref, args.models, args.base_model)
    lines = markdown(rows, summary, names, ref, args.threads, imports, args.title)
    root = Path(args.results_root)
    write_results(args.name, {"machine": machine(), "variants": variants, "imports": imports, "reference": ref,
                              "jobs": args.jobs, "threads": args.threads, "rows": rows, "summary": summary},
                  "\n".join(lines), root, echo=False)
    if curves:
        plot(curves, root / f"{args.name}.png")
    print("\n".join(lines[:40]))
    print(f"wrote {root / (args.name + '.md')}")


if __name__ == "__main__":
    main()
