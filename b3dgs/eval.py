"""``b3dgs-eval``: uncertainty regimes and calibration metrics for one run (or an ensemble of runs).

Adds to ``uq.json`` shaped ``{regime: {cov95, cov95_err, ause_rmse, ause_mae, ece, nll, spearman,
time_s, psnr, lpips, ..., runs, run_checkpoints, per_view: [...]}, _meta: {...}}`` regime by regime (the regimes
already there stay), with sparsification/reliability plots and render | GT | error | uncertainty panels (PNG
and TensorBoard): in the run dir, for an ensemble in its own folder beside its first member (``out=`` picks
the folder for both, but never another run's dir: :func:`check_out_dir`). The last line says where it wrote.
Known errors print ``b3dgs-eval: error: <problem> (fix: <what to do>)`` and exit with code 2.
"""
from __future__ import annotations

import logging
import time
from contextlib import suppress
from pathlib import Path
from typing import Optional

import hydra
import torch
from omegaconf import DictConfig, ListConfig, OmegaConf

from b3dgs.errors import B3dgsError, cli_main, known_errors
from b3dgs.progress import progress
from b3dgs.rundir import read_manifest, remove_stale_staging, run_dir_busy, run_dir_kind, run_dir_stamp, staging_prefix
from b3dgs.train import CONF_DIR
from b3dgs.uq.store import check_members, ensemble_dir, merge_into, read_uq, remove_staging, run_digest

log = logging.getLogger(__name__)


def regimes_from_cfg(cfg: DictConfig) -> dict:
    from hydra.utils import instantiate

    out = {}
    for name, node in (cfg.get("uq") or {}).items():
        if isinstance(node, DictConfig) and "_target_" in node:
            out[name] = instantiate(node)
    if not out:
        raise B3dgsError("No uncertainty regime selected",
                         fix="pass uq=[native,proxy] (options: the files of conf/uq, e.g. native, proxy, ensemble, "
                             "ppu)")
    return out


def refuse_running(run_dirs) -> None:
    """Refuse a run dir that a ``b3dgs-train`` is still writing (its lock is held by a live process)."""
    for r in run_dirs:
        pid = run_dir_busy(Path(str(r)))
        if pid is not None:
            raise B3dgsError(f"the run {r} is still training (b3dgs-train pid {pid} holds it)",
                             "wait for that training to finish, then run b3dgs-eval again")


def _destinations(regimes: dict, runs: list, out_dir: Optional[Path]) -> dict[str, Path]:
    """Where each regime's results go: ``out_dir`` when given; else a regime that combines several runs (an
    ensemble) into its own folder (:func:`b3dgs.uq.store.ensemble_dir`), the others into the first run's dir."""
    out = {}
    for name, regime in regimes.items():
        multi = bool(getattr(regime, "min_members", 0)) and len(runs) > 1
        out[name] = Path(out_dir) if out_dir else ensemble_dir([r.path for r in runs]) if multi else Path(runs[0].path)
    return out


