"""Finished run dirs: finding them, reading them, and keying them by their own config.

A run dir holds ``config.yaml``; ``metrics.json`` is its done marker. A run is keyed by (study, level, scene, method,
seed), all read from ``config.yaml``: scene = ``data.name``; method = :func:`b3dgs.labels.method_label`; study =
``sparse`` when ``data.train_indices`` is set, else ``initcap`` when ``model.init_max_points`` is below the standard
model's default, else ``canonical`` (a ``study`` node, ``name`` and ``level``, wins); level = the study's variable
(the number of train views, ``model.init_max_points``, else ``study.level`` or None). ``group_by`` keys split a study
by their values (``canonical [trainer.max_steps=300]``, still a canonical group: :attr:`Run.base_study`).
"""
from __future__ import annotations

import glob
import json
import logging
import os
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Optional, Sequence

from omegaconf import OmegaConf

from b3dgs.errors import B3dgsError
from b3dgs.protocol import describe_diff, differing_keys, flatten, run_protocol
from b3dgs.labels import method_label
from b3dgs.upgrade import posterior_pass_s, upgrade_targets
from b3dgs.uq.store import run_digest

log = logging.getLogger(__name__)

__all__ = ["ReportError", "Run", "find_runs", "load_runs", "group", "METHOD_ORDER", "method_order"]

METHOD_ORDER = ["standard", "niw", "dpmm", "mcmc"]


class ReportError(B3dgsError):
    """Bad input to the report (the CLI prints it as one line)."""


@dataclass
class Run:
    path: Path
    config: dict
    metrics: dict
    curve: list = field(default_factory=list)  # curve.json points
    uq: dict = field(default_factory=dict)  # regime -> summary with per_view (uq.json without _meta)
    study: str = "canonical"
    level: Any = None
    scene: str = ""
    method: str = ""
    seed: int = 0
    split: str = ""  # the group_by values ("trainer.max_steps=300"), appended to ``study`` as " [...]"

    @property
    def key(self) -> tuple:
        return (self.study, self.level, self.scene, self.method, self.seed)

    @property
    def base_study(self) -> str:
        """The study without its group_by values: ``canonical`` for ``canonical [trainer.max_steps=300]``."""
        return self.study[: -len(f" [{self.split}]")] if self.split else self.study

    def value(self, name: str, regime: Optional[str] = None) -> Optional[float]:
        """A scalar of metrics.json, or of uq.json's ``regime`` when given (None if absent).
        ``block_time_pct``: the posterior blocks' share of the training time in %, (Σ ``block_time_s`` + the
        blocks' pass over the training views after training, ``posterior_pass_s``) / (``train_time_s`` + that pass)
        (measured inside the run, so it holds under any machine load; 0 without blocks)."""
        if name == "block_time_pct" and regime is None:
            t, bt = self.metrics.get("train_time_s"), self.metrics.get("block_time_s")
            if not isinstance(t, (int, float)) or t <= 0 or not isinstance(bt, dict):
                return None
            ps = posterior_pass_s(self.metrics)
            return 100.0 * (float(sum(float(v) for v in bt.values())) + ps) / (float(t) + ps)
        src = self.metrics if regime is None else self.uq.get(regime, {})
        v = src.get(name)
        return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def method_order(methods) -> list[str]:
    """Known methods in the paper's order, then the others alphabetically."""
    ms = set(methods)
    return [m for m in METHOD_ORDER if m in ms] + sorted(ms - set(METHOD_ORDER))


def _is_run_dir(p: Path) -> bool:
    return p.is_dir() and (p / "config.yaml").is_file() and not any(part.startswith(".") for part in p.parts[-1:])


def find_runs(patterns: Sequence[str]) -> tuple[list[Path], list[Path], list[Path]]:
    """(finished run dirs, unfinished run dirs, other uq.json files) matched by the globs.

    A pattern may name run dirs (``outputs/bench/**``, ``**`` recurses), a metrics.json file or a folder
    holding runs somewhere below it.
    """
    runs: set[Path] = set()
    uqs: set[Path] = set()
    for pat in patterns:
        for m in glob.glob(os.path.expanduser(str(pat)), recursive=True):
            p = Path(m)
            if p.is_file():
                if p.name == "uq.json":
                    uqs.add(p.resolve())
                p = p.parent
            if _is_run_dir(p):
                runs.add(p.resolve())
            elif p.is_dir() and "**" not in str(pat):
                runs.update(c.parent.resolve() for c in p.rglob("config.yaml") if _is_run_dir(c.parent))
                uqs.update(u.resolve() for u in p.rglob("uq.json"))
    finished = sorted(r for r in runs if (r / "metrics.json").is_file())
    unfinished = sorted(r for r in runs if not (r / "metrics.json").is_file())
    others = sorted(u for u in uqs if u.parent not in runs)
    return finished, unfinished, others


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise ReportError(f"cannot read {path}: {e}",
                          fix="restore or regenerate that file (b3dgs-train writes metrics.json, b3dgs-eval uq.json), "
                              "or leave its run out of runs=") from e


