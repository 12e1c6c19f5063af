"""Device helpers: move plugin state trees, synchronise before reading a clock, describe the machine."""
from __future__ import annotations

import platform
import time
from typing import Any

import torch


def move_tree(obj: Any, device: torch.device) -> Any:
    """``obj`` (nested dicts / lists of tensors) with every tensor on ``device`` (dtypes unchanged)."""
    if isinstance(obj, torch.Tensor):
        return obj.to(device)
    if isinstance(obj, dict):
        return {k: move_tree(v, device) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(move_tree(v, device) for v in obj)
    return obj


def synchronize(device: "torch.device | str | None" = None) -> None:
    """Wait for queued kernels on a CUDA device (a no-op on the CPU), so that a clock reads real time."""
    dev = torch.device(device) if device is not None else None
    if (dev is None or dev.type == "cuda") and torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.synchronize(dev)


def timed_clock(device: "torch.device | str | None" = None) -> float:
    """``time.perf_counter()`` after :func:`synchronize`."""
    synchronize(device)
    return time.perf_counter()


def randn(shape, *, generator: "torch.Generator | None" = None, dtype=torch.float32, device=None) -> torch.Tensor:
    """Standard normal draws made on ``generator``'s device and delivered on ``device`` (a CPU generator
    gives the same numbers whatever device the model is on)."""
    gdev = generator.device if generator is not None else device
    return torch.randn(shape, generator=generator, dtype=dtype, device=gdev).to(device)


def bernoulli(p: torch.Tensor, generator: "torch.Generator | None" = None) -> torch.Tensor:
    """Bernoulli(p) draws made on ``generator``'s device, returned on ``p``'s device."""
    gdev = generator.device if generator is not None else p.device
    return torch.bernoulli(p.to(gdev), generator=generator).to(p.device)


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo on Linux, else ``platform.processor()``; "" when neither says)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def machine_kind(m: dict) -> str:
    """A :func:`machine` record as one label: "CPU model (cpu_capability)", with the GPU after a comma when there is
    one (what decides whether training's bits reproduce)."""
    gpu = f", {m['cuda_device']}" if m.get("cuda_device") else ""
    return f"{m.get('cpu') or m.get('machine') or '?'} ({m.get('cpu_capability') or '?'}){gpu}"


def machine() -> dict:
    """Where a run or benchmark ran: Python, torch, threads, the CPU and the kernels torch dispatches to on it
    (``cpu_capability``: AVX2, AVX512, ...), and the GPU when CUDA is present. A seed reproduces a run bit for bit
    on the same kind of machine; torch's float32 kernels round differently across CPU kinds, so this says which."""
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {"python": platform.python_version(), "torch": torch.__version__, "threads": torch.get_num_threads(),
            "machine": platform.machine(), "processor": platform.processor(), "cpu": cpu_model(),
            "cpu_capability": torch.backends.cpu.get_cpu_capability(), "cuda_device": gpu}
