"""Count the operations of a training step that force a device→host round-trip on a GPU, per scope.

On CUDA every ``Tensor.item``, ``.tolist``/``.cpu``/``.numpy``, ``nonzero``, boolean-mask indexing and other
data-dependent shapes wait for the GPU's queue to drain. Counting them needs no GPU:

* :class:`HostSyncCounter` (any device) counts them at torch's hooks: a ``TorchDispatchMode`` sees
  ``aten._local_scalar_dense`` (``item``/``bool``/``float``), ``aten.nonzero``, boolean indexing and the other
  data-dependent ops, a ``TorchFunctionMode`` sees ``tolist``, ``numpy`` and ``cpu``. On the CPU every tensor stands
  for one on the device, so the count is what the step would pay there.
* :class:`CudaSyncCounter` counts what the GPU really synchronises (``torch.cuda.set_sync_debug_mode("warn")``).

Both attribute each event to the innermost :func:`scope` open (``core``, ``render``, a plugin's name, ``loop``);
``scope`` costs one global read when no counter is installed. :class:`HostSyncCallback`
(``+callbacks.host_sync._target_=b3dgs.host_sync.HostSyncCallback``) counts a whole run and writes, per step, the count
of each scope and the plugins' periodic work (:meth:`b3dgs.plugin.Plugin.periodic`) to JSON (``bench/host_syncs.py``).
"""
from __future__ import annotations

import contextlib
import warnings
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any, Iterator, Optional

import lightning as L
import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode

from b3dgs.errors import B3dgsError
from b3dgs.io import write_json

__all__ = ["scope", "HostSyncCounter", "CudaSyncCounter", "HostSyncCallback"]

_aten = torch.ops.aten
#: aten ops whose output shape depends on the data, or that read a value back to the host (always a sync on CUDA)
_SYNC_OPS = {_aten._local_scalar_dense.default: "item", _aten.nonzero.default: "nonzero",
             _aten.masked_select.default: "masked_select", _aten.unique_consecutive.default: "unique",
             _aten._unique2.default: "unique", _aten.unique_dim.default: "unique", _aten.bincount.default: "bincount",
             _aten.masked_scatter.default: "masked_scatter", _aten.equal.default: "equal",
             _aten._assert_async.msg: "assert"}
_HOST_COPIES = {"tolist", "numpy", "cpu"}

_STACK: list[str] = []
_COUNTER: Optional["_Counting"] = None


@contextlib.contextmanager
def _scope(name: str) -> Iterator[None]:
    _STACK.append(name)
    try:
        yield
    finally:
        _STACK.pop()


_NULL = contextlib.nullcontext()


def scope(name: str):
    """Attribute the host syncs inside to ``name`` (innermost wins); under ``torch.profiler`` also a
    ``record_function("b3dgs::<name>")`` range; a no-op context otherwise."""
    if _COUNTER is not None:
        return _scope(name)
    if torch.autograd.profiler._is_profiler_enabled:  # noqa: SLF001 - torch's own flag, set while a profiler runs
        return torch.profiler.record_function(f"b3dgs::{name}")
    return _NULL


def _has_bool_index(indices) -> bool:
    return any(isinstance(t, torch.Tensor) and t.dtype in (torch.bool, torch.uint8) for t in (indices or ()))


