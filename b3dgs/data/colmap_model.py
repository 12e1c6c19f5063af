"""COLMAP's sparse model (``cameras``, ``images``, ``points3D``; ``.bin`` or ``.txt``) read with NumPy and
:mod:`struct`: what :mod:`b3dgs.data.colmap` loads, without pycolmap.

The formats, as COLMAP writes and reads them (``src/colmap/scene/reconstruction_io_{binary,text}.cc``):

- ``cameras.bin``: uint64 count; per camera uint32 id, int32 model id, uint64 width, height, then the model's
  float64 parameters (:data:`CAMERA_MODELS`). ``cameras.txt``: ``ID MODEL_NAME WIDTH HEIGHT PARAMS...``.
- ``images.bin``: uint64 count; per image uint32 id, float64 ``qw qx qy qz tx ty tz`` (``cam_from_world``: the
  rotation as a unit quaternion, then the translation), uint32 camera id, the name ending in NUL, uint64 count of 2D
  points, then per point float64 x, y and uint64 3D point id (2^64 - 1: none). ``images.txt``: two lines per image,
  ``ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` and ``X Y POINT3D_ID ...`` (-1: none; the line may be empty).
- ``points3D.bin``: uint64 count; per point uint64 id, float64 x, y, z, uint8 r, g, b, float64 error, uint64 track
  length, then per element uint32 image id, uint32 2D point index. ``points3D.txt``:
  ``ID X Y Z R G B ERROR IMAGE_ID POINT2D_IDX ...``.

Binary files are little-endian; text lines starting with ``#`` and empty lines are skipped (except an image's 2D
point line, which may be empty). COLMAP 3.12+ also writes ``rigs`` and ``frames``; ``images`` keeps its format and
each image's pose in it is the camera's ``cam_from_world`` (for a rig, the rig pose composed with the sensor's), so
those two files are not read. Both files list registered images only: an image without a pose cannot appear.

One pass parses and checks: every binary record is bounds-checked and a file must end right after its last record,
text lines must have the fields their kind needs, ids are unique, each image's camera exists, and each track names an
existing image and one of its 2D points. Each problem is one :class:`~b3dgs.errors.B3dgsError` line naming the file
(and the line of a text file).
"""
from __future__ import annotations

import mmap
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Optional

import numpy as np

from b3dgs.errors import B3dgsError

#: COLMAP model id -> (name, number of parameters) (``src/colmap/sensor/models.h``)
CAMERA_MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5), 4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5), 8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12), 11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
    12: ("SIMPLE_DIVISION", 4), 13: ("DIVISION", 5), 14: ("SIMPLE_FISHEYE", 3), 15: ("FISHEYE", 4), 16: ("EUCM", 6),
    17: ("EQUIRECTANGULAR", 2),
}
MODEL_IDS = {name: mid for mid, (name, _) in CAMERA_MODELS.items()}
FILES = ("cameras", "images", "points3D")
_FIX = "re-export the model (e.g. `colmap model_converter --output_type BIN`) or restore the file"
_POINT2D = np.dtype([("xy", "<f8", (2,)), ("id", "<u8")])
_TRACK = np.dtype([("image_id", "<u4"), ("point2d", "<u4")])

__all__ = ["CAMERA_MODELS", "ColmapCamera", "ColmapImage", "ColmapModel", "model_format", "qvec_to_rotmat",
           "read_model", "unordered_map_order"]


@dataclass(frozen=True)
class ColmapCamera:
    """One camera: ``model`` is COLMAP's name (:data:`CAMERA_MODELS`), ``params`` its float64 parameters."""

    id: int
    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass(frozen=True)
