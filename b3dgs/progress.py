"""Progress bars that stay readable in a log file.

``tqdm`` redraws its bar with a carriage return on every update: in a terminal that is one moving line, in a
cluster's log file or a pipe it is one ever-growing line. :func:`progress` gives a normal bar when its stream is a
terminal and, otherwise, whole lines at most every ``line_every_s`` seconds plus the final state (the training bar,
:class:`b3dgs.callbacks.StepProgressBar`, follows the same rule)."""
from __future__ import annotations

import sys
from typing import Any, Iterable, Optional

from tqdm.autonotebook import tqdm as auto_tqdm  # tqdm's own bar, or its widget inside Jupyter
from tqdm.std import tqdm

LINE_EVERY_S = 30.0


def is_terminal(stream: Any) -> bool:
    """Whether ``stream`` is an interactive terminal (a bar may redraw in place)."""
    isatty = getattr(stream, "isatty", None)
    try:
        return bool(callable(isatty) and isatty())
    except ValueError:  # a closed stream
        return False


class _Lines:
    """The stream a line bar writes to: tqdm's own bare ``"\n"`` / ``"\r"`` writes (at close) are dropped."""

    def __init__(self, stream: Any):
        self.stream = stream

    def write(self, s: str) -> int:
        return self.stream.write(s) if s.strip() else 0

    def flush(self) -> None:
        self.stream.flush()


class _LineTqdm(tqdm):
    """A tqdm that prints its state as a whole line (never a carriage-return redraw); a cleared bar prints nothing."""

    _closing = False
    _printed_n: Optional[int] = None

    def display(self, msg: Optional[str] = None, pos: Optional[int] = None) -> bool:
        text = self.__str__() if msg is None else msg
        if text and not (self._closing and self.n == self._printed_n):  # the last line once, not twice
            self.fp.write(text + "\n")
            self.fp.flush()
            self._printed_n = self.n
        return True

    def close(self) -> None:
        self._closing = True
        super().close()


def progress(iterable: Optional[Iterable] = None, *, file: Any = None, line_every_s: float = LINE_EVERY_S,
             **kwargs) -> tqdm:
    """``tqdm(iterable, file=file, **kwargs)`` on a terminal; else a bar printed as whole lines, at most one every
    ``line_every_s`` seconds and its final state at the end (also for a ``leave=False`` bar, which a terminal clears:
    a log has nothing to clear, and a bar whose last line says 0/N reads as a job that stopped)."""
    stream = sys.stderr if file is None else file
    if auto_tqdm is not tqdm:  # Jupyter: its widget
        return auto_tqdm(iterable, file=file, **kwargs) if file is not None else auto_tqdm(iterable, **kwargs)
    if is_terminal(stream):
        return tqdm(iterable, file=stream, **kwargs)
    kwargs.setdefault("dynamic_ncols", False)
    kwargs["leave"] = True
    return _LineTqdm(iterable, file=_Lines(stream), mininterval=float(line_every_s), maxinterval=float(line_every_s),
                     ascii=True, **kwargs)
