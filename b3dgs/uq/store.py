"""Where ``b3dgs-eval`` writes, and how it adds to a ``uq.json`` without losing what is there.

* :func:`merge_into`: the new regimes are merged into the folder's ``uq.json`` under a lock
  (``.uq.json.lock``, :mod:`filelock`), atomically; a regime's panels (``uq/<regime>_<view>.png``, staged while
  it was scored) replace its old ones in the same step, and the sparsification / reliability plots are redrawn
  from every regime the file holds. Regimes of other evaluations stay, so concurrent evaluations of one run
  keep all their results. A run that changed while the evaluation ran is refused (:func:`check_unchanged`).
* :func:`ensemble_dir`: an ensemble's own folder, beside its first member and named for the members, so that
  it never lands in a member's ``uq.json`` unless ``out=`` asks for it.
* :func:`check_members`: the members of an ensemble must differ only in seed (scene, model, protocol and
  step count agree), like the runs the report pools.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
from contextlib import nullcontext
from pathlib import Path
from typing import Mapping, Optional, Sequence

from b3dgs.errors import B3dgsError
from b3dgs.io import read_json_dict, write_json
from b3dgs.rundir import manifest_lock, read_manifest, record_written, remove_listed, run_dir_stamp
from b3dgs.upgrade import upgrade_targets, uq_panels

UQ_NAME = "uq.json"
LOCK_NAME = ".uq.json.lock"
#: seconds an evaluation waits for another one writing the same uq.json
LOCK_TIMEOUT_S = 600.0
#: the plots :func:`_plot_all` writes (where some regime kept its mean curves)
PLOTS = ("uq/sparsification.png", "uq/reliability.png")


def ensemble_dir(members: Sequence[Path]) -> Path:
    """``<first member's parent>/ensemble_<member names joined by +>`` (a digest of the member paths instead of
    their names when these repeat or run long)."""
    paths = [Path(m).resolve() for m in members]
    names = [p.name for p in paths]
    name = "ensemble_" + "+".join(names)
    if len(set(names)) < len(names) or len(name) > 100:
        digest = hashlib.sha256("\n".join(map(str, paths)).encode()).hexdigest()[:8]
        name = f"ensemble_{names[0][:40]}_and_{len(names) - 1}_more_{digest}"
    return paths[0].parent / name


def _read_config(run_dir: Path) -> Optional[dict]:
    from omegaconf import OmegaConf

    try:
        return upgrade_targets(OmegaConf.to_container(OmegaConf.load(Path(run_dir) / "config.yaml"), resolve=False))
    except Exception:  # noqa: BLE001 - load_run names a damaged config itself
        return None


def _read_metrics(run_dir: Path) -> dict:
    return read_json_dict(Path(run_dir) / "metrics.json") or {}


def check_members(run_dirs: Sequence[str | Path]) -> None:
    """Refuse ensemble members of another scene, model, protocol (:func:`b3dgs.protocol.run_protocol`) or step
    count than the first, and a model given twice (the same final parameters)."""
    from b3dgs.protocol import describe_diff, differing_keys, run_protocol

    fix = "pass run= runs that differ only in seed (one scene, model and protocol), e.g. run=[RUN_S0,RUN_S1,RUN_S2]"
    first = Path(run_dirs[0])
    ref_cfg, ref_m = _read_config(first), _read_metrics(first)
    digests = {(ref_m.get("checkpoint") or {}).get("params_sha256"): first}
    for r in map(Path, run_dirs[1:]):
        cfg, m = _read_config(r), _read_metrics(r)
        if ref_cfg is not None and cfg is not None:
            a, b = run_protocol(ref_cfg), run_protocol(cfg)
            keys = differing_keys(a, b)
            if keys:
                raise B3dgsError(f"the ensemble members differ in {describe_diff(a, b, keys, (f'in {first}', f'in {r}'), 3)}",
                                 fix)
        if ref_m.get("steps") is not None and m.get("steps") is not None and ref_m["steps"] != m["steps"]:
            raise B3dgsError(f"the ensemble members trained for different step counts: {ref_m['steps']} in {first}, "
                             f"{m['steps']} in {r}", fix)
        d = (m.get("checkpoint") or {}).get("params_sha256")
        if d is not None and d in digests:
            raise B3dgsError(f"the ensemble members {digests[d]} and {r} hold the same model (one parameter digest): "
                             "an ensemble of copies has zero spread", fix)
        digests[d] = r


def run_digest(metrics: Optional[Mapping]) -> Optional[str]:
    """The parameter digest of a run's final checkpoint, as its metrics.json records it."""
    return ((metrics or {}).get("checkpoint") or {}).get("params_sha256")