@lru_cache(maxsize=1)
def default_init_cap() -> Optional[int]:
    """``model.init_max_points`` of conf/model/standard.yaml (the models inherit it); None if unreadable."""
    from b3dgs.train import CONF_DIR

    try:
        return int(OmegaConf.load(Path(CONF_DIR) / "model" / "standard.yaml").model.init_max_points)
    except Exception:  # a changed or missing option file: no init-cap inference
        return None


def classify(cfg: dict) -> tuple[str, Any]:
    """(study, level) of a run from its config (see the module docstring)."""
    tag = cfg.get("study") or {}
    ti = (cfg.get("data") or {}).get("train_indices")
    cap, default = (cfg.get("model") or {}).get("init_max_points"), default_init_cap()
    capped = isinstance(cap, int) and default is not None and cap < default
    study = str(tag.get("name") or ("sparse" if ti is not None else "initcap" if capped else "canonical"))
    if study == "sparse":
        return study, (len(ti) if ti is not None else "all")
    if study == "initcap":
        return study, (cfg.get("model") or {}).get("init_max_points")
    return study, tag.get("level")


def check_own_records(path: Path, metrics: dict, curve: list) -> None:
    """Refuse a run whose metrics.json disagrees with its own records: each of psnr, ssim and lpips is the mean of
    its per-view values (``evaluate_views`` writes it so), and the curve's point at the final step holds the final
    PSNR. A hand-edited or mixed-up file would otherwise enter the tables as if measured."""
    import math

    per_view = [v for v in metrics.get("per_view") or [] if isinstance(v, dict)]
    for key in ("psnr", "ssim", "lpips"):
        vals = [v[key] for v in per_view if isinstance(v.get(key), (int, float))]
        top = metrics.get(key)
        if vals and isinstance(top, (int, float)) and len(vals) == len(per_view):
            mean = math.fsum(vals) / len(vals)
            if not abs(mean - top) <= 1e-6 * max(1.0, abs(top)):
                raise ReportError(f"{path / 'metrics.json'} disagrees with its own per-view values: {key} {top:.6g}, "
                                  f"the mean of its {len(vals)} views {mean:.6g}",
                                  "restore the run's files (or train it again); leave it out of runs= meanwhile")
    last = [p for p in curve if isinstance(p, dict) and p.get("step") == metrics.get("steps")
            and isinstance(p.get("psnr"), (int, float))]
    if last and isinstance(metrics.get("psnr"), (int, float)) and not abs(last[-1]["psnr"] - metrics["psnr"]) <= 1e-6:
        raise ReportError(f"{path / 'metrics.json'} disagrees with its curve: final PSNR {metrics['psnr']:.6g}, "
                          f"curve.json at step {metrics['steps']}: {last[-1]['psnr']:.6g}",
                          "restore the run's files (or train it again); leave it out of runs= meanwhile")


def read_run(path: Path) -> Run:
    """One finished run dir -> :class:`Run` (ReportError naming the file if it is malformed)."""
    try:
        cfg = upgrade_targets(OmegaConf.to_container(OmegaConf.load(path / "config.yaml"), resolve=False))
    except Exception as e:  # yaml errors come in many types
        raise ReportError(f"cannot read {path / 'config.yaml'}: {e}",
                          fix="restore that run dir's config.yaml (b3dgs-train writes it), or leave the run out of "
                              "runs=") from e
    metrics = _read_json(path / "metrics.json")
    try:
        scene, seed, _ = str(cfg["data"]["name"]), int(cfg["seed"]), cfg["model"]["name"]
        method = method_label(cfg)
    except (KeyError, TypeError, ValueError) as e:
        raise ReportError(f"{path / 'config.yaml'} lacks data.name, model.name or seed ({e}); "
                          "is it a b3dgs-train run dir?",
                          fix="narrow runs= to b3dgs-train run dirs (each with the config.yaml b3dgs-train "
                              "wrote)") from e
    curve = _read_json(path / "curve.json").get("points", []) if (path / "curve.json").is_file() else []
    check_own_records(path, metrics, curve)
    uq = _own_uq(path, metrics)
    study, level = classify(cfg)
    return Run(path, cfg, metrics, curve, uq, study, level, scene, method, seed)


