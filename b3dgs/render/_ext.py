"""JIT build / load of the C++ (OpenMP) extension: preprocessing, binning, rasterizer, SSIM loss, NIW draws.

The extension is compiled once with ``torch.utils.cpp_extension.load`` (ninja) into a per-user
cache directory keyed by a hash of the sources, the compiler flags and the torch version:
``$B3DGS_CACHE/<hash>`` if ``B3DGS_CACHE`` is set, else ``~/.cache/b3dgs/ext/<hash>``.
Concurrent builds from several processes are serialised with a lock (:mod:`b3dgs.locks`, released by the
kernel even if a process dies, unlike torch's file baton, whose stale lock files we clear while
holding our lock). Later processes import the built module directly without invoking ninja.
"""
from __future__ import annotations

import hashlib
import importlib.machinery
import importlib.util
import os
import re
import sys
import threading
import warnings
from pathlib import Path
from types import ModuleType
from typing import Optional

import torch

from b3dgs.errors import B3dgsError

_CSRC = Path(__file__).resolve().parent / "csrc"
_SOURCES = [_CSRC / "ext.cpp"]
_HASHED = [_CSRC / "ext.cpp", _CSRC / "kernels.h", _CSRC / "preprocess.h", _CSRC / "ssim.h", _CSRC / "sampling.h"]
# Portable flags: no -march=native, no -ffast-math (NaN semantics must hold). FMA contraction off
# so that float32 results track the pure-PyTorch backend as closely as possible.
_CFLAGS = ("-O3", "-fopenmp", "-fno-math-errno", "-ffp-contract=off")
# B3DGS_LANE_STATS=1: a separate build whose kernels count SIMD lane occupancy (bench/lanes.py); slower, never default
LANE_STATS_ENV = "B3DGS_LANE_STATS"


# B3DGS_FMA=1: a separate build whose tile kernels contract a*b + c into fused multiply-adds on CPUs with AVX2 + FMA
# (GCC target clone arch=x86-64-v3). Faster (bench/results/fma.md); results differ from the default build in the last
# bits, and between FMA and non-FMA machines, so it is opt-in: the default build gives the same bits on every x86 CPU.
FMA_ENV = "B3DGS_FMA"


def _cflags() -> tuple[str, ...]:
    flags = _CFLAGS
    if os.environ.get(FMA_ENV) == "1":
        flags = tuple(f for f in flags if not f.startswith("-ffp-contract")) + ("-ffp-contract=fast", "-DB3_FMA")
    return flags + (("-DB3_LANE_STATS",) if os.environ.get(LANE_STATS_ENV) == "1" else ())
_LDFLAGS = ("-fopenmp",)
HINT = "use renderer=torch (pure PyTorch backend)"


class RendererUnavailable(B3dgsError, RuntimeError):
    """The configured renderer (or the C++ extension) cannot run on this machine, with its fix; a RuntimeError too."""


_module: Optional[ModuleType] = None
_thread_lock = threading.Lock()


def _build_hash() -> str:
    h = hashlib.sha256()
    for src in _HASHED:
        h.update(src.name.encode())
        h.update(src.read_bytes())
    for text in (" ".join(_cflags() + _LDFLAGS), torch.__version__, sys.version, os.environ.get("CXX", "c++")):
        h.update(text.encode())  # CXX: the compiler torch's build uses
    return h.hexdigest()[:16]


def cache_dir() -> Path:
    """Build directory of the current sources, flags, compiler ($CXX) and torch version."""
    root = os.environ.get("B3DGS_CACHE")
    base = Path(root).expanduser() if root else Path.home() / ".cache" / "b3dgs" / "ext"
    return base / _build_hash()


def _import_built(path: Path, name: str) -> ModuleType:
    loader = importlib.machinery.ExtensionFileLoader(name, str(path))
    spec = importlib.util.spec_from_file_location(name, str(path), loader=loader)
    assert spec is not None
    mod = importlib.util.module_from_spec(spec)
    loader.exec_module(mod)
    return mod


#: the first build's time on this project's 2-core CPU (g++ -O3, ~50 s), said before it starts
BUILD_TIME = "about 1 minute"


def _build_locked(build_dir: Path, name: str, verbose: bool) -> ModuleType:
    from torch.utils import cpp_extension

    from b3dgs.locks import process_lock

    so_path = build_dir / f"{name}.so"
    with process_lock(build_dir / "b3dgs_build.lock"):  # blocks while another process builds
        if so_path.exists():
            return _import_built(so_path, name)
        (build_dir / "lock").unlink(missing_ok=True)  # torch FileBaton left over by a killed build
        # one line before a build (never a cached load): a first run is otherwise a silent pause
        sys.stderr.write(f"b3dgs: compiling the C++ CPU kernels once ({BUILD_TIME}; cached in {build_dir.parent})\n")
        sys.stderr.flush()
        return cpp_extension.load(
            name=name,
            sources=[str(s) for s in _SOURCES],
            extra_cflags=list(_cflags()),
            extra_ldflags=list(_LDFLAGS),
            build_directory=str(build_dir),
            verbose=verbose,
        )


def load_extension(verbose: bool = False) -> ModuleType:
    """Build (first time only) and load the C++ extension; :class:`RendererUnavailable` (a ``RuntimeError`` too)
    with the compiler's output and a fix on failure."""
    global _module
    if _module is not None:
        return _module
    with _thread_lock:
        if _module is not None:
            return _module
        try:
            name = "b3dgs_rasterize_" + _build_hash()
            build_dir = cache_dir()
            build_dir.mkdir(parents=True, exist_ok=True)
            # Imports directly if an earlier process already built it (checked under the lock,
            # so a half-linked .so is never imported).
            _module = _build_locked(build_dir, name, verbose)
        except Exception as e:  # noqa: BLE001 - compiler errors come as RuntimeError/OSError/...
            raise RendererUnavailable(f"could not build/load the C++ extension ({type(e).__name__}):\n{e}", HINT) from e
        return _module


_WARNED: set[str] = set()
_COMPILER_ERROR = re.compile(r"error:.*")


def first_compiler_error(message: str) -> str:
    """The first ``error:`` line of a failed build's output (or the message's first line)."""
    m = _COMPILER_ERROR.search(message)
    line = m.group(0) if m else (message.strip().splitlines() or ["unknown error"])[0]
    return line.strip()[:300]


def warn_fallback(error: Exception, fallback: str) -> None:
    """One warning per fallback naming the compiler error (a failed build is never silent)."""
    msg = f"b3dgs: the C++ extension did not build ({first_compiler_error(str(error))}); {fallback}"
    if msg not in _WARNED:
        _WARNED.add(msg)
        warnings.warn(msg, RuntimeWarning, stacklevel=3)
