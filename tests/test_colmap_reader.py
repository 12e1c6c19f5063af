"""The NumPy COLMAP reader (:mod:`b3dgs.data.colmap_model`): the same model as pycolmap (frames, poses bit for bit,
points in pycolmap's order, colours, tracks), ``.bin`` = ``.txt``, one-line errors for damaged or inconsistent files,
and COLMAP scenes that load, train and evaluate where pycolmap cannot be imported."""
from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from b3dgs.data import load_scene
from b3dgs.data.colmap import read_colmap
from b3dgs.data.colmap_model import CAMERA_MODELS, read_model, unordered_map_order
from b3dgs.data.images import save_png
from b3dgs.errors import B3dgsError
from conftest import SHARED

REPO = Path(__file__).resolve().parents[1]
DATA = SHARED / "data"
COLMAP_SCENES = ["ethiopian_head", "fern", "flower", "dtu_scan24", "dtu_scan65"]
ENV = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}


def _scene_dir(name: str) -> Path:
    d = DATA / name
    if not (d / "sparse" / "0").is_dir():
        pytest.skip(f"shared scene not found at {d}")
    return d


# ------------------------------------------------------------------------------------------------
# the model as pycolmap reads it, and as the NumPy reader does
# ------------------------------------------------------------------------------------------------


def _pycolmap_view(model_dir: Path, points2d: bool = False) -> dict:
    from b3dgs.data.images import import_pycolmap

    pytest.importorskip("pycolmap")
    pycolmap = import_pycolmap()
    rec = pycolmap.Reconstruction(str(model_dir))
    cams = {c.camera_id: (c.model.name, c.width, c.height, np.asarray(c.params)) for c in rec.cameras.values()}
    ims = {}
    for im in rec.images.values():
        ims[im.image_id] = [im.name, im.camera_id, np.asarray(im.cam_from_world().matrix())]
        if points2d:
            ims[im.image_id] += [np.array([p.xy for p in im.points2D]).reshape(-1, 2),
                                 np.array([-1 if p.point3D_id == 2**64 - 1 else p.point3D_id for p in im.points2D])]
    pts = list(rec.points3D.items())
    return {"cameras": cams, "images": ims, "ids": [k for k, _ in pts],
            "xyz": np.array([p.xyz for _, p in pts]).reshape(-1, 3),
            "rgb": np.array([p.color for _, p in pts], dtype=np.uint8).reshape(-1, 3),
            "tracks": [[(e.image_id, e.point2D_idx) for e in p.track.elements] for _, p in pts]}


def _numpy_view(model_dir: Path, ext=None, points2d: bool = False) -> dict:
    m = read_model(model_dir, ext)
    cams = {c.id: (c.model, c.width, c.height, c.params) for c in m.cameras.values()}
    ims = {}
    for im in m.images.values():
        ims[im.id] = [im.name, im.camera_id, im.viewmat()[:3]] + ([im.xys, im.point3d_ids] if points2d else [])
    order = unordered_map_order(m.point_ids)
    s, tr = m.track_start, m.track
    return {"cameras": cams, "images": ims, "ids": m.point_ids[order].tolist(), "xyz": m.xyz[order],
            "rgb": m.rgb[order],
            "tracks": [list(zip(tr["image_id"][s[i]:s[i + 1]].tolist(), tr["point2d"][s[i]:s[i + 1]].tolist()))
                       for i in order.tolist()]}


def _assert_same(a: dict, b: dict) -> None:
    """Equal bit for bit: arrays by np.array_equal (float64 values, not rounded), the rest by ==."""
    assert a.keys() == b.keys()
    for k in a:
        x, y = a[k], b[k]
        if isinstance(x, dict):
            assert x.keys() == y.keys(), k
            for i in x:
                assert len(x[i]) == len(y[i]), (k, i)
                for u, v in zip(x[i], y[i]):
                    assert (np.array_equal(u, v) and np.asarray(u).dtype.kind == np.asarray(v).dtype.kind
                            if isinstance(u, np.ndarray) else u == v), (k, i, u, v)
        elif isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and np.array_equal(x, y), k
        else:
            assert x == y, k