def uq_scores_other_run(path: Path, metrics: dict, entry: dict) -> Optional[str]:
    """The run a uq.json regime entry scores when that is not the run at ``path`` (else ``None``): its first
    member's parameter digest (``run_checkpoints``) against the run's metrics.json; for entries written before
    digests, the run dir it names, where that still exists (a copy of the same run, by digest, matches)."""
    runs = entry.get("runs") or []
    if not runs:
        return None
    mine = run_digest(metrics)
    theirs = (entry.get("run_checkpoints") or [None])[0]
    if theirs and mine:
        return None if theirs == mine else str(runs[0])
    named = Path(str(runs[0]))
    try:
        if not named.exists() or named.resolve() == Path(path).resolve() or os.path.samefile(named, path):
            return None  # moved or archived since (cannot tell), or this very run
    except OSError:
        return None
    try:
        other = json.loads((named / "metrics.json").read_text())
    except (OSError, ValueError):
        other = None
    return None if mine and run_digest(other) == mine else str(runs[0])


def _own_uq(path: Path, metrics: dict) -> dict:
    """The regimes of ``path/uq.json`` that score this run; the others are left out with a warning line."""
    uq = _read_json(path / "uq.json") if (path / "uq.json").is_file() else {}
    uq = {k: v for k, v in uq.items() if not k.startswith("_") and isinstance(v, dict)}
    other = {k: uq_scores_other_run(path, metrics, v) for k, v in uq.items()}
    bad = {k: o for k, o in other.items() if o}
    if bad:
        log.warning("%s: its uq.json regimes %s score the run %s, not this one: left out of the report (fix: run "
                    "b3dgs-eval run=%s)", path, ", ".join(bad), ", ".join(sorted(set(bad.values()))), path)
    return {k: v for k, v in uq.items() if k not in bad}


def _attach_uq(runs: list[Run], uq_files: Sequence[Path]) -> None:
    """uq.json files outside run dirs (e.g. a deep ensemble's) join the run they name first (found by its path,
    or by its parameter digest where it was moved), when that run's digest matches."""
    by_path = {r.path: r for r in runs}
    by_digest = {run_digest(r.metrics): r for r in runs if run_digest(r.metrics)}
    for f in uq_files:
        for regime, summ in _read_json(f).items():
            if regime.startswith("_") or not isinstance(summ, dict):
                continue
            for member in (summ.get("runs") or [])[:1]:
                theirs = (summ.get("run_checkpoints") or [None])[0]
                owner = (by_path.get(Path(member).resolve()) or by_digest.get(theirs)
                         or _moved_run(runs, Path(f).parent, Path(member)))
                if owner is None:
                    log.warning("%s: regime %s names the run %s, which is not among the report's runs: left out "
                                "(fix: add that run to runs=)", f, regime, member)
                if owner is not None and uq_scores_other_run(owner.path, owner.metrics, summ):
                    log.warning("%s: regime %s names the run %s, which now holds another model: left out of the "
                                "report (fix: run b3dgs-eval for it again)", f, regime, member)
                elif owner is not None and regime not in owner.uq:
                    owner.uq[regime] = summ


def _moved_run(runs: Sequence[Run], base: Path, member: Path) -> Optional[Run]:
    """The run a uq.json names by a path that no longer exists as written (the runs were copied to another machine or
    checkout, ``/work/main/bench/results/runs/fox/standard/s0`` read from ``~/b3dgs/bench/results/runs/...``): a
    relative path resolved from the uq.json's folder, else the one run whose path ends with the longest tail of the
    named path (at least ``<method>/s<seed>``-deep plus one folder); None when no tail is unique."""
    if not member.is_absolute():
        return next((r for r in runs if r.path == (base / member).resolve()), None)
    parts = member.parts
    for k in range(len(parts) - 1, 2, -1):
        hits = [r for r in runs if r.path.parts[-k:] == parts[-k:]]
        if len(hits) == 1:
            return hits[0]
        if len(hits) > 1:
            return None
    return None


#: settings every pooled run must share, across methods and scenes too (the protocol of a table)
SHARED_KEYS = ("trainer.", "data.max_side", "data.test_every", "data.max_images", "data.normalize")


