"""Test callback: a training process that kills or signals itself at a chosen point, like ``kill -9`` / Ctrl-C.

Added to a run through the configurable callbacks, never by b3dgs itself::

    b3dgs-train ... +callbacks.kill._target_=tests.kill_hooks.KillAt +callbacks.kill.step=K +callbacks.kill.signal=TERM

(:func:`kill_args` writes those overrides). Points: ``step=K`` right after training step ``K`` (before that
step's checkpoint: Lightning runs checkpoint callbacks last, and b3dgs's ``last.ckpt`` callback acts on a
SIGTERM / SIGINT recorded here at the same step); ``point="final"`` once training is done, before the final
evaluation and writes; ``point="write:<file name>"`` once the temp file of ``<file name>`` is written, before
:func:`b3dgs.io.atomic_path` renames it onto ``<file name>``; ``point="log"`` right after the job log file
(``train.log``) is created. ``signal``: KILL (default: no handler, no
cleanup), TERM, INT or STOP.
"""
from __future__ import annotations

import os
import signal as _signal
from pathlib import Path
from typing import Optional

import lightning as L

TARGET = "tests.kill_hooks.KillAt"


def kill_args(step: Optional[int] = None, point: Optional[str] = None, sig: str = "KILL") -> list[str]:
    """The command-line overrides that add :class:`KillAt` to a b3dgs-train (or b3dgs-study) run."""
    out = [f"+callbacks.kill._target_={TARGET}", f"+callbacks.kill.signal={sig}"]
    if step is not None:
        out.append(f"+callbacks.kill.step={int(step)}")
    if point is not None:
        out.append(f"+callbacks.kill.point='{point}'")
    return out


class KillAt(L.Callback):
    def __init__(self, step: Optional[int] = None, point: Optional[str] = None, signal: str = "KILL"):
        self.step = None if step is None else int(step)
        self.point = point
        self.signum = int(getattr(_signal, "SIG" + str(signal).upper()))
        if point and point.startswith("write:"):
            self._arm_write(point[len("write:"):])
        if point == "log":
            self._arm_log()

    def _fire(self) -> None:
        os.kill(os.getpid(), self.signum)

    def _arm_write(self, name: str) -> None:
        """Fire when a temp file is about to be renamed onto ``name`` (atomic_path's last act)."""
        replace = os.replace

        def hooked(src, dst, *args, **kw):
            if Path(dst).name == name and Path(src).name.startswith(f".{name}."):
                os.replace = replace
                self._fire()
            return replace(src, dst, *args, **kw)

        os.replace = hooked

    def _arm_log(self) -> None:
        """Fire once a job-log file handler (Hydra's ``train.log``) has created its file."""
        import logging

        for h in logging.getLogger().handlers:
            if isinstance(h, logging.FileHandler):
                def hooked(h=h, opened=h._open):
                    stream = opened()
                    self._fire()
                    return stream

                h._open = hooked

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if self.step is not None and int(trainer.global_step) >= self.step:
            self.step = None
            self._fire()

    def on_fit_end(self, trainer, pl_module) -> None:
        if self.point == "final":
            self.point = None
            self._fire()
