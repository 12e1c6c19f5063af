"""A run dir that one process owns: its lock, its deferred job log and ``.hydra/``, stale temp files, signals.

* :func:`run_dir_lock`: an exclusive ``fcntl.flock`` on ``<run dir>/.b3dgs.lock`` (holding the owner's
  pid), taken before anything else is written; a second process is refused with one line. The kernel drops
  the lock when its process dies (even by ``kill -9``), so a lock file left behind is stale by
  construction: the next run takes it over.
* :class:`DeferredFileHandler`: Hydra's job-log handler (``conf/hydra/default.yaml``) that keeps records in
  memory until :func:`arm_run_log` is called once every check has passed; a refused run writes no log.
  ``.hydra/`` is written by :func:`write_hydra_files` at the same moment (``hydra.output_subdir`` is null).
* :func:`remove_stale_tmp`: the ``.<name>.<random>.tmp`` files of :func:`b3dgs.io.atomic_path` that a kill
  left behind.
* :class:`Interrupted` / :func:`interrupt_handlers`: SIGINT and SIGTERM become a checkpoint at the next step
  boundary (:class:`b3dgs.callbacks.RunCheckpoint`) and an exit with 128 + the signal number.
"""
from __future__ import annotations

import errno
import fcntl
import logging
import os
import signal
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Optional

from b3dgs.errors import B3dgsError

LOCK_NAME = ".b3dgs.lock"


@contextmanager
def run_dir_lock(run_dir: Path, prog: str = "b3dgs-train") -> Iterator[None]:
    """Hold ``run_dir``'s lock for the block; refuse (one line) if another live process holds it.

    An empty run dir left by a refused run is removed on the way out."""
    run_dir = Path(run_dir)
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise B3dgsError(f"the run dir {run_dir} is a file (or lies below one)",
                         "pass hydra.run.dir=PATH to a folder") from None
    except PermissionError:
        raise B3dgsError(f"cannot create the run dir {run_dir}: permission denied",
                         "pass hydra.run.dir=PATH to a writable folder") from None
    path = run_dir / LOCK_NAME
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except PermissionError:
            raise B3dgsError(f"the run dir {run_dir} is not writable",
                             "pass hydra.run.dir=PATH to a writable folder") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            if e.errno not in (errno.EAGAIN, errno.EACCES):
                os.close(fd)
                raise
            owner = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise B3dgsError(f"the run dir {run_dir} is in use by another {prog} (pid {owner})",
                             "wait for it to finish, or pass another hydra.run.dir") from None
        try:  # the file may have been removed by its previous owner between our open and flock: retry
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    try:
        yield
    finally:
        try:
            path.unlink()
        except FileNotFoundError:
            pass
        os.close(fd)
        try:
            run_dir.rmdir()  # only if the run left nothing (a refused run in a new dir)
        except OSError:
            pass


def remove_stale_tmp(run_dir: Path) -> list[Path]:
    """Remove the temp files (``.<name>.*.tmp``) that a killed run left in ``run_dir`` and its sub-folders."""
    gone = []
    for p in Path(run_dir).rglob(".*.tmp"):
        if p.is_file():
            p.unlink()
            gone.append(p)
    return gone


# ------------------------------------------------------------------------------ job log and .hydra/
class DeferredFileHandler(logging.FileHandler):
    """Hydra's job-log file handler, holding records in memory until :func:`arm_run_log` (a refused run
    leaves no log file)."""

    def __init__(self, filename, mode: str = "a", encoding: Optional[str] = None, **kw) -> None:
        super().__init__(filename, mode=mode, encoding=encoding, delay=True)
        self._held: Optional[list[logging.LogRecord]] = []

    def emit(self, record: logging.LogRecord) -> None:
        if self._held is not None:
            if len(self._held) < 10000:
                self._held.append(record)
            return
        super().emit(record)

    def arm(self, fresh: bool = False) -> None:
        held, self._held = self._held or [], None
        if fresh:
            self.mode = "w"  # overwrite=true: the replaced run's log goes too
        for r in held:
            super().emit(r)


def arm_run_log(fresh: bool = False) -> None:
    """Start writing the job log (with what was logged so far); ``fresh``: replace an old log, not append."""
    for h in logging.getLogger().handlers:
        if isinstance(h, DeferredFileHandler):
            h.arm(fresh)


def write_hydra_files(run_dir: Path, cfg) -> None:
    """Hydra's ``.hydra/{config,hydra,overrides}.yaml`` for this job, written once the run is accepted."""
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf, open_dict

    from b3dgs.io import atomic_path

    if not HydraConfig.initialized():
        return
    hc = HydraConfig.instance().cfg
    out = Path(run_dir) / ".hydra"
    out.mkdir(parents=True, exist_ok=True)
    task = cfg.copy()
    with open_dict(task):
        task.pop("hydra", None)
    for name, node in (("config.yaml", task), ("hydra.yaml", hc), ("overrides.yaml", hc.hydra.overrides.task)):
        with atomic_path(out / name) as tmp:
            tmp.write_text(OmegaConf.to_yaml(node))


# ---------------------------------------------------------------------------------------------- signals
class Interrupted(Exception):
    """SIGINT / SIGTERM received; ``exit_code`` is 128 + the signal number (130 / 143)."""

    def __init__(self, signum: int, step: Optional[int] = None):
        self.signum = int(signum)
        self.step = step
        super().__init__(f"interrupted by {signal.Signals(self.signum).name}")

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


class _Pending:
    signum: Optional[int] = None
    deferred = False  # True while training: the signal is acted on at the next step boundary


PENDING = _Pending()


def _on_signal(signum, frame) -> None:
    PENDING.signum = signum
    if not PENDING.deferred:
        raise Interrupted(signum)


@contextmanager
def interrupt_handlers() -> Iterator[_Pending]:
    """SIGINT and SIGTERM raise :class:`Interrupted` here, or (while ``PENDING.deferred``) are recorded for
    :class:`b3dgs.callbacks.RunCheckpoint` to act on after the current step."""
    PENDING.signum, PENDING.deferred = None, False
    if threading.current_thread() is not threading.main_thread():  # signal handlers live in the main thread only
        yield PENDING
        return
    old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    for s in old:
        signal.signal(s, _on_signal)
    try:
        yield PENDING
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        PENDING.deferred = False
