"""The end of a ``b3dgs-train -m`` sweep: a summary table over its finished runs (a Hydra callback).

:class:`SweepSummary` (``conf/hydra/default.yaml``, ``hydra.callbacks.sweep_summary``) reads every finished run
dir below the sweep dir once all jobs are done (any launcher: basic, joblib, submitit), groups the runs by scene,
method label (:func:`b3dgs.labels.method_label`) and the swept settings other than the seed, and prints one row per
group: mean ± SEM over its seeds of PSNR, SSIM, LPIPS, Gaussians and training time. The table also goes to
``<sweep dir>/summary.md`` and ``summary.json``; the last line says where.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Optional

from hydra.experimental.callback import Callback

from b3dgs.io import atomic_path, write_json

log = logging.getLogger(__name__)

__all__ = ["SweepSummary", "summarize_runs"]

COLUMNS = (("psnr", "PSNR (dB)", ".3f"), ("ssim", "SSIM", ".4f"), ("lpips", "LPIPS", ".4f"),
           ("num_gaussians", "Gaussians", ",.0f"), ("train_time_s", "train time (s)", ".1f"))


def _cell(mean: Optional[float], sem: Optional[float], spec: str) -> str:
    if mean is None:
        return "—"
    return format(mean, spec) + ("" if sem is None else f" ± {format(sem, spec)}")


def summarize_runs(run_dirs: list[Path], swept: list[str]) -> tuple[list[str], list[list[str]], list[dict]]:
    """(header, rows, groups) of the table over ``run_dirs``: one row per scene, method and value of the ``swept``
    keys other than ``seed`` (config groups among them show as the scene and method)."""
    from b3dgs.protocol import flatten
    from b3dgs.report.collect import ReportError, read_run
    from b3dgs.report.stats import mean_sem

    runs = []
    for d in run_dirs:
        try:
            runs.append(read_run(d))
        except ReportError as e:
            log.warning("sweep summary: %s left out (%s)", d, e)
    flat = [flatten(r.config) for r in runs]
    # swept values (not config groups: those show in the scene and method columns)
    keys = [k for k in swept if k != "seed" and any(k in f for f in flat)]
    groups: dict[tuple, list] = {}
    for run, f in zip(runs, flat):
        groups.setdefault((run.scene, run.method, *(str(f.get(k)) for k in keys)), []).append(run)
    header = ["scene", "method", *keys, "seeds", *(label for _, label, _ in COLUMNS)]
    rows, out = [], []
    for key, runs in groups.items():
        stats = {name: mean_sem([r.value(name) for r in runs]) for name, _, _ in COLUMNS}
        seeds = sorted(r.seed for r in runs)
        rows.append([*key, f"{len(seeds)} ({', '.join(map(str, seeds))})",
                     *(_cell(*stats[name], spec) for name, _, spec in COLUMNS)])
        out.append({"key": dict(zip(["scene", "method", *keys], key)), "seeds": seeds, "runs": [str(r.path) for r in runs],
                    **{name: {"mean": m, "sem": s} for name, (m, s) in stats.items()}})
    return header, rows, out


class SweepSummary(Callback):
    """Hydra callback: the summary table of a finished multirun (see the module doc)."""

    def on_multirun_end(self, config: Any, **kwargs: Any) -> None:
        from b3dgs.report.collect import find_runs
        from b3dgs.report.document import markdown_table

        sweep = Path(str(config.hydra.sweep.dir))
        runs, unfinished, _ = find_runs([str(sweep)]) if sweep.is_dir() else ([], [], [])
        if not runs:
            print(f"b3dgs-train: the sweep finished no run (nothing in {sweep})", flush=True)
            return
        swept = [str(o).partition("=")[0].lstrip("+~") for o in (config.hydra.overrides.task or []) if "," in str(o)]
        header, rows, groups = summarize_runs(runs, swept)
        lines = markdown_table(header, rows)
        note = (f"{len(runs)} finished runs" + (f", {len(unfinished)} unfinished" if unfinished else "")
                + "; mean ± SEM over seeds (SEM of one seed: none)")
        write_json(sweep / "summary.json", {"runs": [str(r) for r in runs], "groups": groups})
        with atomic_path(sweep / "summary.md") as tmp:
            tmp.write_text("# Sweep summary\n\n" + "\n".join(lines) + f"\n\n{note}.\n")
        print("\n".join(["", "Sweep summary: " + note, *lines, "",
                         f"b3dgs-train: {len(runs)} runs in {sweep}; summary in {sweep / 'summary.md'}"]), flush=True)
