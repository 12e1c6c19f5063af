"""Gaussian splat export/import in the standard 3D Gaussian Splatting PLY layout.

One ``vertex`` element, binary little-endian, all properties ``float`` (float32), in this order:

``x y z  nx ny nz  f_dc_0..2  f_rest_0..(3K-1)  opacity  scale_0..2  rot_0..3  <extras>``

* ``nx ny nz`` are zeros (the layout has them; nothing uses them);
* ``f_dc_*`` are the degree-0 SH coefficients per colour channel;
* ``f_rest_*`` are the remaining ``K`` SH coefficients, channel-major as in the reference 3DGS code:
  ``f_rest_{c*K + j}`` is coefficient ``j`` of colour channel ``c`` (``K = 15`` for SH degree 3);
* ``opacity`` is the pre-sigmoid logit, ``scale_*`` the log-scales, ``rot_*`` the quaternion ``w, x, y, z``
  (as stored, not normalised);
* extras follow as float32: a ``(N,)`` extra ``name`` becomes property ``name``, a ``(N, d)`` extra
  becomes ``name_0 .. name_{d-1}``.

:func:`read_ply` reverses this. Any vertex property outside the standard set is returned as an extra,
``name_0 .. name_{d-1}`` (indices contiguous from 0, no plain ``name`` alongside) regrouped into an
``(N, d)`` tensor; so a ``(N, 1)`` extra comes back as ``(N, 1)``.

:func:`write_splats` writes a model's Gaussians in a scene's own frame: :func:`transform_gaussians` maps the
centres by a similarity ``x -> s R x + t``, adds ``log s`` to the log-scales and turns the quaternions by ``R``.
"""
from __future__ import annotations

import os
import re
from collections import OrderedDict
from pathlib import Path
from typing import Mapping, Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from b3dgs.errors import B3dgsError
from b3dgs.io import atomic_path

__all__ = ["frame_comments", "write_ply", "read_ply", "standard_property_names", "transform_gaussians", "write_splats"]

_BASE_BEFORE = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
_BASE_AFTER = ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_REST_RE = re.compile(r"^f_rest_(\d+)$")
_INDEXED_RE = re.compile(r"^(.+)_(\d+)$")


def standard_property_names(num_rest: int) -> list[str]:
    """The standard property names for ``num_rest`` SH rest coefficients per channel (K)."""
    return _BASE_BEFORE + [f"f_rest_{i}" for i in range(3 * num_rest)] + _BASE_AFTER


def _as_f32(name: str, x, shape: tuple) -> np.ndarray:
    """Convert to a float32 numpy array and check the shape (-1 entries are free, checked by caller)."""
    if isinstance(x, Tensor):
        x = x.detach().cpu()
        if x.dtype == torch.bfloat16:
            x = x.float()
        x = x.numpy()
    a = np.asarray(x, dtype=np.float32)
    if a.ndim != len(shape) or any(s != -1 and s != t for s, t in zip(shape, a.shape)):
        want = "(" + ", ".join("N" if i == 0 else ("K" if s == -1 else str(s)) for i, s in enumerate(shape)) + ")"
        raise B3dgsError(f"write_ply: {name} must have shape {want}, got {tuple(a.shape)}",
                         fix=f"pass {name} with one row per Gaussian, shape {want} (N = number of Gaussians, the "
                             "same for every array)")
    if not np.isfinite(a).all():
        raise B3dgsError(f"write_ply: {name} contains NaN or Inf",
                         fix=f"pass finite values; a model with NaN/Inf {name} diverged in training: lower the "
                             "learning rates (e.g. model.lr_means) and retrain")
    return a