class _Counting:
    """Per-step, per-scope counts; ``events`` keeps the first few (scope, kind) with a short stack for the report."""

    def __init__(self, keep_stacks: int = 0) -> None:
        self.step: Optional[int] = None
        self.counts: dict[int, Counter] = defaultdict(Counter)  # step -> Counter[scope]
        self.kinds: dict[str, Counter] = defaultdict(Counter)  # scope -> Counter[kind]
        self.sites: dict[str, Counter] = defaultdict(Counter)  # scope -> Counter["file:line fn (kind)"]
        self.keep_stacks = keep_stacks

    def record(self, kind: str, site: Optional[str] = None) -> None:
        where = _STACK[-1] if _STACK else "outside"
        key = -1 if self.step is None else self.step
        self.counts[key][where] += 1
        self.kinds[where][kind] += 1
        if self.keep_stacks:
            self.sites[where][f"{site or _site()} ({kind})"] += 1

    def per_step(self) -> dict[int, dict[str, int]]:
        return {s: dict(c) for s, c in sorted(self.counts.items())}

    def install(self) -> "_Counting":
        """Start counting (one counter at a time)."""
        global _COUNTER
        if _COUNTER is not None:
            raise B3dgsError("a host-sync counter is already installed: one counts at a time", "add one "
                             "HostSyncCallback (+callbacks.host_sync._target_=b3dgs.host_sync.HostSyncCallback), or "
                             "remove the counter installed first")
        self._start()
        _COUNTER = self
        return self

    def remove(self) -> None:
        global _COUNTER
        self._stop()
        _COUNTER = None

    __enter__ = install

    def __exit__(self, *exc) -> None:
        self.remove()


def _site() -> str:
    """The innermost frame outside torch and this module: where the sync was asked for."""
    import sys

    f = sys._getframe(2)
    while f is not None:
        fn = f.f_code.co_filename
        if "/torch/" not in fn and fn != __file__ and "contextlib" not in fn:
            return f"{'/'.join(Path(fn).parts[-2:])}:{f.f_lineno} {f.f_code.co_name}"
        f = f.f_back
    return "?"


class _DispatchCounter(TorchDispatchMode):
    def __init__(self, sink: _Counting) -> None:
        super().__init__()
        self.sink = sink

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        kind = _SYNC_OPS.get(func)
        if kind is None:
            if func in (_aten.index.Tensor, _aten.index_put.default, _aten.index_put_.default,
                        _aten._index_put_impl_.default) and _has_bool_index(args[1] if len(args) > 1 else None):
                kind = "bool_index"
            elif func is _aten.repeat_interleave.Tensor and kwargs.get("output_size") is None:
                kind = "repeat_interleave"
        if kind is not None:
            self.sink.record(kind)
        return func(*args, **kwargs)


class _FunctionCounter(TorchFunctionMode):
    def __init__(self, sink: _Counting) -> None:
        super().__init__()
        self.sink = sink

    def __torch_function__(self, func, types, args=(), kwargs=None):
        name = getattr(func, "__name__", "")
        if name in _HOST_COPIES and args and isinstance(args[0], torch.Tensor):
            self.sink.record(name)
        return func(*args, **(kwargs or {}))


class HostSyncCounter(_Counting):
    """Counts host syncs at torch's hooks (see the module docstring); use as a context manager or ``install``/``remove``."""

    _modes: list = []

    def _start(self) -> None:
        self._modes = [_FunctionCounter(self), _DispatchCounter(self)]
        for m in self._modes:
            m.__enter__()

    def _stop(self) -> None:
        for m in reversed(self._modes):
            m.__exit__(None, None, None)
        self._modes = []


class CudaSyncCounter(_Counting):
    """Counts the synchronisations the CUDA runtime really performs (``torch.cuda.set_sync_debug_mode("warn")``)."""

    _catch = None

    def _start(self) -> None:
        self._catch = warnings.catch_warnings()
        self._catch.__enter__()
        warnings.simplefilter("always")
        orig = warnings.showwarning

        def show(message, category, filename, lineno, file=None, line=None):
            if "synchronizing" in str(message):  # c10's "called a synchronizing CUDA operation"
                # the warning's own location: the Python line that asked for the sync (not this handler's frame)
                self.record("cuda_sync", f"{'/'.join(Path(filename).parts[-2:])}:{lineno}")
            else:
                orig(message, category, filename, lineno, file, line)

        warnings.showwarning = show
        torch.cuda.set_sync_debug_mode("warn")

    def _stop(self) -> None:
        torch.cuda.set_sync_debug_mode("default")
        if self._catch is not None:
            self._catch.__exit__(None, None, None)
            self._catch = None


