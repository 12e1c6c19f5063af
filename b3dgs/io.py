"""Atomic file writing: results are either fully written or not there at all."""
from __future__ import annotations

import json
import math
import os
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator


#: the marker of :func:`atomic_path`'s temp files, ``.<name>.b3dgs-<random>.tmp``: what a kill leaves is told apart
#: from a user's own ``.*.tmp`` file (:func:`b3dgs.rundir.remove_stale_tmp` removes only ours)
TEMP_MARK = ".b3dgs-"


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path in the target's directory; rename it onto ``path`` on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}{TEMP_MARK}", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp_path, 0o666 & ~umask)  # mkstemp creates 0600; give the usual file mode
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_json(path: str | os.PathLike, obj: Any, indent: int = 2) -> None:
    """Write JSON atomically. NaN/Inf are rejected (they are not JSON); use None."""
    text = json.dumps(obj, indent=indent, allow_nan=False, default=_json_default)
    with atomic_path(path) as tmp:
        tmp.write_text(text + "\n")



def read_json_dict(path: str | os.PathLike) -> dict | None:
    """The JSON object in ``path``; None when it is missing, unreadable, or not an object."""
    try:
        d = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) else None

def save_figure(fig: Any, path: str | os.PathLike, dpi: Any = None) -> Path:
    """Write a matplotlib figure to ``path`` as PNG, atomically (``dpi``: matplotlib's, default the figure's), and
    close it if pyplot manages it; the one way b3dgs saves a figure. Returns ``path``."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", **({} if dpi is None else {"dpi": dpi}))
    pyplot = sys.modules.get("matplotlib.pyplot")
    if pyplot is not None:
        pyplot.close(fig)
    return path


def _plain_leaf(o: Any) -> Any:
    """A tensor / array as a (nested) list, a numpy scalar as a Python number, a path as a string; anything
    else is returned as it is."""
    try:
        import numpy as np
        import torch

        if isinstance(o, torch.Tensor):
            return o.detach().cpu().tolist()
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, np.generic):
            return o.item()
    except ImportError:  # pragma: no cover
        pass
    if isinstance(o, Path):
        return str(o)
    return o


def _json_default(o: Any) -> Any:
    plain = _plain_leaf(o)
    if plain is o:
        raise TypeError(f"Object of type {type(o).__name__} is not JSON serialisable")  # protocol: json's default=
    return plain


def to_jsonable(obj: Any) -> Any:
    """``obj`` as plain JSON values, recursively: containers, tensors and arrays as lists, numpy scalars as
    numbers, and non-finite floats as None (JSON has no NaN; :func:`write_json` refuses them)."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    plain = _plain_leaf(obj)
    if plain is not obj:
        return to_jsonable(plain)
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj
