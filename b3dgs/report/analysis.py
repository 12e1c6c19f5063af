"""The report's numbers, from :class:`~b3dgs.report.collect.Run` lists: canonical macro table (per-scene
seed means, then the mean over scenes, as the paper's Table 1), per-scene tables, paired analysis,
curves against training time, Pareto points and time to target."""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from b3dgs.report.collect import Run, group, method_order
from b3dgs.report.stats import mean_sem, paired_stats, pareto_front, time_to_fraction

__all__ = ["COLUMNS", "HIGHER_IS_BETTER", "scene_means", "uq_regimes", "uq_key", "macro_row", "canonical_table",
           "per_scene", "paired", "curves", "time_to_target", "pareto", "UQ_COLUMNS", "uq_table"]

UQ = "uq"  # placeholder for the configured uq.json regime (cfg.uq_regime)
# (name, label, source: None = metrics.json / UQ = uq.json regime)
COLUMNS = [("psnr", "PSNR ↑", None), ("ssim", "SSIM ↑", None), ("lpips", "LPIPS ↓", None), ("ause_rmse", "AUSE ↓", UQ),
           ("ece", "ECE ↓", UQ), ("cov95", "Cov@95", UQ), ("num_gaussians", "Gauss.", None),
           ("render_fps", "FPS ↑", None), ("train_time_s", "Time (s) ↓", None),
           ("block_time_pct", "Blocks % of time", None)]
HIGHER_IS_BETTER = {"psnr": True, "ssim": True, "lpips": False, "ause_rmse": False, "ece": False,
                    "cov95_err": False, "num_gaussians": False, "render_fps": True, "train_time_s": False,
                    "block_time_pct": False}


def scene_means(runs: Sequence[Run], name: str, regime: Optional[str] = None) -> dict[str, float]:
    """{scene: mean over seeds of ``name``} for the scenes where any run logged it."""
    out = {}
    for (scene,), rs in group(runs, "scene").items():
        m, _ = mean_sem([r.value(name, regime) for r in rs])
        if m is not None:
            out[scene] = m
    return out


def uq_regimes(runs: Sequence[Run], preferred: Optional[str]) -> list[str]:
    """The uq.json regimes of a table's AUSE / ECE / Cov@95 columns: ``preferred`` (cfg.uq_regime) where every run
    with a uq.json has it (or no run has one), else every regime the runs have, ``preferred`` first: a run
    evaluated with ``uq=[native]`` only shows its native numbers, not a dash."""
    have = [set(r.uq) for r in runs if r.uq]
    if not have or (preferred and all(preferred in h for h in have)):
        return [preferred] if preferred else []
    found = set().union(*have)
    return ([preferred] if preferred in found else []) + sorted(found - {preferred})


def uq_key(name: str, regime: str, regimes: Sequence[str]) -> str:
    """A macro row's key of uq.json value ``name`` of ``regime``: the plain name for the first regime, else
    ``name@regime``."""
    return name if not regimes or regime == regimes[0] else f"{name}@{regime}"


def macro_row(runs: Sequence[Run], uq_regime: "str | Sequence[str] | None") -> dict:
    """Macro means over scenes of per-scene seed means, every column; ``n_scenes``/``n_runs`` beside. The uq.json
    columns come from ``uq_regime`` (one regime, or several: the first under the plain names, the others under
    :func:`uq_key`'s ``name@regime``)."""
    regimes = [uq_regime] if isinstance(uq_regime, str) else list(uq_regime or [])
    row = {"n_scenes": len({r.scene for r in runs}), "n_runs": sum(1 for r in runs if r.value("psnr") is not None),
           "seeds": sorted({r.seed for r in runs})}
    for name, _, src in COLUMNS:
        if src == UQ and not regimes:
            row[name] = None
        for regime in regimes if src == UQ else [None]:
            key = uq_key(name, regime, regimes) if regime else name
            sm = scene_means(runs, name, regime)
            row[key] = float(np.mean(list(sm.values()))) if sm else None
            if sm and len(sm) < row["n_scenes"]:
                row.setdefault("partial", {})[key] = len(sm)
    if len(regimes) > 1:
        row["uq_regimes"] = regimes
    return row


#: uq.json keys of the uncertainty table (the paper's Table 3 columns plus NLL, rank correlation and cost)
UQ_COLUMNS = ["psnr", "ause_rmse", "ece", "cov95", "cov95_err", "nll", "spearman", "time_s", "train_time_s"]


def uq_table(runs: Sequence[Run]) -> dict[str, dict]:
    """{'method (regime)': macro row over scenes of per-scene seed means} for every uq.json regime of the runs (the
    paper's Table 3 shape). A regime over several runs (the deep ensemble) sits on its first member's run and counts
    once per scene; its time_s/train_time_s are summed over its members by b3dgs-eval."""
    keys = sorted({(r.method, g) for r in runs for g in r.uq})
    order = {m: i for i, m in enumerate(method_order(r.method for r in runs))}
    out = {}
    for method, regime in sorted(keys, key=lambda k: (order.get(k[0], 99), k[1])):
        rs = [r for r in runs if r.method == method and regime in r.uq]
        row = {"n_scenes": len({r.scene for r in rs}), "n_runs": len(rs)}
        for name in UQ_COLUMNS:
            sm = scene_means(rs, name, regime)
            row[name] = float(np.mean(list(sm.values()))) if sm else None
        n_members = max(len(r.uq[regime].get("runs") or [1]) for r in rs)
        out[f"{method} ({regime})" if n_members == 1 else f"{regime} of {n_members} {method} runs"] = row
    return out


