"""Locks across processes, all in one place: :func:`process_lock` and :func:`lock_holder`.

The lock is filelock's native lock on a descriptor of the lock file (``filelock.lock_descriptor``: ``flock`` on
Unix, ``LockFileEx`` on Windows), so the operating system releases it when its holder exits, also when it is
killed (``kill -9``): a lock file left behind is stale by construction and the next process takes it over. The
holder writes its pid into the file, so a refusal can name it (``... in use by another b3dgs-train (pid 123)``).
Used for the run dir (:func:`b3dgs.rundir.run_dir_lock`), the C++ build (:mod:`b3dgs.render._ext`) and the
active-view study's shared phase-1 models; ``b3dgs-eval`` merges into ``uq.json`` under ``filelock.FileLock``.
"""
from __future__ import annotations

import os
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Optional

from filelock import lock_descriptor, unlock_descriptor


class LockHeld(Exception):
    """:func:`process_lock` with ``wait=False`` found the lock held; ``pid``: the holder's, or ``"?"``."""

    def __init__(self, path: Path, pid: str):
        super().__init__(f"{path} is held by pid {pid}")
        self.path, self.pid = path, pid


def _read_pid(fd: int) -> str:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        return os.read(fd, 32).decode(errors="replace").strip()
    except OSError:
        return ""


def pid_alive(pid) -> bool:
    """Whether the process ``pid`` (an int or its text) is alive (another user's counts)."""
    try:
        os.kill(int(pid), 0)
    except (ValueError, ProcessLookupError, OverflowError):
        return False
    except PermissionError:
        pass  # alive, another user's
    return True


@contextmanager
def process_lock(path: Path, *, wait: bool = True, remove: bool = False) -> Iterator[None]:
    """Hold the lock on ``path`` (created if missing) for the block, with this process's pid in the file.

    ``wait=False`` raises :class:`LockHeld` at once when another process (or another call in this one) holds it.
    ``remove=True`` deletes the file on the way out. ``OSError`` from opening the file (e.g. ``PermissionError``)
    propagates."""
    path = Path(path)
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            got = lock_descriptor(fd, blocking=wait)
        except BaseException:
            os.close(fd)
            raise
        if not got:
            pid = _read_pid(fd) or "?"
            os.close(fd)
            raise LockHeld(path, pid)
        try:  # the file may have been removed by its previous holder between our open and lock: retry
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    os.ftruncate(fd, 0)
    os.lseek(fd, 0, os.SEEK_SET)
    os.write(fd, f"{os.getpid()}\n".encode())
    try:
        yield
    finally:
        if remove:
            path.unlink(missing_ok=True)
        else:
            unlock_descriptor(fd)
        os.close(fd)


def lock_holder(path: Path) -> Optional[str]:
    """The pid of the live process that holds the lock on ``path`` (``"?"`` if it wrote none), else ``None``.

    A probe of another reader holds the lock for microseconds and writes no pid: a held lock whose file names no
    live process is probed again before it counts as held."""
    pid = ""
    for attempt in range(3):
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError:
            return None
        try:
            if lock_descriptor(fd, blocking=False):
                unlock_descriptor(fd)
                return None
            pid = _read_pid(fd)
        finally:
            os.close(fd)
        if pid_alive(pid):
            return pid
        time.sleep(0.01 * (attempt + 1))
    return pid or "?"