def _tiny_pycolmap_model(root: Path) -> dict[str, Path]:
    """A model written by pycolmap: cameras 1 PINHOLE and 2 OPENCV, 3 images (two on camera 1), 40 points (more than
    the 13 and 29 buckets of the first rehashes) with tracks of 2 or 3 images, in ``root/bin`` and ``root/txt``."""
    from b3dgs.data.images import import_pycolmap

    pytest.importorskip("pycolmap")
    pycolmap = import_pycolmap()
    rng = np.random.default_rng(3)
    rec = pycolmap.Reconstruction()
    for cid, model, params, w, h in ((1, "PINHOLE", [50.0, 52.0, 32.0, 24.0], 64, 48),
                                     (2, "OPENCV", [40.0, 41.0, 39.5, 30.5, -0.05, 0.01, 0.001, -0.002], 80, 60)):
        cam = pycolmap.Camera.create_from_model_name(cid, model, params[0], w, h)
        cam.params = params
        rec.add_camera_with_trivial_rig(cam)
    for iid, cid in ((1, 1), (2, 2), (3, 1)):
        q = rng.normal(size=4)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(q / np.linalg.norm(q)), rng.normal(size=3))
        image = pycolmap.Image(name=f"view_{iid}.png", keypoints=rng.uniform(0, 48, (45, 2)), camera_id=cid,
                               image_id=iid)
        rec.add_image_with_trivial_frame(image, pose)
    for j in range(40):
        track = pycolmap.Track()
        for iid in ((1, 2, 3), (1, 3), (2, 3))[j % 3]:
            track.add_element(iid, j)
        rec.add_point3D(rng.normal(size=3), track, rng.integers(0, 256, 3).astype(np.uint8))
    out = {}
    for ext in ("bin", "txt"):
        d = root / ext / "sparse" / "0"
        d.mkdir(parents=True)
        (rec.write_binary if ext == "bin" else rec.write_text)(str(d))
        out[ext] = d
    return out


def test_camera_model_table_matches_pycolmap():
    """Every model pycolmap knows has the id and parameter count of :data:`CAMERA_MODELS`."""
    from b3dgs.data.images import import_pycolmap

    pytest.importorskip("pycolmap")
    pycolmap = import_pycolmap()
    seen = 0
    for name, mid in pycolmap.CameraModelId.__members__.items():
        if int(mid) < 0:
            continue
        n = len(pycolmap.Camera.create_from_model_name(1, name, 1.0, 2, 2).params)
        assert CAMERA_MODELS[int(mid)] == (name, n)
        seen += 1
    assert seen >= 11


def test_tiny_pycolmap_model_reads_as_pycolmap_reads_it(tmp_path):
    """Cameras, poses (bit for bit), 2D points, points in pycolmap's order, colours and tracks, from .bin and .txt."""
    dirs = _tiny_pycolmap_model(tmp_path)
    for ext, d in dirs.items():
        want = _pycolmap_view(d, points2d=True)
        got = _numpy_view(d, points2d=True)
        assert len(got["ids"]) == 40 and got["ids"] != sorted(got["ids"])  # pycolmap's (hash) order, not the file's
        _assert_same(got, want)
    _assert_same(_numpy_view(dirs["bin"], points2d=True), _numpy_view(dirs["txt"], points2d=True))


@pytest.mark.parametrize("scene", COLMAP_SCENES)
def test_shared_scene_reads_as_pycolmap_reads_it_bin_and_txt(tmp_path, scene):
    """Each shared COLMAP scene: the same model as pycolmap's, and its text export (pycolmap's write_text) gives the
    same model and the same loaded frames, points, colours and tracks as the binary one."""
    d = _scene_dir(scene)
    model = d / "sparse" / "0"
    want = _pycolmap_view(model)
    _assert_same(_numpy_view(model), want)

    from b3dgs.data.images import import_pycolmap

    txt = tmp_path / scene
    (txt / "sparse" / "0").mkdir(parents=True)
    import_pycolmap().Reconstruction(str(model)).write_text(str(txt / "sparse" / "0"))
    (txt / "images").symlink_to(d / "images")
    _assert_same(_numpy_view(txt / "sparse" / "0"), want)
    a, b = read_colmap(d, point_tracks=True), read_colmap(txt, point_tracks=True)
    assert [f.name for f in a[0]] == [f.name for f in b[0]] and len(a[0]) == len(want["images"])
    assert all(np.array_equal(x.K, y.K) and np.array_equal(x.viewmat, y.viewmat) for x, y in zip(a[0], b[0]))
    assert np.array_equal(a[1], b[1]) and np.array_equal(a[2], b[2]) and a[3] == b[3]
    names = {v[0] for v in want["images"].values()}
    assert len(a[3]) == len(a[1]) and all(set(t) <= names and t == sorted(t) for t in a[3])