def write_ply(path: str | os.PathLike, means: Tensor, scales_log: Tensor, quats: Tensor, opacity_logit: Tensor,
              sh0: Tensor, shN: Optional[Tensor] = None, extra: Optional[Mapping[str, Tensor]] = None,
              comments: Sequence[str] = ()) -> Path:
    """Write Gaussians to ``path`` (atomically) in the standard 3DGS PLY layout; return the path.

    Shapes: ``means`` (N, 3); ``scales_log`` (N, 3); ``quats`` (N, 4) as w, x, y, z; ``opacity_logit``
    (N,) (an (N, 1) tensor is accepted); ``sh0`` (N, 3) DC coefficients ((N, 1, 3) accepted); ``shN``
    (N, K, 3) rest coefficients, K >= 0 (None means K = 0); ``extra``: name -> (N,) or (N, d) values.
    All values must be finite; they are stored as float32. Tensors may require grad (they are detached).
    ``comments``: header comment lines (readers skip them).
    """
    m = _as_f32("means", means, (-1, 3))
    n = m.shape[0]
    s = _as_f32("scales_log", scales_log, (n, 3))
    q = _as_f32("quats", quats, (n, 4))
    o = opacity_logit
    if isinstance(o, (Tensor, np.ndarray)) and o.ndim == 2 and o.shape[1] == 1:
        o = o[:, 0]
    o = _as_f32("opacity_logit", o, (n,))
    d = sh0
    if isinstance(d, (Tensor, np.ndarray)) and d.ndim == 3 and d.shape[1] == 1:
        d = d[:, 0]
    d = _as_f32("sh0", d, (n, 3))
    r = np.zeros((n, 0, 3), np.float32) if shN is None else _as_f32("shN", shN, (n, -1, 3))
    k = r.shape[1]

    names = standard_property_names(k)
    columns: list[np.ndarray] = [m, np.zeros((n, 3), np.float32), d,
                                 r.transpose(0, 2, 1).reshape(n, 3 * k),  # channel-major: c*K + j
                                 o[:, None], s, q]
    for key, val in (extra or {}).items():
        if not isinstance(key, str) or not _NAME_RE.match(key):
            raise B3dgsError(f"write_ply: extra name {key!r} is not a valid PLY property name",
                             fix="name each extra property with letters, digits and _ only, not starting with a "
                                 "digit (e.g. 'mu_var')")
        ndim = val.ndim if hasattr(val, "ndim") else np.ndim(val)
        if ndim == 1:
            a = _as_f32(f"extra[{key!r}]", val, (n,))
            names.append(key)
            columns.append(a[:, None])
        elif ndim == 2:
            a = _as_f32(f"extra[{key!r}]", val, (n, -1))
            names.extend(f"{key}_{i}" for i in range(a.shape[1]))
            columns.append(a)
        else:
            raise B3dgsError(f"write_ply: extra[{key!r}] must have shape (N,) or (N, d), got {tuple(np.shape(val))}",
                             fix=f"pass extra[{key!r}] with one row per Gaussian: shape (N,) or (N, d)")
    twice = [nm for i, nm in enumerate(names) if nm in names[:i]]
    if twice:
        raise B3dgsError(f"write_ply: property name {twice[0]!r} would appear twice (extra names clash)",
                         fix="rename the extra property so it differs from the 3DGS fields (x, opacity, f_dc_0, ...) "
                             "and from the other extras")

    from plyfile import PlyData, PlyElement

    data = np.concatenate(columns, axis=1) if n else np.zeros((0, len(names)), np.float32)
    data = np.ascontiguousarray(data, dtype="<f4")
    assert data.shape[1] == len(names)
    vertex = data.view(np.dtype([(nm, "<f4") for nm in names])).reshape(n)
    path = Path(path)
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(vertex, "vertex")], text=False, byte_order="<",
                comments=[" ".join(str(c).split()) for c in comments]).write(str(tmp))
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; an export is meant to be shared
    return path


