"""Open a finished run dir for the viewer, or refuse it in one line (:class:`~b3dgs.errors.B3dgsError`).

Refused: a path that does not exist or is no run dir, a run still training (its lock is held) or
unfinished (no ``metrics.json``, the done marker, or no ``checkpoints/last.ckpt``), and a run written by
another b3dgs version (``metrics.json`` without the checkpoint record this version writes, or a config /
checkpoint this code cannot rebuild: unknown settings, plugins or parameters).
"""
from __future__ import annotations

import json
from contextlib import suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from b3dgs.errors import B3dgsError

__all__ = ["ViewedRun", "acquired_views", "open_run", "suggested_cameras"]


@dataclass
class ViewedRun:
    """A loaded run plus what the side panel shows: ``metrics.json``, ``curve.json`` points, acquired views."""

    path: Path
    loaded: object  # b3dgs.runs.LoadedRun
    metrics: dict
    curve: list[dict] = field(default_factory=list)
    acquired: list[str] = field(default_factory=list)
    suggested: list = field(default_factory=list)  # b3dgs-suggest's cameras in rank order (RUN/suggest/suggest.json)

    @property
    def module(self):
        return self.loaded.module

    @property
    def scene(self):
        return self.loaded.scene


def acquired_views(path: Optional[Path]) -> list[str]:
    """The acquired views in pick order from an active-view study row's ``selection.json`` (``path``: the
    file or its row dir); [] when there is none."""
    if path is None:
        return []
    path = Path(path)
    f = path / "selection.json" if path.is_dir() else path
    if not f.is_file():
        return []
    try:
        sel = json.loads(f.read_text())
        return [str(n) for n in sel["selected"]]
    except (ValueError, KeyError, TypeError) as e:
        raise B3dgsError(f"{f} is not an active-view selection ({type(e).__name__}: {e})",
                         "pass acquired=ROW_DIR of b3dgs-study active, or leave acquired out") from None


def suggested_cameras(run_dir: Path) -> list:
    """The cameras ``b3dgs-suggest`` left in ``run_dir/suggest/suggest.json``, in rank order (the run's frame); []
    when there is none or it cannot be read (the viewer opens the run anyway)."""
    import torch

    from b3dgs.types import Camera

    f = Path(run_dir) / "suggest" / "suggest.json"
    if not f.is_file():
        return []
    try:
        return [Camera(f"suggest_{int(s['rank']):02d}", torch.tensor(s["K"], dtype=torch.float32),
                       torch.tensor(s["viewmat"], dtype=torch.float32), int(s["width"]), int(s["height"]))
                for s in json.loads(f.read_text())["suggestions"]]
    except (ValueError, KeyError, TypeError, B3dgsError):
        return []


def open_run(run_dir, acquired: Optional[str] = None, renderer=None, data_path: Optional[str] = None) -> ViewedRun:
    """Check and load ``run_dir`` (see the module doc for what is refused); ``data_path``: its scene folder on this
    machine (:func:`b3dgs.runs.locate_scene`)."""
    from hydra.errors import InstantiationException

    from b3dgs.rundir import not_a_run_dir, run_dir_busy
    from b3dgs.runs import load_run

    run_dir = Path(str(run_dir)).expanduser()
    again = f"b3dgs-train ... hydra.run.dir={run_dir} overwrite=true"
    if not run_dir.exists():
        raise B3dgsError(f"no run dir at {run_dir}", "pass run=DIR of a finished b3dgs-train run (outputs/train/...)")
    if not run_dir.is_dir():
        raise B3dgsError(f"{run_dir} is a file, not a run dir", "pass run=DIR of a finished b3dgs-train run")
    if not (run_dir / "config.yaml").is_file():
        raise not_a_run_dir(run_dir)
    pid = run_dir_busy(run_dir)  # a live process holding the run dir's lock
    if pid is not None:
        raise B3dgsError(f"{run_dir} is still training (b3dgs-train pid {pid}); it has no final model yet",
                         "wait for it to finish: b3dgs-view opens finished runs (their checkpoints/last.ckpt and "
                         "metrics.json)")
    if not (run_dir / "metrics.json").is_file() or not (run_dir / "checkpoints" / "last.ckpt").is_file():
        missing = "metrics.json" if not (run_dir / "metrics.json").is_file() else "checkpoints/last.ckpt"
        raise B3dgsError(f"{run_dir} holds an unfinished run: no {missing}",
                         f"finish it with `b3dgs-train ... hydra.run.dir={run_dir} resume=auto`")
    try:
        metrics = json.loads((run_dir / "metrics.json").read_text())
    except ValueError as e:
        raise B3dgsError(f"{run_dir / 'metrics.json'} is damaged ({e})",
                         f"finish the run again with `b3dgs-train ... hydra.run.dir={run_dir} resume=auto`") from None
    if not isinstance(metrics, dict) or "checkpoint" not in metrics:
        raise B3dgsError(f"{run_dir} was written by another b3dgs version: its metrics.json has no checkpoint record",
                         f"train it again with this version (`{again}`)")
    from b3dgs.render.renderers import RendererUnavailable

    try:
        loaded = load_run(run_dir, renderer=renderer, data_path=data_path)
    except RendererUnavailable:  # about this machine, not the run: its own line
        raise
    except (FileNotFoundError, ValueError) as e:  # load_run's own one-line reasons (identity, digest, config)
        msg = " ".join(str(e).split())
        raise B3dgsError(f"cannot open {run_dir}: {msg.split(' (fix:')[0]}",
                         msg.split("(fix: ", 1)[1].rstrip(")") if "(fix: " in msg else f"train it again (`{again}`)") from None
    except (InstantiationException, ImportError, AttributeError, KeyError, TypeError, RuntimeError) as e:
        # a config naming settings or plugins this code lacks, or a state dict of other parameters
        raise B3dgsError(f"{run_dir} was written by another b3dgs version: this code cannot rebuild it "
                         f"({type(e).__name__}: {' '.join(str(e).split())[:160]})",
                         f"view it with the b3dgs version that trained it, or train it again (`{again}`)") from None
    curve = []
    with suppress(ValueError, AttributeError):  # a damaged curve.json: no curve
        if (run_dir / "curve.json").is_file():
            curve = list(json.loads((run_dir / "curve.json").read_text()).get("points") or [])
    sel = Path(acquired) if acquired else (run_dir if (run_dir / "selection.json").is_file() else None)
    return ViewedRun(run_dir, loaded, metrics, curve, acquired_views(sel), suggested_cameras(run_dir))
