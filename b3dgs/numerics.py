"""Named counters for numerical guards (clamps, jitters, floors).

Every place (posterior math, renderer, ops) that modifies a value for numerical
safety calls :func:`guard` with the number of affected entries, so no guard is
ever applied silently: counts are queryable via :func:`guard_counts` and each
name is logged on its first firing and then at most once per ``LOG_EVERY``
firing calls.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from typing import Iterator, Sequence, Union

import torch

from b3dgs.errors import B3dgsError

__all__ = ["guard", "guard_counts", "guard_calls", "reset_guards", "LOG_EVERY", "float_dtype", "scalar_or_vector",
           "on_device_path", "forced_device_path", "guard_deferred", "guard_where", "safe_cholesky", "sym", "vector",
           "guard_fill", "zero_invalid"]

log = logging.getLogger(__name__)

#: A name is logged on its first firing call and then once every LOG_EVERY firing calls.
LOG_EVERY = 1000

_lock = threading.Lock()
_counts: dict[str, int] = {}
_fired_calls: dict[str, int] = {}
# device-side guard counts not read yet: name -> (entries, firing calls), 0-d int64 tensors on the mask's device
_pending: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}
_FORCE_DEVICE_PATH = False


def on_device_path(x: Union[torch.Tensor, torch.device]) -> bool:
    """Whether per-step code keeps its values on the device, with no host read: for tensors off the CPU, or any
    tensor inside :func:`forced_device_path` (tests). On the CPU path, code reads values on the host as it always
    did, so CPU runs keep their bits; the device path computes the same quantities without a host sync."""
    dev = x.device if isinstance(x, torch.Tensor) else torch.device(x)
    return _FORCE_DEVICE_PATH or dev.type != "cpu"


@contextlib.contextmanager
def forced_device_path() -> Iterator[None]:
    """Run the device path (:func:`on_device_path`) on CPU tensors: how the tests check it without a GPU."""
    global _FORCE_DEVICE_PATH
    old, _FORCE_DEVICE_PATH = _FORCE_DEVICE_PATH, True
    try:
        yield
    finally:
        _FORCE_DEVICE_PATH = old


def guard_deferred(name: str, mask: torch.Tensor) -> None:
    """:func:`guard` without a host sync on the device path: the count is added on the device and read when the
    counts are (:func:`guard_counts`, once per checkpoint or at the end of a run); on the CPU path, :func:`guard`."""
    if not on_device_path(mask):
        guard(name, mask)
        return
    n = mask.sum() if mask.dtype == torch.bool else mask.reshape(()).long()
    with _lock:
        cnt, calls = _pending.get(name, (None, None))
        if cnt is None or cnt.device != n.device:
            if cnt is not None:
                _flush_locked()
            cnt = torch.zeros((), dtype=torch.long, device=n.device)
            calls = torch.zeros((), dtype=torch.long, device=n.device)
        _pending[name] = (cnt.add_(n), calls.add_(n > 0))


def guard_where(name: str, mask: torch.Tensor, fixed, value: torch.Tensor) -> torch.Tensor:
    """``torch.where(mask, fixed, value)``, counted as guard ``name`` (``fixed``: a tensor, a scalar, or a callable
    that makes it, called only when needed). On the CPU path ``value`` itself comes back where the guard did not fire
    (as before); on the device path the ``where`` always runs and the count is deferred (:func:`guard_deferred`),
    so there is no host sync."""
    if on_device_path(mask):
        guard_deferred(name, mask)
    elif not guard(name, mask):
        return value
    return torch.where(mask, fixed() if callable(fixed) else fixed, value)


def _flush_locked() -> None:
    """Move the deferred device counts into the host counters (one read per guard name); holds ``_lock``."""
    if not _pending:
        return
    items = list(_pending.items())
    _pending.clear()
    for name, (cnt, calls) in items:
        n, k = int(cnt), int(calls)
        if n == 0:
            continue
        first = name not in _counts
        _counts[name] = _counts.get(name, 0) + n
        _fired_calls[name] = _fired_calls.get(name, 0) + k
        if first:
            log.warning("numerical guard '%s' fired on %d entries in %d calls (counted on the device)", name, n, k)


def _to_count(mask_or_count: Union[torch.Tensor, int, bool, float]) -> int:
    if isinstance(mask_or_count, torch.Tensor):
        if mask_or_count.dtype == torch.bool:
            return int(mask_or_count.sum().item())
        if mask_or_count.numel() == 1:
            return int(mask_or_count.item())
        raise B3dgsError("guard(): tensor argument must be a bool mask or a scalar count",
                         fix="pass guard() a bool mask of the guarded entries, or an int count (a one-element tensor "
                             "also works)")
    if isinstance(mask_or_count, bool):
        return int(mask_or_count)
    n = int(mask_or_count)
    if n < 0:
        raise B3dgsError(f"guard(): negative count {n}",
                         fix="pass guard() a count >= 0 (the number of entries the guard changed)")
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
    """Snapshot of the number of guarded entries per guard name (deferred device counts read first)."""
    with _lock:
        _flush_locked()
        return dict(_counts)


def guard_calls() -> dict[str, int]:
    """Snapshot of the number of calls in which each guard fired (at least one entry)."""
    with _lock:
        _flush_locked()
        return dict(_fired_calls)


def reset_guards() -> None:
    """Clear all guard counters."""
    with _lock:
        _pending.clear()
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
        raise B3dgsError(f"{name}: expected shape ({K},) or a scalar, got {tuple(t.shape)}",
                         fix=f"pass {name} as a scalar or as a ({K},) tensor with one value per Gaussian")
    return t


def vector(name: str, x) -> torch.Tensor:
    """``x`` in float64, refused unless a 1-D (K,) tensor; ``name`` is the value's name in the error."""
    if not isinstance(x, torch.Tensor) or x.ndim != 1:
        raise B3dgsError(f"{name}: expected a 1-D (K,) tensor, got {getattr(x, 'shape', type(x).__name__)}",
                         fix=f"pass {name} as a 1-D torch tensor with one entry per Gaussian, shape (K,)")
    return x.to(torch.float64)