def read_ply(path: str | os.PathLike) -> dict:
    """Read a standard 3DGS PLY file (any PLY encoding plyfile reads).

    Returns ``{"means", "scales_log", "quats", "opacity_logit", "sh0", "shN", "extra"}`` with float32
    tensors shaped as :func:`write_ply` takes them (``shN`` is (N, K, 3), K = 0 when there are no
    ``f_rest_*``) and ``extra`` a dict name -> (N,) or (N, d). Raises :class:`B3dgsError` (a ``ValueError``)
    naming the problem for a missing, malformed, truncated or incomplete file or non-finite values.
    """
    from plyfile import PlyData, PlyParseError

    path = Path(path)
    if not path.is_file():
        raise B3dgsError(f"PLY file {path} does not exist", "pass the path of an existing .ply file (a run's point_cloud.ply)")
    try:
        with open(path, "rb") as f:
            ply = PlyData.read(f, mmap=False)
    except PlyParseError as e:
        raise B3dgsError(f"{path}: not a readable PLY file ({e})",
                         fix="pass a binary or ASCII PLY file (e.g. a run's point_cloud.ply), or re-export it "
                             "with b3dgs-export") from e
    except (ValueError, EOFError, UnicodeDecodeError, OSError) as e:
        raise B3dgsError(f"{path}: not a readable PLY file (corrupt or truncated: {e})",
                         fix="pass a complete PLY file: re-export it with b3dgs-export, or copy it again if "
                             "the transfer was cut short") from e
    try:
        vertex = ply["vertex"]
    except KeyError:
        raise B3dgsError(f"{path}: PLY file has no 'vertex' element",
                         fix="pass a PLY of Gaussians with a 'vertex' element (a 3DGS point_cloud.ply, as "
                             "b3dgs-export writes)") from None
    arr = vertex.data
    props = list(arr.dtype.names or ())
    for p in props:
        if arr.dtype[p].subdtype is not None or arr.dtype[p].kind not in "fiub":
            raise B3dgsError(f"{path}: vertex property {p!r} is a list or non-numeric; expected scalars",
                             fix="pass a 3DGS-layout PLY whose vertex properties are scalar floats (as b3dgs-export "
                                 "writes), not a mesh")

    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"] + _BASE_AFTER
    for p in required:
        if p not in props:
            raise B3dgsError(f"{path}: PLY file lacks vertex property {p!r} required by the 3DGS layout",
                             fix="pass a 3DGS-layout PLY (x, y, z, f_dc_0..2, opacity, scale_0..2, rot_0..3, as "
                                 f"b3dgs-export writes); {p!r} is missing")
    rest_idx = sorted(int(mt.group(1)) for p in props if (mt := _REST_RE.match(p)))
    if rest_idx != list(range(len(rest_idx))):
        missing = sorted(set(range(max(rest_idx) + 1)) - set(rest_idx))
        raise B3dgsError(f"{path}: PLY file lacks vertex property 'f_rest_{missing[0]}' (f_rest_* must be contiguous)",
                         fix="pass a 3DGS-layout PLY whose f_rest_0 .. f_rest_{3K-1} are all present (as "
                             "b3dgs-export writes)")
    if len(rest_idx) % 3:
        raise B3dgsError(f"{path}: {len(rest_idx)} f_rest_* properties, not a multiple of 3 colour channels",
                         fix="pass a 3DGS-layout PLY with 0, 9, 24 or 45 f_rest_* properties (SH degree 0-3, three "
                             "colour channels)")
    k = len(rest_idx) // 3
    n = len(arr)

    def cols(names: list[str]) -> np.ndarray:
        if not names:
            return np.zeros((n, 0), np.float32)
        return np.stack([np.asarray(arr[nm], dtype=np.float32) for nm in names], axis=1)

    out = {"means": cols(["x", "y", "z"]), "scales_log": cols(["scale_0", "scale_1", "scale_2"]),
           "quats": cols(["rot_0", "rot_1", "rot_2", "rot_3"]), "opacity_logit": cols(["opacity"])[:, 0],
           "sh0": cols(["f_dc_0", "f_dc_1", "f_dc_2"]),
           "shN": cols([f"f_rest_{i}" for i in range(3 * k)]).reshape(n, 3, k).transpose(0, 2, 1)}

    standard = set(standard_property_names(k))
    others = [p for p in props if p not in standard]
    groups: "OrderedDict[str, list[tuple[int, str]]]" = OrderedDict()
    for p in others:
        mt = _INDEXED_RE.match(p)
        key = mt.group(1) if mt else p
        groups.setdefault(key, []).append((int(mt.group(2)) if mt else -1, p))
    extra: dict[str, np.ndarray] = OrderedDict()
    for key, members in groups.items():
        idx = sorted(i for i, _ in members)
        if key not in others and idx == list(range(len(idx))):
            extra[key] = cols([f"{key}_{i}" for i in idx])
        else:  # not a clean name_0..name_{d-1} group: keep each property as it is
            for _, p in members:
                extra[p] = cols([p])[:, 0]

    for name, a in list(out.items()) + [(f"extra[{k!r}]", v) for k, v in extra.items()]:
        if not np.isfinite(a).all():
            bad = int((~np.isfinite(a)).reshape(n, -1).any(axis=1).sum()) if n else 0
            raise B3dgsError(f"{path}: {name} has non-finite values in {bad} of {n} vertices",
                             fix="pass a PLY with finite values only; re-export the run with b3dgs-export, or drop "
                                 "those vertices first")

    result = {key: torch.from_numpy(np.ascontiguousarray(v)) for key, v in out.items()}
    result["extra"] = {key: torch.from_numpy(np.ascontiguousarray(v)) for key, v in extra.items()}
    return result