def test_unordered_map_order_matches_pycolmap_for_any_ids():
    """Random, sparse and unsorted point ids (inserted in file order) list in pycolmap's order."""
    from b3dgs.data.images import import_pycolmap

    pytest.importorskip("pycolmap")
    pycolmap = import_pycolmap()
    rng = np.random.default_rng(0)
    for n, is_sorted in ((1, True), (14, False), (300, True), (6000, False)):
        ids = rng.choice(10**7, n, replace=False).astype(np.uint64) + 1
        if is_sorted:
            ids.sort()
        rec = pycolmap.Reconstruction()
        for i in ids.tolist():
            rec.add_point3D_with_id(i, pycolmap.Point3D())
        assert ids[unordered_map_order(ids)].tolist() == list(rec.points3D.keys())


# ------------------------------------------------------------------------------------------------
# a tiny scene written here (no pycolmap): text and binary
# ------------------------------------------------------------------------------------------------


def _write_tiny_scene(root: Path, n_views: int = 8, w: int = 48, h: int = 36, n_points: int = 60) -> Path:
    """A COLMAP scene written without pycolmap: ``n_views`` PINHOLE cameras on a ring looking at the origin, random
    smooth images, ``n_points`` points in the unit cube seen by every view; ``sparse/0`` (binary) and ``sparse/txt``
    (text, the same model)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(1)
    (root / "images").mkdir(parents=True)
    xyz = rng.uniform(-1, 1, (n_points, 3))
    rgb = rng.integers(0, 256, (n_points, 3))
    K = np.array([[30.0, 0, w / 2], [0, 30.0, h / 2], [0, 0, 1]])
    images = []
    for i in range(n_views):
        a = 2 * np.pi * i / n_views
        c = np.array([4 * np.cos(a), 4 * np.sin(a), 1.0])
        z = -c / np.linalg.norm(c)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        t = -R @ c
        qx, qy, qz, qw = Rotation.from_matrix(R).as_quat()
        uv = (xyz @ R.T + t) @ K.T
        images.append((i + 1, (qw, qx, qy, qz), t, f"v{i:02d}.png", uv[:, :2] / uv[:, 2:]))
        img = rng.uniform(0, 1, (h // 4, w // 4, 3)).repeat(4, 0).repeat(4, 1)
        save_png(root / "images" / f"v{i:02d}.png", img)
    txt, bin_ = root / "sparse" / "txt", root / "sparse" / "0"
    txt.mkdir(parents=True)
    bin_.mkdir(parents=True)
    (txt / "cameras.txt").write_text(f"# one camera\n1 PINHOLE {w} {h} 30 30 {w / 2} {h / 2}\n")
    lines = ["# images"]
    for iid, q, t, name, uv in images:
        lines.append(" ".join(repr(float(v)) for v in (*q, *t)).join([f"{iid} ", f" 1 {name}"]))
        lines.append(" ".join(f"{u!r} {v!r} {j + 1}" for j, (u, v) in enumerate(uv.tolist())))
    (txt / "images.txt").write_text("\n".join(lines) + "\n")
    pts = [f"{j + 1} {' '.join(repr(float(v)) for v in xyz[j])} {' '.join(str(int(c)) for c in rgb[j])} 0.5 "
           + " ".join(f"{iid} {j}" for iid, *_ in images) for j in range(n_points)]
    (txt / "points3D.txt").write_text("\n".join(pts) + "\n")

    u64 = struct.Struct("<Q").pack
    (bin_ / "cameras.bin").write_bytes(u64(1) + struct.pack("<IiQQ4d", 1, 1, w, h, 30, 30, w / 2, h / 2))
    ims = u64(len(images))
    for iid, q, t, name, uv in images:
        ims += struct.pack("<I7dI", iid, *q, *t, 1) + name.encode() + b"\0" + u64(len(uv))
        ims += b"".join(struct.pack("<2dQ", u, v, j + 1) for j, (u, v) in enumerate(uv.tolist()))
    (bin_ / "images.bin").write_bytes(ims)
    ps = u64(n_points)
    for j in range(n_points):
        ps += struct.pack("<Q3d3BdQ", j + 1, *xyz[j], *(int(c) for c in rgb[j]), 0.5, len(images))
        ps += b"".join(struct.pack("<II", iid, j) for iid, *_ in images)
    (bin_ / "points3D.bin").write_bytes(ps)
    return root


def test_tiny_scene_text_and_binary_load_the_same(tmp_path):
    root = _write_tiny_scene(tmp_path / "tiny")
    _assert_same(_numpy_view(root / "sparse" / "0", points2d=True), _numpy_view(root / "sparse" / "txt", points2d=True))
    a = load_scene("colmap", str(root), sparse_dir="sparse/txt", test_every=4)
    b = load_scene("colmap", str(root), sparse_dir="sparse/0", test_every=4)
    assert [c.name for c in a.train] == [c.name for c in b.train] and len(a.test) == 2
    for x, y in zip(a.train + a.test, b.train + b.test):
        assert x.K.equal(y.K) and x.viewmat.equal(y.viewmat) and x.image.equal(y.image)
    assert a.points.equal(b.points) and a.point_colors.equal(b.point_colors) and a.points.shape == (60, 3)


# ------------------------------------------------------------------------------------------------
# damaged and inconsistent files: one line naming the file
# ------------------------------------------------------------------------------------------------


def _copy_model(tmp_path: Path, which: str) -> Path:
    root = _write_tiny_scene(tmp_path / "tiny")
    d = tmp_path / "scene"
    (d / "sparse").mkdir(parents=True)
    shutil.copytree(root / "sparse" / which, d / "sparse" / "0")
    (d / "images").symlink_to(root / "images")
    return d


def _patch(path: Path, offset: int, data: bytes) -> None:
    b = bytearray(path.read_bytes())
    b[offset:offset + len(data)] = data
    path.write_bytes(bytes(b))


_IMAGE0 = 8 + 4 + 56  # images.bin: the camera id of the first image
_TRACK0 = 8 + 51  # points3D.bin: the first track element of the first point


@pytest.mark.parametrize("name,edit,text", [
    ("cameras.bin", lambda p: _patch(p, 0, struct.pack("<Q", 2**40)), "header says 1099511627776 cameras"),
    ("cameras.bin", lambda p: _patch(p, 12, struct.pack("<i", 99)), "unknown model id 99"),
    ("images.bin", lambda p: p.write_bytes(p.read_bytes()[:-5]), "truncated inside the 2D points of image 7"),
    ("images.bin", lambda p: _patch(p, _IMAGE0, struct.pack("<I", 9)), r"image 0 \('v00.png'\) names camera 9"),
    ("images.bin", lambda p: _patch(p, 8, struct.pack("<I", 2)), "image 1 repeats the image id 2 of image 0"),
    ("points3D.bin", lambda p: p.write_bytes(p.read_bytes() + b"\0"), "1 unexpected bytes after the last record"),
    ("points3D.bin", lambda p: p.write_bytes(p.read_bytes()[:12]), "header says 60 3D points but only 4 bytes"),
    ("points3D.bin", lambda p: _patch(p, _TRACK0, struct.pack("<I", 77)),
     "the track of 3D point 0 names image 77, which images.bin does not have"),
    ("points3D.bin", lambda p: _patch(p, _TRACK0 + 4, struct.pack("<I", 60)),
     "names 2D point 60 of image 1, which has 60"),
])
def test_damaged_or_inconsistent_binary_file_is_one_line(tmp_path, name, edit, text):
    d = _copy_model(tmp_path, "0")
    edit(d / "sparse" / "0" / name)
    for load in (lambda: read_model(d / "sparse" / "0"), lambda: load_scene("colmap", str(d), test_every=0)):
        with pytest.raises(B3dgsError, match=text) as ei:
            load()
        msg = str(ei.value)
        assert "\n" not in msg and name in msg and "fix:" in msg, msg


def _edit_line(path: Path, number: int, new: str) -> None:
    lines = path.read_text().splitlines()
    lines[number - 1] = new
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("name,line,new,text", [
    ("cameras.txt", 2, "1 PINHOLE 48 36 30 30 24", "line 2: camera 1 \\(PINHOLE\\) has 3 parameters, the model has 4"),
    ("cameras.txt", 2, "1 PINHOLEX 48 36 30 30 24 18", "line 2: unknown camera model 'PINHOLEX'"),
    ("cameras.txt", 2, "1 PINHOLE 48 36 30 30 24 twelve", "line 2: camera parameters: expected numbers"),
    ("images.txt", 2, "1 1 0 0 0 0 0 0 1 my image.png", "line 2: expected `IMAGE_ID .*got 11 fields"),
    ("images.txt", 2, "1 1 0 0 0 0 0 0 3 v00.png", r"line 2 \('v00.png'\) names camera 3"),
    ("images.txt", 3, "1.0 2.0", "line 3: the 2D points of image 1 must be `X Y POINT3D_ID` triples, got 2"),
    ("points3D.txt", 1, "1 0 0 0 255 0 0 0.5 1", "line 1: expected `POINT3D_ID X Y Z R G B ERROR`"),
    ("points3D.txt", 1, "1 0 0 0 256 0 0 0.5 1 0", "line 1: the colour 256 0 0 of 3D point 1 is not 0..255"),
    ("points3D.txt", 2, "2 0 0 0 255 0 0 0.5 12 1", "the track of line 2 names image 12, which images.txt does not"),
    ("points3D.txt", 2, "1 0 0 0 255 0 0 0.5 1 1", "line 2 repeats the 3D point id 1 of line 1"),
])
def test_malformed_or_inconsistent_text_line_is_one_line(tmp_path, name, line, new, text):
    d = _copy_model(tmp_path, "txt")
    _edit_line(d / "sparse" / "0" / name, line, new)
    for load in (lambda: read_model(d / "sparse" / "0"), lambda: load_scene("colmap", str(d), test_every=0)):
        with pytest.raises(B3dgsError, match=text) as ei:
            load()
        msg = str(ei.value)
        assert "\n" not in msg and name in msg and "fix:" in msg, msg


# ------------------------------------------------------------------------------------------------
# no pycolmap: importing b3dgs, loading, training and evaluating a COLMAP scene
# ------------------------------------------------------------------------------------------------


def test_importing_b3dgs_does_not_import_pycolmap():
    code = "import sys, b3dgs, b3dgs.data, b3dgs.train; assert 'pycolmap' not in sys.modules, 'pycolmap imported'"
    proc = subprocess.run([sys.executable, "-c", code], env=ENV, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]


_NO_PYCOLMAP = '''
"""Run a module as __main__ where pycolmap cannot be imported; any attempt is reported on stderr."""
import atexit, runpy, sys


class _NoPycolmap:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] == "pycolmap":
            sys.stderr.write("PYCOLMAP IMPORT ATTEMPTED\\n")
            raise ImportError("pycolmap is blocked by the test")
        return None


sys.meta_path.insert(0, _NoPycolmap())
atexit.register(lambda: sys.stderr.write(f"PYCOLMAP IN sys.modules: {'pycolmap' in sys.modules}\\n"))
module, sys.argv = sys.argv[1], sys.argv[1:]
runpy.run_module(module, run_name="__main__", alter_sys=True)
'''


@pytest.mark.slow
def test_colmap_scene_loads_trains_and_evaluates_without_pycolmap(tmp_path):
    """b3dgs-train and b3dgs-eval on a COLMAP scene (binary model) with pycolmap blocked: both succeed and nothing
    tries to import it."""
    root = _write_tiny_scene(tmp_path / "tiny")
    wrapper = tmp_path / "no_pycolmap.py"
    wrapper.write_text(_NO_PYCOLMAP)
    run = tmp_path / "run"

    def call(*args: str) -> subprocess.CompletedProcess:
        proc = subprocess.run([sys.executable, str(wrapper), *args], env=ENV, capture_output=True, text=True,
                              timeout=600, cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert "PYCOLMAP IMPORT ATTEMPTED" not in proc.stderr and "PYCOLMAP IN sys.modules: False" in proc.stderr
        return proc

    call("b3dgs.train", "data=colmap", f"data.path={root}", "data.test_every=4",
         "trainer.max_steps=10", "trainer.eval_every=10", "trainer.enable_progress_bar=false", "logger=none",
         "trainer.save_renders=false", f"hydra.run.dir={run}")
    metrics = json.loads((run / "metrics.json").read_text())
    assert np.isfinite(metrics["psnr"]) and metrics["num_gaussians"] > 0
    call("b3dgs.eval", f"run={run}", "uq=proxy", "max_views=2")
