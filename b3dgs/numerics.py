"""Named counters for numerical guards (clamps, jitters, floors).

Every place (posterior math, renderer, ops) that modifies a value for numerical
safety calls :func:`guard` with the number of affected entries, so no guard is
ever applied silently: counts are queryable via :func:`guard_counts` and each
name is logged on its first firing and then at most once per ``LOG_EVERY``
firing calls.
"""

from __future__ import annotations

import logging
import threading
from typing import Union

import torch

from b3dgs.errors import B3dgsError

__all__ = ["guard", "guard_counts", "guard_calls", "reset_guards", "LOG_EVERY", "float_dtype", "scalar_or_vector"]

log = logging.getLogger(__name__)

#: A name is logged on its first firing call and then once every LOG_EVERY firing calls.
LOG_EVERY = 1000

_lock = threading.Lock()
_counts: dict[str, int] = {}
_fired_calls: dict[str, int] = {}


def _to_count(mask_or_count: Union[torch.Tensor, int, bool, float]) -> int:
    if isinstance(mask_or_count, torch.Tensor):
        if mask_or_count.dtype == torch.bool:
            return int(mask_or_count.sum().item())
        if mask_or_count.numel() == 1:
            return int(mask_or_count.item())
        raise B3dgsError("guard(): tensor argument must be a bool mask or a scalar count")
    if isinstance(mask_or_count, bool):
        return int(mask_or_count)
    n = int(mask_or_count)
    if n < 0:
        raise B3dgsError(f"guard(): negative count {n}")
    return n


def guard(name: str, mask_or_count: Union[torch.Tensor, int, bool]) -> int:
    """Record that guard ``name`` fired on ``mask_or_count`` entries; returns that count."""
    n = _to_count(mask_or_count)
    if n == 0:
        return 0
    with _lock:
        _counts[name] = _counts.get(name, 0) + n
        calls = _fired_calls.get(name, 0)
        _fired_calls[name] = calls + 1
        total = _counts[name]
    if calls % LOG_EVERY == 0:
        log.warning("numerical guard '%s' fired on %d entries (total %d, firing call #%d)", name, n, total, calls + 1)
    return n


def guard_counts() -> dict[str, int]:
    """Snapshot of the number of guarded entries per guard name."""
    with _lock:
        return dict(_counts)


def guard_calls() -> dict[str, int]:
    """Snapshot of the number of calls in which each guard fired (at least one entry)."""
    with _lock:
        return dict(_fired_calls)


def reset_guards() -> None:
    """Clear all guard counters."""
    with _lock:
        _counts.clear()
        _fired_calls.clear()


def float_dtype(x: torch.Tensor) -> torch.dtype:
    """The dtype of a result computed from ``x``: its own if floating point, else torch's default."""
    return x.dtype if x.is_floating_point() else torch.get_default_dtype()


def scalar_or_vector(name: str, x, K: int, device) -> torch.Tensor:
    """(K,) float64 from a (K,) tensor or a scalar (broadcast); ``name`` is the value's name in the error."""
    t = torch.as_tensor(x, dtype=torch.float64, device=device)
    if t.ndim == 0:
        return t.expand(K)
    if tuple(t.shape) != (K,):
        raise B3dgsError(f"{name}: expected shape ({K},) or a scalar, got {tuple(t.shape)}")
    return t