def guard_fill(name: str, mask: torch.Tensor, x: torch.Tensor, value: float) -> torch.Tensor:
    """``x`` set to ``value`` where ``mask``, counted as guard ``name``: :func:`guard_where` with a constant."""
    return guard_where(name, mask, value, x)


def zero_invalid(name: str, x: torch.Tensor) -> torch.Tensor:
    """``x`` with its non-finite and negative entries set to 0, counted as guard ``name``."""
    return guard_fill(name, ~torch.isfinite(x) | (x < 0), x, 0.0)


def sym(A: torch.Tensor) -> torch.Tensor:
    """The symmetric part ½(A + Aᵀ) of a batch of square matrices."""
    return 0.5 * (A + A.transpose(-1, -2))


#: Escalating diagonal jitter for safe_cholesky, relative to the mean |diagonal|.
CHOLESKY_JITTERS = (1e-12, 1e-10, 1e-8, 1e-6, 1e-5, 1e-4, 1e-3)


def safe_cholesky(A: torch.Tensor, jitters: Sequence[float] = CHOLESKY_JITTERS) -> torch.Tensor:
    """Lower Cholesky factor of symmetric A (..., D, D), computed in float64, never NaN.

    Failing matrices get diagonal jitter ``j * mean|diag|`` for j in ``jitters`` (escalating;
    guard ``cholesky.jitter``); if all fail, eigenvalues are clipped (``cholesky.eig_fallback``);
    non-finite matrices are replaced by the identity (``cholesky.nonfinite``).
    """
    if not isinstance(A, torch.Tensor) or A.ndim < 2 or A.shape[-1] != A.shape[-2]:
        raise B3dgsError(f"A: expected (..., D, D), got {getattr(A, 'shape', type(A).__name__)}",
                         fix="pass A as a float tensor of shape (..., D, D), a batch of square matrices")
    dtype = float_dtype(A)
    shape = A.shape
    D = int(shape[-1])
    A64 = sym(A.to(torch.float64).reshape(-1, D, D))
    eye = torch.eye(D, dtype=torch.float64, device=A.device)
    finite = torch.isfinite(A64).all(-1).all(-1)
    if guard("cholesky.nonfinite", ~finite):
        A64 = torch.where(finite[:, None, None], A64, eye.expand_as(A64))
    scale = A64.diagonal(dim1=-2, dim2=-1).abs().mean(-1)
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    L, info = torch.linalg.cholesky_ex(A64)
    failed = info != 0
    n_failed = int(failed.sum())
    if n_failed:
        guard("cholesky.jitter", n_failed)
        L = L.clone()
        for j in jitters:
            idx = failed.nonzero().squeeze(1)
            Lj, infoj = torch.linalg.cholesky_ex(A64[idx] + (j * scale[idx])[:, None, None] * eye)
            ok = infoj == 0
            L[idx[ok]] = Lj[ok]
            failed[idx[ok]] = False
            if not bool(failed.any()):
                break
        if guard("cholesky.eig_fallback", failed):
            idx = failed.nonzero().squeeze(1)
            evals, evecs = torch.linalg.eigh(A64[idx])
            floor = (jitters[-1] if len(jitters) else 1e-3) * scale[idx]
            evals = torch.maximum(evals, floor[:, None])
            Af = sym(evecs @ torch.diag_embed(evals) @ evecs.transpose(-1, -2))
            Lf, infof = torch.linalg.cholesky_ex(Af)
            # last resort: diagonal factor (always valid)
            diag_L = torch.diag_embed(torch.sqrt(torch.maximum(Af.diagonal(dim1=-2, dim2=-1), floor[:, None])))
            Lf = torch.where((infof == 0)[:, None, None], Lf, diag_L)
            L[idx] = Lf
    return L.reshape(shape).to(dtype)