def read_uq(folder: Path) -> dict:
    """``folder/uq.json`` (``{}`` without one); a damaged one is refused in one line, never replaced."""
    path = Path(folder) / UQ_NAME
    if not path.exists():
        return {}
    try:
        d = json.loads(path.read_text())
        if not isinstance(d, dict):
            raise B3dgsError("not a JSON object")
    except (OSError, ValueError) as e:
        raise B3dgsError(f"{path} is damaged ({' '.join(str(e).split())[:80]}); b3dgs-eval adds to it and never "
                         "replaces it", "move it away, or pass out=PATH to another folder") from None
    return d


def check_unchanged(folder: Path, new: Mapping[str, dict], expect: Optional[Mapping] = None) -> None:
    """Refuse to merge results into ``folder`` once a run changed under the evaluation: ``folder`` holds another run
    than ``expect`` (its :func:`b3dgs.rundir.run_dir_stamp` when the evaluation started: ``overwrite=true`` replaced
    it, or a training started there), or a run an entry scored has another final checkpoint than the one evaluated."""
    folder = Path(folder)
    if expect is not None and run_dir_stamp(folder) != dict(expect):
        raise B3dgsError(f"{folder} holds another run than when this b3dgs-eval started (overwrite=true or a training "
                         f"replaced it meanwhile): its results were not merged into {folder / UQ_NAME}",
                         f"run b3dgs-eval again on the run {folder} holds now")
    for entry in new.values():
        for run, digest in zip(entry.get("runs") or [], entry.get("run_checkpoints") or []):
            if digest is not None and run_digest(_read_metrics(run)) != digest:
                raise B3dgsError(f"the run {run} changed while this b3dgs-eval ran (its final checkpoint is not the "
                                 f"one evaluated): the results were not merged into {folder / UQ_NAME}",
                                 f"run b3dgs-eval run={run} again")


def merge_into(folder: Path, new: Mapping[str, dict], meta: Mapping, staging: Optional[Path],
               expect: Optional[Mapping] = None) -> dict:
    """Merge the regimes ``new`` (each with its ``panels``, staged in ``staging`` with its TensorBoard events in
    ``staging/tb_uq``) into ``folder/uq.json`` under the folder's uq lock and (a run dir) its run dir lock, after
    :func:`check_unchanged` (``expect``: the folder's run dir stamp when the evaluation started); the files are listed
    in a run dir's manifest by name before they are written. Returns the merged file."""
    from filelock import FileLock, Timeout

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    try:
        lock = FileLock(str(folder / LOCK_NAME), timeout=LOCK_TIMEOUT_S)
        lock.acquire()
    except Timeout:
        raise B3dgsError(f"another b3dgs-eval has been writing {folder / UQ_NAME} for {LOCK_TIMEOUT_S:.0f} s",
                         f"wait for it, or remove {folder / LOCK_NAME} if no b3dgs-eval runs") from None
    try:
        with manifest_lock(folder, "b3dgs-eval") if read_manifest(folder) is not None else nullcontext():
            check_unchanged(folder, new, expect)
            have = read_uq(folder)
            old_meta = have.get("_meta") if isinstance(have.get("_meta"), dict) else {}
            stale = []
            for name, entry in new.items():
                old = have.get(name)
                if isinstance(old, dict):
                    stale += sorted(set(uq_panels(name, old, old_meta)) - set(entry.get("panels") or []))
            events = sorted((Path(staging) / "tb_uq").glob("*")) if staging is not None else []
            merged = {**{k: v for k, v in have.items() if k != "_meta"}, **new, "_meta": {**old_meta, **meta}}
            record_written(folder, [UQ_NAME, LOCK_NAME, *(PLOTS if _curves(merged) else ()),
                                    *(f"tb_uq/{e.name}" for e in events),
                                    *(p for e in new.values() for p in e.get("panels") or [])], forget=stale)
            remove_listed(folder, stale)
            for name, entry in new.items():
                for p in entry.get("panels") or []:
                    dst = folder / p
                    dst.parent.mkdir(parents=True, exist_ok=True)
                    os.replace(Path(staging) / Path(p).name, dst)
            if events:
                (folder / "tb_uq").mkdir(exist_ok=True)
                for e in events:
                    os.replace(e, folder / "tb_uq" / e.name)
            write_json(folder / UQ_NAME, merged)
            _plot_all(folder, merged)
    finally:
        lock.release()
    return merged


def _curves(merged: Mapping) -> dict:
    return {k: v["curves"] for k, v in merged.items()
            if not k.startswith("_") and isinstance(v, dict) and isinstance(v.get("curves"), dict)}


def _plot_all(folder: Path, merged: Mapping) -> None:
    """The sparsification and reliability plots of every regime in ``merged`` that kept its mean curves."""
    from b3dgs.uq.plots import plot_reliability, plot_sparsification

    curves = _curves(merged)
    if curves:
        plot_sparsification(curves, folder / PLOTS[0])
        plot_reliability(curves, folder / PLOTS[1])


def remove_staging(staging: Optional[Path]) -> None:
    if staging is not None:
        shutil.rmtree(staging, ignore_errors=True)