class ColmapImage:
    """One registered image: ``qvec`` (qw, qx, qy, qz) and ``tvec`` are its world-to-camera pose; ``xys`` (N, 2) its
    2D points and ``point3d_ids`` (N,) the 3D point each one observes (-1: none)."""

    id: int
    qvec: np.ndarray
    tvec: np.ndarray
    camera_id: int
    name: str
    xys: np.ndarray
    point3d_ids: np.ndarray

    def viewmat(self) -> np.ndarray:
        """(4, 4) float64 world-to-camera (OpenCV axes): rotation :func:`qvec_to_rotmat`, translation ``tvec``."""
        out = np.eye(4)
        out[:3, :3] = qvec_to_rotmat(self.qvec)
        out[:3, 3] = self.tvec
        return out


@dataclass(frozen=True)
class ColmapModel:
    """A parsed model: cameras and images by id (file order); 3D points as arrays in file order, the track of point
    ``i`` being ``track[track_start[i]:track_start[i + 1]]`` (fields ``image_id``, ``point2d``)."""

    path: Path
    cameras: dict[int, ColmapCamera]
    images: dict[int, ColmapImage]
    point_ids: np.ndarray  # (M,) uint64
    xyz: np.ndarray  # (M, 3) float64
    rgb: np.ndarray  # (M, 3) uint8
    error: np.ndarray  # (M,) float64
    track_start: np.ndarray  # (M + 1,) int64
    track: np.ndarray  # (T,) _TRACK


def qvec_to_rotmat(q) -> np.ndarray:
    """(3, 3) rotation of the unit quaternion ``(w, x, y, z)``, computed term by term as Eigen's
    ``Quaternion::toRotationMatrix`` does, so that it equals pycolmap's ``cam_from_world().matrix()`` bit for bit."""
    w, x, y, z = (float(v) for v in q)
    tx, ty, tz = 2.0 * x, 2.0 * y, 2.0 * z
    twx, twy, twz = tx * w, ty * w, tz * w
    txx, txy, txz = tx * x, ty * x, tz * x
    tyy, tyz, tzz = ty * y, tz * y, tz * z
    return np.array([[1.0 - (tyy + tzz), txy - twz, txz + twy],
                     [txy + twz, 1.0 - (txx + tzz), tyz - twx],
                     [txz - twy, tyz + twx, 1.0 - (txx + tyy)]])


# ------------------------------------------------------------------------------------- binary files


class _Reader:
    """Bounds-checked little-endian reads from a memory-mapped file (no read past its end)."""

    def __init__(self, path: Path, buf):
        self.path, self.buf, self.pos = path, buf, 0

    def remaining(self) -> int:
        return len(self.buf) - self.pos

    def bad(self, what: str) -> B3dgsError:
        return B3dgsError(f"COLMAP file {self.path} is damaged: {what} (at byte {self.pos} of {len(self.buf)})", _FIX)

    def take(self, size: int, what: str) -> int:
        """The position of the next ``size`` bytes, which the reader moves past."""
        if size > self.remaining():
            raise self.bad(f"truncated inside {what}")
        self.pos += size
        return self.pos - size

    def unpack(self, st: struct.Struct, what: str) -> tuple:
        return st.unpack_from(self.buf, self.take(st.size, what))

    def array(self, dtype: np.dtype, n: int, what: str) -> np.ndarray:  # a copy: the map is closed after
        return np.frombuffer(self.buf, dtype=dtype, count=n, offset=self.take(n * dtype.itemsize, what)).copy()

    def count(self, min_record: int, what: str) -> int:
        (n,) = self.unpack(_U64, f"the {what} count")
        if n * min_record > self.remaining():
            raise self.bad(f"header says {n} {what} but only {self.remaining()} bytes follow "
                           f"(at least {min_record} per record): truncated")
        return n

    def name(self, what: str) -> str:
        end = self.buf.find(b"\0", self.pos)
        if end < 0:
            raise self.bad(f"unterminated name in {what}")
        raw, self.pos = self.buf[self.pos:end], end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise self.bad(f"the name of {what} is not UTF-8") from None

    def done(self) -> None:
        if self.remaining():
            raise self.bad(f"{self.remaining()} unexpected bytes after the last record")