def _apply_group_by(run: Run, group_by: Sequence[str]) -> None:
    """Runs that differ in a ``group_by`` key are reported as separate studies (``study [key=value]``)."""
    if group_by:
        flat = flatten(run.config)
        run.split = ", ".join(f"{k}={flat.get(k)}" for k in group_by)
        run.study = f"{run.study} [{run.split}]"


def check_pooling(runs: Sequence[Run], group_by: Sequence[str] = ()) -> None:
    """Refuse to pool runs of different protocols: the seeds of one (study, level, scene, method) must agree on
    every setting that changes results (:func:`b3dgs.protocol.run_protocol`), and all runs of a study on the
    trainer and resolution settings; ``group_by`` keys split them instead."""
    hint = "pass group_by=[{keys}] to report each value separately, or narrow runs= to one protocol"
    for name, rs, pick in [("seeds of " + "/".join(map(str, k[2:4])) + f" ({k[0]})", v, None)
                           for k, v in group(runs, "study", "level", "scene", "method").items()] + \
                          [(f"runs of study {k[0]}", v, SHARED_KEYS) for k, v in group(runs, "study").items()]:
        ref = rs[0]
        for r in rs[1:]:
            a, b = run_protocol(ref.config), run_protocol(r.config)
            if pick is not None:
                a = {k: v for k, v in a.items() if k.startswith(pick)}
                b = {k: v for k, v in b.items() if k.startswith(pick)}
            keys = differing_keys(a, b)
            if keys:
                raise ReportError(f"the {name} differ in {describe_diff(a, b, keys, names=(f'in {ref.path}', f'in {r.path}'), limit=2)}",
                                  hint.format(keys=','.join(keys[:3])))


def machine_kinds(runs: Sequence[Run]) -> dict[str, int]:
    """{kind of machine: runs} over the runs whose metrics.json records ``machine`` (CPU model, torch's CPU
    dispatch, GPU: b3dgs.device.machine; runs from before it recorded one are left out), sorted by kind."""
    from b3dgs.device import machine_kind

    kinds: dict[str, int] = {}
    for r in runs:
        m = r.metrics.get("machine")
        if isinstance(m, dict):
            k = machine_kind(m)
            kinds[k] = kinds.get(k, 0) + 1
    return dict(sorted(kinds.items()))


def load_runs(patterns: Sequence[str] | str, on_duplicate: str = "error", group_by: Sequence[str] = ()
              ) -> tuple[list[Run], list[Path]]:
    """Finished runs matched by the glob(s), one per key, and the unfinished run dirs skipped; runs of
    different protocols are refused (:func:`check_pooling`) unless ``group_by`` separates them."""
    patterns = [patterns] if isinstance(patterns, (str, os.PathLike)) else list(patterns)
    group_by = [str(k) for k in group_by]
    finished, unfinished, uq_files = find_runs(patterns)
    if not finished:
        extra = f" ({len(unfinished)} unfinished: no metrics.json)" if unfinished else ""
        raise ReportError(f"no finished run dirs matched runs={patterns}{extra}",
                          fix="pass a glob of b3dgs-train run dirs, e.g. runs='outputs/train/*' (b3dgs-train's own; "
                              "a -m sweep's are in outputs/multirun/<time>/*; quote the glob so the shell does not "
                              "expand it)")
    keyed: dict[tuple, Run] = {}
    for path in finished:
        run = read_run(path)
        _apply_group_by(run, group_by)
        old = keyed.get(run.key)
        if old is not None:
            if on_duplicate != "newest":
                raise ReportError(f"two finished runs share (study, level, scene, method, seed)={run.key}: "
                                  f"{old.path} and {run.path}", fix="narrow runs= or pass on_duplicate=newest")
            newer = (run.path / "metrics.json").stat().st_mtime > (old.path / "metrics.json").stat().st_mtime
            run = run if newer else old
        keyed[run.key] = run
    runs = sorted(keyed.values(), key=lambda r: (r.study, str(r.level), r.scene, r.method, r.seed))
    check_pooling(runs, group_by)
    _attach_uq(runs, uq_files)
    return runs, unfinished


def group(runs: Sequence[Run], *fields: str) -> dict[tuple, list[Run]]:
    """Runs grouped by the given attributes (insertion order of first appearance)."""
    out: dict[tuple, list[Run]] = {}
    for r in runs:
        out.setdefault(tuple(getattr(r, f) for f in fields), []).append(r)
    return out