def _quat_of(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix (the largest-component branch, stable everywhere)."""
    m = R
    w2 = np.array([1 + m[0, 0] + m[1, 1] + m[2, 2], 1 + m[0, 0] - m[1, 1] - m[2, 2],
                   1 - m[0, 0] + m[1, 1] - m[2, 2], 1 - m[0, 0] - m[1, 1] + m[2, 2]])
    i = int(np.argmax(w2))
    r = 0.5 * np.sqrt(max(w2[i], 1e-300))
    q = {0: [r, (m[2, 1] - m[1, 2]) / (4 * r), (m[0, 2] - m[2, 0]) / (4 * r), (m[1, 0] - m[0, 1]) / (4 * r)],
         1: [(m[2, 1] - m[1, 2]) / (4 * r), r, (m[0, 1] + m[1, 0]) / (4 * r), (m[0, 2] + m[2, 0]) / (4 * r)],
         2: [(m[0, 2] - m[2, 0]) / (4 * r), (m[0, 1] + m[1, 0]) / (4 * r), r, (m[1, 2] + m[2, 1]) / (4 * r)],
         3: [(m[1, 0] - m[0, 1]) / (4 * r), (m[0, 2] + m[2, 0]) / (4 * r), (m[1, 2] + m[2, 1]) / (4 * r), r]}[i]
    return np.asarray(q) / np.linalg.norm(q)


def transform_gaussians(means: Tensor, scales_log: Tensor, quats: Tensor, scale: float, rotation=None,
                        translation=None) -> tuple[Tensor, Tensor, Tensor]:
    """(means, scales_log, quats) of Gaussians under ``x -> scale * rotation @ x + translation``: centres mapped,
    ``log(scale)`` added to every log-scale, each quaternion (w, x, y, z) left-multiplied by ``rotation``'s (its
    covariance becomes ``s² R Σ Rᵀ``). Computed in float64, returned in the input dtype."""
    if not (scale > 0 and np.isfinite(scale)):
        raise B3dgsError(f"transform_gaussians: scale must be a positive finite number, got {scale}",
                         fix="pass scale > 0 and finite (1.0 keeps the size)")
    R = np.eye(3) if rotation is None else np.asarray(rotation, np.float64)
    t = np.zeros(3) if translation is None else np.asarray(translation, np.float64)
    dt = means.dtype
    m = means.detach().double().cpu()
    out_means = float(scale) * m @ torch.from_numpy(R).T + torch.from_numpy(t)
    out_scales = scales_log.detach().double().cpu() + float(np.log(scale))
    q = quats.detach().double().cpu()
    if not np.allclose(R, np.eye(3), atol=1e-12):
        a = torch.from_numpy(_quat_of(R))
        w0, x0, y0, z0 = a
        w1, x1, y1, z1 = q.unbind(-1)
        q = torch.stack([w0 * w1 - x0 * x1 - y0 * y1 - z0 * z1, w0 * x1 + x0 * w1 + y0 * z1 - z0 * y1,
                         w0 * y1 - x0 * z1 + y0 * w1 + z0 * x1, w0 * z1 + x0 * y1 - y0 * x1 + z0 * w1], -1)
    return out_means.to(dt), out_scales.to(dt), q.to(quats.dtype)


def write_splats(path: str | os.PathLike, splats: Mapping[str, Tensor], transform=None,
                 extra: Optional[Mapping[str, Tensor]] = None, comments: Sequence[str] = ()) -> Path:
    """Write a model's Gaussians (``splats``: means, scales, quats, opacities, sh0 (N, 1, 3), shN) with
    :func:`write_ply`, mapped by ``transform`` first when given: an object with ``scale``, ``rotation`` and
    ``translation`` taking the model's frame to the PLY's (e.g. ``scene.transform.inverse()``, back to the
    COLMAP / transforms.json frame). A rotation other than the identity is refused for view-dependent colour
    (``shN`` with K > 0 would need its SH coefficients rotated too)."""
    means, scales, quats = splats["means"], splats["scales"], splats["quats"]
    shN = splats["shN"]
    if transform is not None:
        rot = np.asarray(transform.rotation, np.float64)
        if shN.shape[1] and not np.allclose(rot, np.eye(3), atol=1e-12):
            raise B3dgsError("write_splats: a rotating transform would need the f_rest_* SH coefficients rotated too",
                             fix="pass a transform whose rotation is the identity (scale and translation only), or "
                                 "splats with an empty shN (SH degree 0)")
        means, scales, quats = transform_gaussians(means, scales, quats, float(transform.scale), rot,
                                                   transform.translation)
    return write_ply(path, means, scales, quats, splats["opacities"], splats["sh0"][:, 0], shN, extra=extra,
                     comments=comments)


def frame_comments(frame) -> list[str]:
    """Header comments of a PLY written in a scene's own frame: the training frame's transform ``frame`` (scale,
    translation) and that posterior extras keep the training frame's units."""
    from b3dgs import __version__

    t = ", ".join(f"{v:.9g}" for v in frame.translation)
    return [f"b3dgs {__version__}: x y z scale_* rot_* in the scene's own frame (COLMAP / transforms.json); "
            f"training frame x_norm = {float(frame.scale):.9g} * R x + ({t})",
            "b3dgs: extra properties (posterior summaries) are in the training frame's units"]