_U64 = struct.Struct("<Q")
_CAMERA = struct.Struct("<IiQQ")
_IMAGE = struct.Struct("<I7dI")
_POINT = np.dtype([("id", "<u8"), ("xyz", "<f8", (3,)), ("rgb", "u1", (3,)), ("error", "<f8")])  # 43 bytes, packed
_POINT_SIZE = _POINT.itemsize + 8  # and the track length


def _read_binary(path: Path, parse: Callable[[_Reader], object]):
    size = path.stat().st_size
    if size < 8:
        raise B3dgsError(f"COLMAP file {path} is damaged: {size} bytes, shorter than its 8-byte header", _FIX)
    with open(path, "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as buf:
        r = _Reader(path, buf)
        out = parse(r)
        r.done()
    return out


def _cameras_bin(r: _Reader) -> list[tuple[int, str, int, int, np.ndarray, str]]:
    out = []
    for i in range(r.count(_CAMERA.size, "cameras")):
        cid, model_id, w, h = r.unpack(_CAMERA, f"camera {i}")
        if model_id not in CAMERA_MODELS:
            raise r.bad(f"camera {i} has the unknown model id {model_id}")
        name, n = CAMERA_MODELS[model_id]
        params = r.array(np.dtype("<f8"), n, f"the parameters of camera {i}")
        out.append((cid, name, w, h, params, f"camera {i}"))
    return out


def _images_bin(r: _Reader) -> list[tuple]:
    out = []
    for i in range(r.count(_IMAGE.size + 9, "images")):
        iid, qw, qx, qy, qz, tx, ty, tz, cid = r.unpack(_IMAGE, f"the pose of image {i}")
        name = r.name(f"image {i}")
        (n2d,) = r.unpack(_U64, f"the point count of image {i}")
        pts = r.array(_POINT2D, n2d, f"the 2D points of image {i}")
        ids = pts["id"].view(np.int64)  # 2^64 - 1 (none) reads as -1, as in the text format
        out.append((iid, (qw, qx, qy, qz), (tx, ty, tz), cid, name, pts["xy"], ids, f"image {i}"))
    return out


def _points_bin(r: _Reader) -> tuple:
    n = r.count(_POINT_SIZE, "3D points")
    buf, fixed, tracks, starts = r.buf, [], [], np.zeros(n + 1, np.int64)
    for i in range(n):
        pos = r.take(_POINT_SIZE, f"3D point {i}")
        (length,) = _U64.unpack_from(buf, pos + _POINT.itemsize)
        r.take(length * _TRACK.itemsize, f"the track of 3D point {i}")
        fixed.append(buf[pos:pos + _POINT.itemsize])
        tracks.append(buf[pos + _POINT_SIZE:r.pos])
        starts[i + 1] = starts[i] + length
    pts = np.frombuffer(b"".join(fixed), dtype=_POINT)
    track = np.frombuffer(b"".join(tracks), dtype=_TRACK)
    return (pts["id"].copy(), pts["xyz"].copy(), pts["rgb"].copy(), pts["error"].copy(), starts, track,
            lambda i: f"3D point {i}")


# --------------------------------------------------------------------------------------- text files


def _bad_line(path: Path, line: int, what: str) -> B3dgsError:
    return B3dgsError(f"COLMAP file {path} line {line}: {what}",
                      "fix that line or re-export the model (e.g. `colmap model_converter --output_type TXT`)")


def _lines(path: Path, keep_next: bool = False) -> Iterator[tuple[int, str, Optional[tuple[int, str]]]]:
    """(line number, stripped line) of the data lines; with ``keep_next``, each comes with the line after it (the
    images file's 2D point line, which may be empty), which is then consumed."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise B3dgsError(f"COLMAP file {path} is not UTF-8 text ({e.reason} at byte {e.start})", _FIX) from None
    rows = enumerate((row.strip() for row in text.splitlines()), start=1)
    for n, line in rows:
        if line and not line.startswith("#"):
            yield n, line, next(rows, None) if keep_next else None


def _numbers(path: Path, line: int, fields: list[str], kind, what: str) -> list:
    try:
        return [kind(f) for f in fields]
    except ValueError:
        raise _bad_line(path, line, f"{what}: expected numbers, got {' '.join(fields)[:80]!r}") from None


def _in_range(path: Path, line: int, values: list[int], lo: int, hi: int, what: str) -> list[int]:
    bad = [v for v in values if not lo <= v < hi]
    if bad:
        raise _bad_line(path, line, f"{what} {bad[0]} is out of range ({lo} .. {hi - 1})")
    return values


def _cameras_txt(path: Path) -> list[tuple]:
    out = []
    for n, line, _ in _lines(path):
        f = line.split()
        if len(f) < 4:
            raise _bad_line(path, n, f"expected `CAMERA_ID MODEL WIDTH HEIGHT PARAMS...`, got {line[:80]!r}")
        cid, w, h = _numbers(path, n, [f[0], f[2], f[3]], int, "camera id, width and height")
        _in_range(path, n, [cid], 0, 2**32, "camera id")
        if f[1] not in MODEL_IDS:
            raise _bad_line(path, n, f"unknown camera model {f[1]!r} (COLMAP's models: {', '.join(MODEL_IDS)})")
        want = CAMERA_MODELS[MODEL_IDS[f[1]]][1]
        if len(f) - 4 != want:
            raise _bad_line(path, n, f"camera {cid} ({f[1]}) has {len(f) - 4} parameters, the model has {want}")
        out.append((cid, f[1], w, h, np.array(_numbers(path, n, f[4:], float, "camera parameters")), f"line {n}"))
    return out


def _images_txt(path: Path) -> list[tuple]:
    out = []
    for n, line, nxt in _lines(path, keep_next=True):
        f = line.split()
        if len(f) != 10:
            raise _bad_line(path, n, "expected `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME` (10 fields, no spaces "
                                     f"in the name), got {len(f)} fields")
        iid, cid = _numbers(path, n, [f[0], f[8]], int, "image and camera ids")
        _in_range(path, n, [iid, cid], 0, 2**32, "image or camera id")
        pose = _numbers(path, n, f[1:8], float, "pose")
        xys, ids = np.empty((0, 2)), np.empty(0, np.int64)
        if nxt is not None and nxt[1]:
            g = nxt[1].split()
            if len(g) % 3:
                raise _bad_line(path, nxt[0], f"the 2D points of image {iid} must be `X Y POINT3D_ID` triples, got "
                                              f"{len(g)} fields")
            xys = np.array(_numbers(path, nxt[0], g[0::3] + g[1::3], float, "2D points")).reshape(2, -1).T.copy()
            ids = _numbers(path, nxt[0], g[2::3], int, "3D point ids")
            ids = np.array(_in_range(path, nxt[0], ids, -1, 2**63, "3D point id"), dtype=np.int64)
        out.append((iid, tuple(pose[:4]), tuple(pose[4:]), cid, f[9], xys, ids, f"line {n}"))
    return out


def _points_txt(path: Path) -> tuple:
    ids, xyz, rgb, err, starts, tracks, where = [], [], [], [], [0], [], []
    for n, line, _ in _lines(path):
        f = line.split()
        if len(f) < 8 or (len(f) - 8) % 2:
            raise _bad_line(path, n, "expected `POINT3D_ID X Y Z R G B ERROR` and (IMAGE_ID POINT2D_IDX) pairs, got "
                                     f"{len(f)} fields")
        pid, r, g, b = _numbers(path, n, [f[0], *f[4:7]], int, "point id and colour")
        if not all(0 <= c <= 255 for c in (r, g, b)):
            raise _bad_line(path, n, f"the colour {r} {g} {b} of 3D point {pid} is not 0..255")
        _in_range(path, n, [pid], 0, 2**64, "3D point id")
        track = _in_range(path, n, _numbers(path, n, f[8:], int, "track"), 0, 2**32, "track image id or 2D point index")
        ids.append(pid)
        xyz.append(_numbers(path, n, f[1:4], float, "position"))
        rgb.append((r, g, b))
        err.append(_numbers(path, n, [f[7]], float, "error")[0])
        starts.append(starts[-1] + len(track) // 2)
        tracks.append(np.array(track, dtype=np.uint32).reshape(-1, 2))
        where.append(n)
    track = np.empty(starts[-1], _TRACK)
    flat = np.concatenate(tracks) if tracks else np.empty((0, 2), np.uint32)
    track["image_id"], track["point2d"] = flat[:, 0], flat[:, 1]
    return (np.array(ids, dtype=np.uint64), np.array(xyz, dtype=np.float64).reshape(-1, 3),
            np.array(rgb, dtype=np.uint8).reshape(-1, 3), np.array(err, dtype=np.float64),
            np.array(starts, dtype=np.int64), track, lambda i: f"line {where[i]}")


# ---------------------------------------------------------------------------------------- the model


def model_format(model_dir: str | os.PathLike) -> Optional[str]:
    """``".bin"`` or ``".txt"``: the format COLMAP reads from ``model_dir`` (binary when all three ``.bin`` files are
    there, as ``Reconstruction::Read`` decides), or None when neither set is complete."""
    d = Path(model_dir)
    for ext in (".bin", ".txt"):
        if all((d / f"{n}{ext}").is_file() for n in FILES):
            return ext
    return None


def _unique(path: Path, ids, where: Callable[[int], str], what: str) -> None:
    seen: dict[int, int] = {}
    for i, k in enumerate(ids):
        if k in seen:
            raise B3dgsError(f"COLMAP file {path}: {where(i)} repeats the {what} id {k} of {where(seen[k])}", _FIX)
        seen[k] = i


def read_model(model_dir: str | os.PathLike, ext: Optional[str] = None) -> ColmapModel:
    """Parse and check the COLMAP model in ``model_dir`` (``ext``: ``".bin"`` or ``".txt"``; None: as
    :func:`model_format`). Raises :class:`B3dgsError` (one line) on a damaged or inconsistent file."""
    d = Path(model_dir)
    ext = ext or model_format(d)
    if ext not in (".bin", ".txt"):
        raise B3dgsError(f"no COLMAP model (cameras/images/points3D .bin or .txt) in {d}",
                         "point at the folder that holds the model (e.g. sparse/0)")
    p = {n: d / f"{n}{ext}" for n in FILES}
    if ext == ".bin":
        cams = _read_binary(p["cameras"], _cameras_bin)
        ims = _read_binary(p["images"], _images_bin)
        ids, xyz, rgb, err, starts, track, where_pt = _read_binary(p["points3D"], _points_bin)
    else:
        cams, ims = _cameras_txt(p["cameras"]), _images_txt(p["images"])
        ids, xyz, rgb, err, starts, track, where_pt = _points_txt(p["points3D"])

    _unique(p["cameras"], [c[0] for c in cams], lambda i: cams[i][5], "camera")
    cameras = {}
    for cid, model, w, h, params, where in cams:
        if not (0 < w < 2**20 and 0 < h < 2**20):
            raise B3dgsError(f"COLMAP file {p['cameras']}: {where} (id {cid}) has the size {w}x{h}", _FIX)
        cameras[cid] = ColmapCamera(cid, model, int(w), int(h), params)
    _unique(p["images"], [m[0] for m in ims], lambda i: ims[i][7], "image")
    images = {}
    for iid, q, t, cid, name, xys, pids, where in ims:
        if cid not in cameras:
            raise B3dgsError(f"COLMAP file {p['images']}: {where} ({name!r}) names camera {cid}, which "
                             f"{p['cameras'].name} does not have", _FIX)
        images[iid] = ColmapImage(iid, np.array(q, dtype=np.float64), np.array(t, dtype=np.float64), cid, name, xys,
                                  pids)
    _unique(p["points3D"], ids.tolist(), where_pt, "3D point")
    _check_tracks(p, images, starts, track, where_pt)
    return ColmapModel(d, cameras, images, ids, xyz, rgb, err, starts, track)


def _check_tracks(p: dict[str, Path], images: dict[int, ColmapImage], starts, track, where_pt) -> None:
    """Each track element names an existing image and one of its 2D points."""
    if not len(track):
        return
    known = np.array(sorted(images), dtype=np.int64)
    n2d = np.array([len(images[i].xys) for i in sorted(images)], dtype=np.int64)
    tid = track["image_id"].astype(np.int64)
    at = np.minimum(np.searchsorted(known, tid), max(len(known) - 1, 0))
    missing = (known[at] != tid) if len(known) else np.ones(len(tid), bool)
    beyond = ~missing & (track["point2d"].astype(np.int64) >= n2d[at] if len(known) else False)
    for bad, what in ((missing, "image"), (beyond, "2D point")):
        if bad.any():
            e = int(np.argmax(bad))
            pt = int(np.searchsorted(starts, e, side="right")) - 1
            iid, k = int(tid[e]), int(track["point2d"][e])
            detail = (f"image {iid}, which {p['images'].name} does not have" if what == "image" else
                      f"2D point {k} of image {iid}, which has {len(images[iid].xys)}")
            raise B3dgsError(f"COLMAP file {p['points3D']}: the track of {where_pt(pt)} names {detail}", _FIX)


# libstdc++'s std::unordered_map bucket counts as it grows from empty (max load factor 1, growth factor 2): it
# rehashes to the next count before inserting element count + 1.
_BUCKETS = (13, 29, 59, 127, 257, 541, 1109, 2357, 5087, 10273, 20753, 42043, 85229, 172933, 351061, 712697,
            1447153, 2938679, 5967347, 12117689, 24607243, 49969847, 101473717, 206062531, 418451333)


def unordered_map_order(keys: np.ndarray) -> np.ndarray:
    """Indices of the distinct integer ``keys``, inserted in their order, in the order a libstdc++
    ``std::unordered_map`` lists them: the order in which pycolmap (< 4.1 on Linux) listed a model's 3D points, kept so
    that scenes load with their points in the same order as before (runs keep their bits).

    The map is one list of nodes in runs of equal bucket (``key % buckets``, the hash of an integer being itself); a
    key whose bucket is empty goes to the front of the list, else to the front of its bucket's run; a rehash
    re-inserts the nodes, in list order, into an empty map of the next bucket count (:data:`_BUCKETS`)."""
    keys = np.asarray(keys, dtype=np.uint64)
    n = len(keys)
    if n > _BUCKETS[-1]:
        return np.arange(n)
    order, start = np.empty(0, np.int64), 0
    for buckets in _BUCKETS:
        if start:
            order = _insert(keys, np.empty(0, np.int64), order, buckets)
        end = min(n, buckets)
        order = _insert(keys, order, np.arange(start, end), buckets)
        start = end
        if start >= n:
            break
    return order


def _insert(keys: np.ndarray, listed: np.ndarray, new: np.ndarray, buckets: int) -> np.ndarray:
    """The list ``listed`` (indices into keys, runs of equal bucket) after inserting ``new`` one by one."""
    b_old, b_new = keys[listed] % np.uint64(buckets), keys[new] % np.uint64(buckets)
    runs, first_old = np.unique(b_old, return_index=True)  # a run's place: its first position in the list
    _, first_new, inv = np.unique(b_new, return_index=True, return_inverse=True)
    at = np.minimum(np.searchsorted(runs, b_new), max(len(runs) - 1, 0))
    has_run = runs[at] == b_new if len(runs) else np.zeros(len(new), bool)
    run_old = first_old[np.searchsorted(runs, b_old)] if len(listed) else np.empty(0, np.int64)
    # a new run goes before all others, the later its first key the earlier; new keys go first in their run,
    # the later the earlier
    run_new = np.where(has_run, first_old[at] if len(runs) else 0, -first_new[inv.reshape(-1)] - 1)
    run = np.concatenate([run_old, run_new])
    within = np.concatenate([np.arange(len(listed)), -np.arange(1, len(new) + 1)])
    return np.concatenate([listed, new])[np.lexsort((within, run))]