class HostSyncCallback(L.Callback):
    """Count host syncs over a training run and write them to ``out`` (JSON): per step, the count of each scope and the
    periodic work the plugins declared. ``backend``: ``auto`` (CUDA's own count on a CUDA model, else the op-level
    counter), ``ops`` or ``cuda``. ``keep_stacks``: also record the file:line of each sync (slower). ``device_path``:
    run the device path (no host reads per step) on CPU tensors; a GPU run takes it anyway."""

    def __init__(self, out: str = "host_syncs.json", backend: str = "auto", keep_stacks: bool = True,
                 max_steps: Optional[int] = None, device_path: bool = False) -> None:
        super().__init__()
        if backend not in ("auto", "ops", "cuda"):
            raise B3dgsError(f"host_sync backend={backend} is not one of auto|ops|cuda",
                             "pass +callbacks.host_sync.backend=auto (CUDA's own count on a CUDA model), ops or cuda")
        self.out, self.backend, self.keep_stacks, self.max_steps = out, backend, keep_stacks, max_steps
        self.device_path = device_path
        self._forced = None
        self.counter: Optional[_Counting] = None
        self.periodic: dict[int, list[str]] = {}
        self._loop = None

    def on_train_start(self, trainer, pl_module) -> None:
        cuda = pl_module.device.type == "cuda"
        use_cuda = self.backend == "cuda" or (self.backend == "auto" and cuda)
        self.counter = (CudaSyncCounter if use_cuda else HostSyncCounter)(keep_stacks=int(self.keep_stacks))
        if self.device_path:  # count what a GPU run would do, on CPU tensors (b3dgs.numerics.forced_device_path)
            from b3dgs.numerics import forced_device_path

            self._forced = forced_device_path()
            self._forced.__enter__()
        self.counter.install()
        self._loop = _scope("loop")
        self._loop.__enter__()

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        if self.counter is None:
            return
        step = int(pl_module.global_step)
        if self.max_steps is not None and step >= self.max_steps:
            self._stop()
            return
        self.counter.step = step
        info = pl_module._static_info()
        work = {w for p in pl_module.plugins.values() for w in p.periodic(step, info)}
        if step % max(int(trainer.log_every_n_steps), 1) == 0:
            work.add("log")  # the core's own periodic reads (metrics logging, the deferred finiteness check)
        self.periodic[step] = sorted(work)

    def _stop(self) -> None:
        if self.counter is None:
            return
        if self._loop is not None:
            self._loop.__exit__(None, None, None)
            self._loop = None
        self.counter.remove()
        if self._forced is not None:
            self._forced.__exit__(None, None, None)
            self._forced = None
        self.write()
        self.counter = None

    def on_train_end(self, trainer, pl_module) -> None:
        self._stop()

    def on_exception(self, trainer, pl_module, exception) -> None:
        self._stop()

    def result(self) -> dict[str, Any]:
        c = self.counter
        return {"backend": type(c).__name__, "per_step": {str(k): v for k, v in c.per_step().items()},
                "periodic": {str(k): v for k, v in self.periodic.items()},
                "kinds": {k: dict(v) for k, v in c.kinds.items()},
                "sites": {k: dict(v.most_common(40)) for k, v in c.sites.items()}}

    def write(self) -> None:
        path = Path(self.out)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_json(path, self.result())


def summarise(result: dict[str, Any]) -> dict[str, dict[str, float]]:
    """Mean syncs per step of each kind of step (``ordinary``: no periodic work declared; else the declared work joined
    by ``+``), per scope; ``steps`` is how many steps of that kind were counted."""
    rows: dict[str, Counter] = defaultdict(Counter)
    nsteps: Counter = Counter()
    for step, work in result["periodic"].items():  # every counted step, also those without a sync
        kind = "+".join(work) or "ordinary"
        nsteps[kind] += 1
        rows[kind].update(result["per_step"].get(step, {}))
    return {k: {"steps": nsteps[k], **{s: rows[k][s] / nsteps[k] for s in sorted(rows[k])}} for k in sorted(nsteps)}