def canonical_table(runs: Sequence[Run], uq_regime: "str | Sequence[str] | None") -> dict[str, dict]:
    """{method: macro row} in the paper's method order."""
    by_m = group(runs, "method")
    return {m: macro_row(by_m[(m,)], uq_regime) for m in method_order(r.method for r in runs)}


def per_scene(runs: Sequence[Run], name: str = "psnr") -> dict[str, dict[str, dict]]:
    """{scene: {method: {mean, sem, n}}} of ``name`` over seeds."""
    out: dict[str, dict[str, dict]] = {}
    for (scene, method), rs in group(runs, "scene", "method").items():
        m, s = mean_sem([r.value(name) for r in rs])
        n = sum(1 for r in rs if r.value(name) is not None)  # a run that did not log it is not counted
        out.setdefault(scene, {})[method] = {"mean": m, "sem": s, "n": n}
    return {s: out[s] for s in sorted(out)}


def paired(runs: Sequence[Run], a: str, b: str, name: str, regime: Optional[str] = None, **boot) -> dict:
    """``a`` − ``b`` on ``name``: per scene the mean over the seeds both methods ran, then the scene-level
    paired statistics (cluster bootstrap over scenes, exact sign-flip p, wins/losses, p floor)."""
    per_scene_d, n_pairs = {}, 0
    for (scene,), rs in group(runs, "scene").items():
        va = {r.seed: r.value(name, regime) for r in rs if r.method == a}
        vb = {r.seed: r.value(name, regime) for r in rs if r.method == b}
        d = [va[s] - vb[s] for s in sorted(va.keys() & vb.keys()) if va[s] is not None and vb[s] is not None]
        if d:
            per_scene_d[scene] = float(np.mean(d))
            n_pairs += len(d)
    res = paired_stats(list(per_scene_d.values()), HIGHER_IS_BETTER.get(name, True), **boot)
    return {"a": a, "b": b, "metric": name, "per_scene": per_scene_d, "n_pairs": n_pairs, **res}


def curves(runs: Sequence[Run], key: str = "psnr") -> dict[str, dict[str, dict]]:
    """{scene: {method: {t, y, sem, n_seeds}}}: seeds averaged at each logged step that all of them
    logged (time and ``key`` both averaged), with the SEM of ``key``."""
    out: dict[str, dict[str, dict]] = {}
    for (scene, method), rs in group(runs, "scene", "method").items():
        cs = [{p["step"]: p for p in r.curve if key in p} for r in rs if r.curve]
        cs = [c for c in cs if c]
        if not cs:
            continue
        steps = sorted(set.intersection(*(set(c) for c in cs)))
        t = [float(np.mean([c[s]["train_time_s"] for c in cs])) for s in steps]
        ms = [mean_sem([c[s][key] for c in cs]) for s in steps]
        out.setdefault(scene, {})[method] = {"step": steps, "t": t, "y": [m for m, _ in ms],
                                             "sem": [e for _, e in ms], "n_seeds": len(cs)}
    return {s: out[s] for s in sorted(out)}


def time_to_target(runs: Sequence[Run], fractions: Sequence[float] = (0.95, 0.99)) -> dict[str, dict]:
    """{method: {"t95": macro mean s, ..., "per_scene": {scene: {"t95": ...}}}}: per run, the training time
    to reach a fraction of its final PSNR gain over the first logged point, seed means, macro mean."""
    out: dict[str, dict] = {}
    by_m = group(runs, "method")
    for m in method_order(r.method for r in runs):
        row: dict = {"per_scene": {}}
        for f in fractions:
            k = f"t{round(f * 100):d}"
            for (scene,), rs in group(by_m[(m,)], "scene").items():
                v, _ = mean_sem([time_to_fraction(r.curve, f) for r in rs])
                row["per_scene"].setdefault(scene, {})[k] = v
            vals = [d[k] for d in row["per_scene"].values() if d.get(k) is not None]
            row[k] = float(np.mean(vals)) if vals else None
        finals = scene_means(by_m[(m,)], "train_time_s")
        row["train_time_s"] = float(np.mean(list(finals.values()))) if finals else None
        out[m] = row
    return out


PARETO_AXES = [("train_time_s", "train time (s)", False), ("num_gaussians", "#Gaussians", False),
               ("render_fps", "render FPS", True)]


def pareto(runs: Sequence[Run]) -> dict[str, dict]:
    """{scene or "macro": {"points": {method: {psnr, train_time_s, num_gaussians, render_fps}},
    "front": {axis: [methods on the PSNR frontier]}}}."""
    panels: dict[str, dict] = {}
    scenes = sorted({r.scene for r in runs})
    for label in scenes + (["macro"] if len(scenes) > 1 else []):
        sel = runs if label == "macro" else [r for r in runs if r.scene == label]
        pts = {}
        for m in method_order(r.method for r in sel):
            rs = [r for r in sel if r.method == m]
            vals = {k: list(scene_means(rs, k).values()) for k in ["psnr"] + [a for a, _, _ in PARETO_AXES]}
            pts[m] = {k: (float(np.mean(v)) if v else None) for k, v in vals.items()}
        front = {}
        for axis, _, higher in PARETO_AXES:
            ms = [m for m, p in pts.items() if p[axis] is not None and p["psnr"] is not None]
            cost = [(-pts[m][axis] if higher else pts[m][axis]) for m in ms]
            front[axis] = [ms[i] for i in pareto_front(cost, [pts[m]["psnr"] for m in ms])]
        panels[label] = {"points": pts, "front": front}
    return panels
