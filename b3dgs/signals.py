"""SIGINT and SIGTERM as an exception: :class:`Interrupted` (exit code 128 + the signal number), raised at once or,
while ``PENDING.deferred``, recorded for the code that stops at a safe point (a training step's end, a viewer's loop).
Every command runs inside :func:`interrupt_handlers` (:func:`b3dgs.errors.run_cli`), so a signal unwinds its
``finally`` blocks and locks and ends with one line; training and b3dgs-process nest their own, to save or resume."""
from __future__ import annotations

import signal
import sys
import threading
from contextlib import contextmanager
from typing import Iterator, Optional

__all__ = ["PENDING", "Interrupted", "interrupt_handlers"]


class Interrupted(BaseException):
    """SIGINT / SIGTERM received; ``exit_code`` is 128 + the signal number (130 / 143). A ``BaseException``, as
    ``KeyboardInterrupt`` is, so that no ``except Exception`` mistakes a signal for a failure of what it guards."""

    def __init__(self, signum: int, step: Optional[int] = None):
        self.signum = int(signum)
        self.step = step
        super().__init__(f"interrupted by {self.signal_name}")

    @property
    def exit_code(self) -> int:
        return 128 + self.signum

    @property
    def signal_name(self) -> str:
        return signal.Signals(self.signum).name

    def report(self, prog: str, advice: Optional[str] = None) -> int:
        """Write ``PROG: stopped by SIGTERM[; ADVICE]`` on stderr (after what stdout holds) and return the exit code."""
        sys.stdout.flush()
        sys.stderr.write(f"{prog}: stopped by {self.signal_name}{'; ' + advice if advice else ''}\n")
        sys.stderr.flush()
        return self.exit_code


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