def check_out_dir(out_dir: Path, first) -> None:
    """``out=`` may name a new folder, one of the user's, or the run dir of the run evaluated (or a copy of it, by
    parameter digest); not another run's dir, whose ``uq.json`` holds that run's results only (issue 46 §6)."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir() or run_dir_kind(out_dir) not in ("run", "legacy"):
        return
    mine, theirs = run_digest(first.metrics), run_dir_stamp(out_dir)["params_sha256"]
    if out_dir.resolve() == Path(first.path).resolve() or (mine is not None and mine == theirs):
        return
    raise B3dgsError(f"out={out_dir} is the run dir of another run: its uq.json holds that run's results, not those "
                     f"of {first.path}", f"leave out= out to write into {first.path}, or pass out= a folder that is "
                     "not a run dir")


def evaluate_uq(run_dirs: list[str], regimes: dict, seed: int = 0, max_views: Optional[int] = None,
                panels: int = 3, out_dir: Optional[Path] = None, loaded: Optional[list] = None,
                meta: Optional[dict] = None, lpips_weights: Optional[str] = None, data_path: Optional[str] = None) -> dict:
    """Fit every regime on the loaded run(s), score it on the test views and add it to a ``uq.json``; returns this
    evaluation's regimes and ``_meta``.

    Regimes with an epistemic part are also scored on that part alone (:func:`b3dgs.uq.metrics.epistemic_view`).
    ``loaded``: already loaded runs (:class:`b3dgs.runs.LoadedRun`) used instead of ``run_dirs``; ``meta``: extra
    ``_meta`` entries. Results go to ``out_dir`` (default: :func:`_destinations`), merged into its ``uq.json`` only if
    neither its run nor a scored run changed meanwhile (:func:`b3dgs.uq.store.merge_into`); each entry records its runs
    and their parameter digests (``run_checkpoints``), views, seed, panels and mean curves. ``data_path``: the runs'
    scene folder on this machine (:func:`b3dgs.runs.locate_scene`).
    """
    import tempfile

    from b3dgs.metrics.image import psnr as psnr_fn
    from b3dgs.metrics.lpips import get_lpips
    from b3dgs.runs import load_run
    from b3dgs.uq.metrics import epistemic_summary, epistemic_view, evaluate_view, summarize, to_jsonable
    from b3dgs.uq.plots import plot_uncertainty_panel

    if loaded:
        runs = list(loaded)
        first = runs[0]
    else:
        if not run_dirs:
            raise B3dgsError("run= must name at least one run dir",
                             fix="pass run=<a b3dgs-train run dir> (or run=[dir1,dir2] for regimes that combine "
                                 "several runs)")
        refuse_running(run_dirs)
        if len(run_dirs) > 1 and any(getattr(r, "min_members", 0) for r in regimes.values()):
            check_members(run_dirs)
        first = load_run(run_dirs[0], data_path=data_path)
        runs = [first] + [load_run(r, scene=first.scene) for r in run_dirs[1:]]
    scene = first.scene
    cams = scene.test[:max_views] if max_views else scene.test
    if not cams:
        raise B3dgsError("The scene has no test views (data.test_every=0?); nothing to evaluate",
                         fix="evaluate a run trained with held-out views: data.test_every=8 (the default) or "
                             "data.test_split=sector")
    dests = _destinations(regimes, runs, out_dir)
    made = [d for d in dict.fromkeys(dests.values()) if not d.exists()]
    for d in dict.fromkeys(dests.values()):
        read_uq(d)  # a damaged uq.json is refused before any work, not after
        # so is a damaged run manifest (the results join it): before anything is written, not after
        read_manifest(d, fix="pass out=DIR to write the results into another folder")
    if out_dir is not None:
        check_out_dir(out_dir, first)
    # what each folder holds now: the results are merged only into the same run (§8: overwrite=true meanwhile)
    stamps = {d: run_dir_stamp(d) for d in dict.fromkeys(dests.values())}
    lpips_model, lpips_reason = get_lpips(lpips_weights)
    train_times = [float((r.metrics or {}).get("train_time_s") or 0.0) for r in runs]
    writers: dict = {}
    staging: dict[Path, Path] = {}

    def writer_for(d: Path):
        if d not in writers:
            try:
                from torch.utils.tensorboard import SummaryWriter

                writers[d] = SummaryWriter(str(staging[d] / "tb_uq"))  # published with the panels
            except Exception as e:  # tensorboard missing: PNGs only
                log.warning("TensorBoard unavailable (%s); panels are written as PNG only", e)
                writers[d] = None
        return writers[d]

    result: dict = {}
    meta = {"nll_note": "NLL is comparable only within one uncertainty regime",
            "views": [c.name for c in cams], "seed": int(seed),
            "calib_views": [c.name for c in getattr(scene, "calib", None) or []], **(meta or {})}
    try:
        for name, regime in regimes.items():
            # regimes that combine several runs declare ``min_members``; the others use the first run
            multi = bool(getattr(regime, "min_members", 0))
            members = runs if multi else [first]
            dest = dests[name]
            if dest not in staging:
                dest.mkdir(parents=True, exist_ok=True)
                for p in remove_stale_staging(dest):
                    log.info("removed %s, the staging folder of an interrupted b3dgs-eval", p.name)
                staging[dest] = Path(tempfile.mkdtemp(prefix=staging_prefix(), dir=dest))
            t0 = time.perf_counter()
            regime.fit([r.module for r in members], scene)
            gen = torch.Generator().manual_seed(int(seed))
            per_view, panel_files = [], []
            for i, cam in enumerate(progress(cams, desc=f"uq {name}", leave=False)):
                pred = regime.predict(cam, generator=gen).cpu()
                row = evaluate_view(pred.mean, pred.var, cam.image)
                row["name"] = cam.name
                row["psnr"] = float(psnr_fn(pred.mean.clamp(0, 1), cam.image))
                if lpips_model is not None:
                    row["lpips"] = float(lpips_model(pred.mean.clamp(0, 1), cam.image))
                row["mean_epistemic"] = float(pred.epistemic.mean())
                row["aleatoric"] = pred.aleatoric
                if regime.has_epistemic:
                    row.update(epistemic_view(pred.epistemic, pred.mean, cam.image, pred.var, seed=int(seed)))
                per_view.append(row)
                if i < panels:
                    err = (pred.mean - cam.image).abs().mean(-1)
                    panel = f"{name}_{Path(cam.name).stem}.png"
                    img = plot_uncertainty_panel(pred.mean.clamp(0, 1), cam.image, err, pred.var.sqrt(),
                                                 staging[dest] / panel, title=f"{name}: {cam.name}")
                    panel_files.append(f"uq/{panel}")
                    writer = writer_for(dest)
                    if writer is not None:
                        writer.add_image(f"uq/{name}/{cam.name}", torch.from_numpy(img).permute(2, 0, 1), 0)
            elapsed = time.perf_counter() - t0
            summ = summarize(per_view)
            curves = summ.pop("mean_curves", None)
            summ["spearman"] = summ.get("spearman_rho")
            summ["has_epistemic"] = bool(regime.has_epistemic)
            if regime.has_epistemic:
                summ.update(epistemic_summary(per_view))
            summ["fit"] = dict(getattr(regime, "fit_info", None) or {})
            summ["time_s"] = round(elapsed, 3)
            summ["train_time_s"] = round(sum(train_times) if multi else train_times[0], 3)
            summ["samples"] = getattr(regime, "samples", None)
            summ["runs"] = [str(r.path) for r in members]
            summ["run_checkpoints"] = [run_digest(r.metrics) for r in members]
            summ["views"] = [c.name for c in cams]
            summ["seed"] = int(seed)
            summ["panels"] = panel_files
            summ["curves"] = curves
            if lpips_model is None:
                summ["lpips_reason"] = lpips_reason
            result[name] = to_jsonable(summ)
            log.info("%s: Cov@95 %.3f (|err| %.3f), AUSE-RMSE %.4f, ECE %.4f, NLL %.3f, %.1f s", name,
                     summ.get("cov95", float("nan")), summ.get("cov95_err", float("nan")),
                     summ.get("ause_rmse", float("nan")), summ.get("ece", float("nan")), summ.get("nll", float("nan")),
                     elapsed)
        for w in writers.values():
            if w is not None:
                w.close()
        meta = to_jsonable(meta)
        for dest in dict.fromkeys(dests.values()):
            merge_into(dest, {k: v for k, v in result.items() if dests[k] == dest}, meta, staging.get(dest),
                       expect=stamps[dest])
    finally:
        for d in staging.values():
            remove_staging(d)
        for d in made:
            with suppress(OSError):
                d.rmdir()  # a folder made for an evaluation that failed
    wrote = "; ".join(f"{', '.join(k for k in result if dests[k] == d)} to {d / 'uq.json'} (plots in {d / 'uq'})"
                      for d in dict.fromkeys(dests.values()))
    log.info("Wrote %s", wrote)
    result["_meta"] = meta
    return result


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="eval")
def hydra_main(cfg: DictConfig) -> None:
    from b3dgs.validation import validate_config

    with known_errors("b3dgs-eval", cfg, quiet=True):
        runs = cfg.run
        run_dirs = [str(r) for r in runs] if isinstance(runs, (ListConfig, list, tuple)) else [str(runs)]
        refuse_running(run_dirs)  # before the checks that would call a running run unfinished
        regimes = validate_config(cfg, app="eval")
        if cfg.get("threads"):
            torch.set_num_threads(int(cfg.threads))
        evaluate_uq(run_dirs, regimes, seed=int(cfg.seed), max_views=cfg.get("max_views"),
                    panels=int(cfg.panels), out_dir=Path(cfg.out) if cfg.get("out") else None,
                    lpips_weights=cfg.get("lpips_weights"), data_path=OmegaConf.select(cfg, "data.path"))


main = cli_main("b3dgs-eval", hydra_main, "eval")


if __name__ == "__main__":
    main()
