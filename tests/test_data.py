"""Scene loading: COLMAP, transforms.json, LLFF, synthetic; preprocessing; DataModule; PNG I/O."""
from __future__ import annotations

import logging
import re
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from b3dgs.data import load_scene
from b3dgs.data.images import encode_png, load_image, save_png
from b3dgs.data.llff import write_llff
from b3dgs.data.scene import compute_bounds, look_at_point, split_indices
from b3dgs.data.synthetic import load_synthetic
from b3dgs.errors import B3dgsError
from b3dgs.types import Camera

REPO = Path(__file__).resolve().parents[1]
from conftest import SHARED

DATA = SHARED / "data"
HEAD = DATA / "ethiopian_head"
FOX = DATA / "fox"
needs_head = pytest.mark.skipif(not (HEAD / "sparse" / "0").is_dir(), reason="ethiopian_head not available")
needs_fox = pytest.mark.skipif(not (FOX / "transforms.json").is_file(), reason="fox not available")


def project(cam: Camera, pts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(uv (M, 2) pixel coordinates, z (M,)) of world points in ``cam``."""
    pc = pts.double() @ cam.viewmat[:3, :3].double().T + cam.viewmat[:3, 3].double()
    uvw = pc @ cam.K.double().T
    return uvw[:, :2] / uvw[:, 2:3], pc[:, 2]


def inside(cam: Camera, uv: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    return (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)


def centres(cams: list[Camera]) -> torch.Tensor:
    return torch.stack([c.center for c in cams])


# ------------------------------------------------------------------------------------------------
# COLMAP
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def head_scene():
    return load_scene("colmap", str(HEAD), max_side=128, test_every=8)


@needs_head
def test_colmap_ethiopian_head(head_scene):
    s = head_scene
    assert len(s.train) + len(s.test) == 66
    assert len(s.test) == 9 and len(s.train) == 57  # indices 0, 8, ..., 64
    names = sorted(c.name for c in s.train + s.test)
    assert [c.name for c in s.test] == names[::8]
    cam = s.train[0]
    assert (cam.width, cam.height) == (128, 128)
    assert cam.image.shape == (128, 128, 3) and cam.image.dtype == torch.float32
    assert 0.0 <= float(cam.image.min()) and float(cam.image.max()) <= 1.0
    r = 128 / 553
    assert torch.allclose(cam.K, torch.tensor([[369.9013503 * r, 0, 276.5 * r], [0, 369.9013503 * r, 276.5 * r], [0, 0, 1]]), atol=1e-3)
    assert s.points is not None and s.points.shape == (4767, 3) and s.point_colors.shape == (4767, 3)
    assert s.extent == pytest.approx(1.0)
    c = centres(s.train + s.test)
    assert torch.allclose(c.mean(0), torch.zeros(3), atol=1e-4)
    assert 1.1 * float((c - c.mean(0)).norm(dim=1).max()) == pytest.approx(1.0, abs=1e-4)
    # SfM points project mostly inside the image, in front of the camera.
    for cam in s.test[:4]:
        uv, z = project(cam, s.points)
        assert float(inside(cam, uv, z).float().mean()) > 0.7
    assert torch.all(s.bounds_min < s.bounds_max)
    q = torch.quantile(s.points, 0.5, dim=0)
    assert torch.all(q > s.bounds_min) and torch.all(q < s.bounds_max)


@needs_head
def test_colmap_unnormalized_is_similar(head_scene):
    raw = load_scene("colmap", str(HEAD), max_side=64, test_every=8, normalize=False, max_images=9)
    assert len(raw.train) + len(raw.test) == 9
    assert raw.extent > 1.5  # raw COLMAP frame
    assert raw.train[0].image.shape == (64, 64, 3)
    # pairwise camera distances scale by 1/extent under normalisation
    norm = load_scene("colmap", str(HEAD), max_side=64, test_every=8, max_images=9)
    dr = torch.cdist(centres(raw.train), centres(raw.train))
    dn = torch.cdist(centres(norm.train), centres(norm.train))
    assert torch.allclose(dr / raw.extent, dn, atol=1e-4)


def _write_colmap(root: Path, model: str, params: list[float], w: int, h: int, image: np.ndarray | None) -> None:
    from b3dgs.data.images import import_pycolmap

    pycolmap = import_pycolmap()
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, model, params[0], w, h)
    cam.params = params
    rec.add_camera_with_trivial_rig(cam)
    rec.add_image_with_trivial_frame(pycolmap.Image(name="a.png", camera_id=1, image_id=1), pycolmap.Rigid3d())
    (root / "sparse" / "0").mkdir(parents=True)
    rec.write(str(root / "sparse" / "0"))
    (root / "images").mkdir()
    save_png(root / "images" / "a.png", image if image is not None else np.zeros((h, w, 3)))


@pytest.mark.parametrize("model,params", [("SIMPLE_RADIAL", [50.0, 32.0, 24.0, 0.05]),
                                          ("OPENCV", [50.0, 52.0, 31.0, 25.0, -0.08, 0.01, 0.002, -0.001])])
def test_colmap_distorted_model_undistorted_on_load_or_used_as_pinhole(tmp_path, caplog, model, params):
    """A distorted COLMAP camera (once refused) is undistorted on load by default (data.undistort null or true: K'
    is K with both focal lengths scaled by one factor, the image resampled); data.undistort=false loads its pinhole
    part as it is, with one warning naming what was ignored."""
    from b3dgs.data.datamodule import SceneDataModule
    from b3dgs.data.undistort import Distortion, undistort_image

    yy, xx = np.mgrid[0:48, 0:64]
    image = np.stack([0.5 + 0.4 * np.sin(xx / 5.0), 0.5 + 0.4 * np.cos(yy / 4.0), np.full((48, 64), 0.3)], -1)
    _write_colmap(tmp_path, model, params, 64, 48, image)
    fx, fy, cx, cy = (params[0], params[0], *params[1:3]) if model == "SIMPLE_RADIAL" else params[:4]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    default = load_scene("colmap", str(tmp_path), test_every=0, normalize=False).train[0]
    on = SceneDataModule(kind="colmap", path=str(tmp_path), test_every=0, normalize=False, undistort=True).scene.train[0]
    with caplog.at_level(logging.WARNING, logger="b3dgs.data"):
        off = load_scene("colmap", str(tmp_path), test_every=0, normalize=False, undistort=False).train[0]
    assert torch.equal(default.image, on.image) and torch.equal(default.K, on.K)
    s = float(on.K[0, 0]) / fx
    assert s != 1.0 and float(on.K[1, 1]) == pytest.approx(s * fy, rel=1e-6)
    assert torch.equal(on.K[:2, 2], torch.tensor([cx, cy], dtype=torch.float32))
    png = load_image(tmp_path / "images" / "a.png")
    want, Kp = undistort_image(png, K, Distortion(model, tuple(params[len(params) - (1 if model == "SIMPLE_RADIAL" else 4):])))
    assert np.array_equal(on.image.numpy(), want) and np.allclose(on.K.numpy(), Kp, rtol=1e-6)
    assert not torch.equal(on.image, off.image)
    assert torch.equal(off.K, torch.tensor(K, dtype=torch.float32)) and torch.equal(off.image, torch.from_numpy(png))
    warnings = [r.getMessage() for r in caplog.records if "distortion" in r.getMessage()]
    assert len(warnings) == 1 and f"camera 1 {model}" in warnings[0] and "data.undistort=false" in warnings[0]


def test_colmap_model_it_cannot_undistort_is_refused_in_one_line(tmp_path):
    _write_colmap(tmp_path, "FOV", [50.0, 50.0, 32.0, 24.0, 0.5], 64, 48, None)
    for undistort in (None, True, False):
        with pytest.raises(B3dgsError, match=r"camera 1 .*FOV.*image_undistorter") as e:
            load_scene("colmap", str(tmp_path), test_every=0, undistort=undistort)
        assert "\n" not in str(e.value)


def test_colmap_tiny_pinhole_and_size_mismatch(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    _write_colmap(a, "SIMPLE_PINHOLE", [50.0, 32.0, 24.0], 64, 48, np.full((48, 64, 3), 0.5))
    s = load_scene("colmap", str(a), test_every=0, normalize=False)
    assert torch.allclose(s.train[0].K, torch.tensor([[50.0, 0, 32], [0, 50, 24], [0, 0, 1]]))
    assert s.points is None
    _write_colmap(b, "PINHOLE", [50.0, 50.0, 32.0, 24.0], 64, 48, np.zeros((40, 64, 3)))
    with pytest.raises(ValueError, match=r"a\.png.*64x40"):
        load_scene("colmap", str(b), test_every=0)


# ------------------------------------------------------------------------------------------------
# transforms.json
# ------------------------------------------------------------------------------------------------


@needs_fox
def test_transforms_fox(caplog):
    with caplog.at_level(logging.WARNING, logger="b3dgs.data"):
        s = load_scene("transforms", str(FOX), max_side=128, test_every=8)
    warnings = [r for r in caplog.records if "distortion" in r.getMessage()]
    assert len(warnings) == 1 and "k1=" in warnings[0].getMessage()
    cams = s.train + s.test
    assert len(cams) == 67 and len(s.test) == 9
    assert s.points is None
    cam = s.train[0]
    assert (cam.width, cam.height) == (72, 128)  # portrait 270x480 -> 72x128
    assert cam.image.shape == (128, 72, 3)
    assert float(cam.K[0, 0]) == pytest.approx(343.88 * 72 / 270, rel=1e-5)
    assert float(cam.K[1, 1]) == pytest.approx(343.6225 * 128 / 480, rel=1e-5)
    assert float(cam.K[1, 2]) == pytest.approx(241.317 * 128 / 480, rel=1e-5)
    assert s.extent == pytest.approx(1.0)
    # OpenGL -> OpenCV: the point the cameras look at is in front of every camera (z > 0).
    V = np.stack([c.viewmat.double().numpy() for c in cams])
    p, well_posed = look_at_point(V)
    assert well_posed
    z = V[:, 2, :3] @ p + V[:, 2, 3]
    assert np.all(z > 0.2)
    # ... and it projects near the image centre, inside the random-init box.
    uv, _ = project(cam, torch.tensor(p)[None])
    assert 0 < float(uv[0, 0]) < cam.width and 0 < float(uv[0, 1]) < cam.height
    lo, hi = s.bounds_min.double().numpy(), s.bounds_max.double().numpy()
    assert np.all(lo < p) and np.all(p < hi)
    # cameras stay outside the box
    assert not np.any(np.all((V[:, :3, :3].transpose(0, 2, 1) @ -V[:, :3, 3:])[..., 0] > lo, axis=1)
                      & np.all((V[:, :3, :3].transpose(0, 2, 1) @ -V[:, :3, 3:])[..., 0] < hi, axis=1))


def _blender_scene(tmp_path: Path) -> Path:
    """A tiny Blender-style scene: camera_angle_x, extension-less file paths, RGBA images."""
    import json

    raw = load_synthetic(n_views=3, resolution=16, seed=1)
    frames = []
    (tmp_path / "train").mkdir()
    for i, cam in enumerate(raw.cameras):
        rgba = np.zeros((16, 16, 4), dtype=np.uint8)
        rgba[..., 0] = 255  # red, half of it transparent
        rgba[:, :8, 3] = 255
        save_png(tmp_path / "train" / f"r_{i}.png", rgba)
        c2w = np.linalg.inv(cam.viewmat.double().numpy()) @ np.diag([1.0, -1, -1, 1])  # OpenCV -> OpenGL
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": c2w.tolist()})
    fx = float(raw.cameras[0].K[0, 0])
    meta = {"camera_angle_x": 2 * np.arctan(8 / fx), "frames": frames}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    return tmp_path


def test_transforms_blender_rgba(tmp_path):
    raw = load_synthetic(n_views=3, resolution=16, seed=1)
    root = _blender_scene(tmp_path)
    s = load_scene("transforms", str(root), test_every=0, normalize=False, background=(0.0, 0.0, 1.0))
    assert [c.name for c in s.train] == ["train/r_0.png", "train/r_1.png", "train/r_2.png"]
    for got, want in zip(s.train, raw.cameras):
        assert torch.allclose(got.viewmat, want.viewmat, atol=1e-5)
        assert torch.allclose(got.K, want.K, atol=1e-4)
    img = s.train[0].image
    assert torch.allclose(img[:, :8], torch.tensor([1.0, 0, 0]).expand(16, 8, 3))
    assert torch.allclose(img[:, 8:], torch.tensor([0.0, 0, 1.0]).expand(16, 8, 3))  # composited on background
    assert s.background == (0.0, 0.0, 1.0)


def test_transforms_non_numeric_value_names_file_frame_and_key(tmp_path):
    import json

    root = _blender_scene(tmp_path)
    meta = json.loads((root / "transforms.json").read_text())
    meta["frames"][1]["fl_x"] = "abc"
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"transforms.json: frame 1 fl_x='abc' is not a number \(fix: write a number"):
        load_scene("transforms", str(root), test_every=0)


def test_16bit_png_scaled_by_bit_depth(tmp_path):
    """The same raw value loads as the same intensity whatever the image's own maximum."""
    from PIL import Image

    for name, peak in (("dark", 200), ("bright", 60000)):
        a = np.full((4, 4), 200, dtype=np.uint16)
        a[0, 0] = peak
        Image.fromarray(a).save(tmp_path / f"{name}.png")
    dark, bright = (load_image(tmp_path / f"{n}.png") for n in ("dark", "bright"))
    want = 200 / 65535
    assert float(dark[1, 1, 0]) == pytest.approx(want) and float(bright[1, 1, 0]) == pytest.approx(want)


# ------------------------------------------------------------------------------------------------
# LLFF
# ------------------------------------------------------------------------------------------------


def _llff_scene(root: Path, n: int = 5, res: int = 24, downscale: int = 1) -> list[Camera]:
    raw = load_synthetic(n_views=n, resolution=res, seed=3)
    write_llff(root, raw.cameras, near_far=(1.0, 6.0))
    d = root / ("images" if downscale == 1 else f"images_{downscale}")
    for i, cam in enumerate(raw.cameras):
        img = cam.image.numpy()
        if downscale > 1:
            img = img.reshape(res // downscale, downscale, res // downscale, downscale, 3).mean(axis=(1, 3))
        save_png(d / f"IMG_{i:03d}.png", img)
    return raw.cameras


def test_llff_roundtrip(tmp_path):
    cams = _llff_scene(tmp_path)
    s = load_scene("llff", str(tmp_path), test_every=0, normalize=False)
    assert [c.name for c in s.train] == [f"IMG_{i:03d}.png" for i in range(5)]
    for got, want in zip(s.train, cams):
        assert torch.allclose(got.viewmat, want.viewmat, atol=1e-5)
        assert torch.allclose(got.K, want.K, atol=1e-4)
        assert torch.allclose(got.image, want.image, atol=1 / 255)
    # normalised + downscaled: K scales with the image, centres are the similarity image
    s2 = load_scene("llff", str(tmp_path), test_every=0, max_side=12)
    assert s2.train[0].image.shape == (12, 12, 3)
    assert torch.allclose(s2.train[0].K, cams[0].K * torch.tensor([[0.5], [0.5], [1.0]]), atol=1e-4)
    assert s2.extent == pytest.approx(1.0)


def test_llff_downscaled_images_dir(tmp_path):
    cams = _llff_scene(tmp_path, downscale=2)
    s = load_scene("llff", str(tmp_path), test_every=0, normalize=False, images_dir="images_2")
    assert s.train[0].width == 12
    assert torch.allclose(s.train[0].K, cams[0].K * torch.tensor([[0.5], [0.5], [1.0]]), atol=1e-4)


def test_llff_nonfinite_pose(tmp_path):
    _llff_scene(tmp_path, n=3, res=8)
    pb = np.load(tmp_path / "poses_bounds.npy")
    pb[1, 3] = np.nan
    np.save(tmp_path / "poses_bounds.npy", pb)
    with pytest.raises(ValueError, match="non-finite"):
        load_scene("llff", str(tmp_path))


# ------------------------------------------------------------------------------------------------
# synthetic
# ------------------------------------------------------------------------------------------------


def test_synthetic_deterministic_and_nontrivial():
    a = load_scene("synthetic", None, n_views=8, resolution=32, seed=0)
    b = load_scene("synthetic", None, n_views=8, resolution=32, seed=0)
    c = load_scene("synthetic", None, n_views=8, resolution=32, seed=1)
    assert len(a.train) == 7 and len(a.test) == 1
    for x, y in zip(a.train + a.test, b.train + b.test):
        assert torch.equal(x.image, y.image) and torch.equal(x.viewmat, y.viewmat)
    assert torch.equal(a.points, b.points) and torch.equal(a.point_colors, b.point_colors)
    assert not torch.equal(a.train[0].image, c.train[0].image)
    imgs = torch.stack([cam.image for cam in a.train])
    assert float(imgs.std()) > 0.1
    fg = (imgs.sum(-1) > 0.02).float().mean()
    assert 0.2 < float(fg) < 0.9  # objects on a black background
    assert 2000 <= len(a.points) <= 5000
    assert a.extent == pytest.approx(1.0)


def test_synthetic_default_size():
    raw = load_synthetic(max_images=2)  # defaults: 48 views at 128 px
    assert len(raw.cameras) == 2 and raw.cameras[0].image.shape == (128, 128, 3)
    assert raw.cameras[-1].name == "view_047"


def test_synthetic_points_on_surfaces():
    raw = load_synthetic(n_views=4, resolution=64, seed=2)
    world = raw.extras["world"]
    pts = torch.tensor(raw.points)
    for cam in raw.cameras:
        img, depth = world.render(cam.K.numpy(), cam.viewmat.numpy(), 64, 64, supersample=2)
        uv, z = project(cam, pts)
        ok = inside(cam, uv, z)
        ij = uv[ok].floor().long()
        pix = torch.tensor(img)[ij[:, 1], ij[:, 0]]
        assert float((pix.sum(-1) > 0.02).float().mean()) > 0.98  # surface points land on the objects (2x2 rays/pixel)
        d = torch.tensor(depth)[ij[:, 1], ij[:, 0]]
        vis = (d - z[ok]).abs() < 0.01 * z[ok]  # visible: the first hit is the point itself (within 1%)
        assert int(vis.sum()) > 200
        col = torch.tensor(raw.point_colors)[ok][vis]
        # compare against the (smooth) colour at the pixel centre, allowing for in-pixel variation
        assert float((pix[vis] - col).abs().mean()) < 0.03
    # through load_scene (normalised) the points still project onto coloured pixels
    s = load_scene("synthetic", None, n_views=4, resolution=64, seed=2, test_every=0)
    cam = s.train[0]
    uv, z = project(cam, s.points)
    ok = inside(cam, uv, z)
    ij = uv[ok].floor().long()
    assert float((cam.image[ij[:, 1], ij[:, 0]].sum(-1) > 0.02).float().mean()) > 0.97


# ------------------------------------------------------------------------------------------------
# preprocessing
# ------------------------------------------------------------------------------------------------


def test_split_and_train_indices():
    assert split_indices(10, 8) == ([1, 2, 3, 4, 5, 6, 7, 9], [0, 8])
    assert split_indices(3, 0) == ([0, 1, 2], [])
    s = load_scene("synthetic", None, n_views=10, resolution=8, test_every=8, train_indices=[0, 7, 3])
    assert [c.name for c in s.train] == ["view_001", "view_009", "view_004"]
    assert [c.name for c in s.test] == ["view_000", "view_008"]
    with pytest.raises(IndexError):
        load_scene("synthetic", None, n_views=10, resolution=8, train_indices=[8])
    with pytest.raises(B3dgsError, match=r"data.train_indices=\[-1\] is invalid"):  # refused before the scene loads
        load_scene("synthetic", None, n_views=10, resolution=8, train_indices=[-1])


def test_bounds_rules():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(1000, 3))
    pts[0] = 1e6  # outlier ignored by the percentiles
    lo, hi = compute_bounds(np.eye(4)[None], pts)
    assert np.all(hi < 4) and np.all(lo > -4)
    # no points: cube around the look-at point, half-size = 0.5 x median camera distance to it
    raw = load_synthetic(n_views=6, resolution=8)
    V = np.stack([c.viewmat.double().numpy() for c in raw.cameras])
    p, ok = look_at_point(V)
    assert ok and np.allclose(p, [0, 0, 0.35], atol=1e-6)
    lo, hi = compute_bounds(V, None)
    dist = np.median([float(c.center.double().sub(torch.tensor(p)).norm()) for c in raw.cameras])
    assert np.allclose((lo + hi) / 2, p) and np.allclose(hi - lo, dist, atol=1e-5)



def test_look_at_fallback_forward_facing():
    # parallel / slightly diverging optical axes (forward-facing): the box goes in front of the rig
    V = []
    for x in np.linspace(-1, 1, 5):
        a = 0.02 * x  # diverging yaw
        R = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])  # world->camera
        v = np.eye(4)
        v[:3, :3] = R
        v[:3, 3] = -R @ np.array([x, 0.0, 0.0])
        V.append(v)
    V = np.stack(V)
    p, ok = look_at_point(V)
    assert not ok and p[2] > 0.5  # in front (+z), not behind the cameras
    p, ok = look_at_point(V, fallback_depth=4.0)
    assert not ok and np.allclose(p, [0, 0, 4.0], atol=1e-6)
    lo, hi = compute_bounds(V, None, fallback_depth=4.0)
    assert lo[2] > 0 and np.all(lo < p) and np.all(p < hi)


# ------------------------------------------------------------------------------------------------
# errors
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["colmap", "transforms", "llff"])
def test_missing_path(tmp_path, kind):
    with pytest.raises(B3dgsError, match=r"data.path=.*nope does not exist \(fix: pass data.path="):
        load_scene(kind, str(tmp_path / "nope"))
    with pytest.raises(B3dgsError, match=r"(does not exist|has no) .*\(fix: "):
        load_scene(kind, str(tmp_path))  # exists but empty
    with pytest.raises(B3dgsError, match=rf"data={kind} reads a scene folder, and data.path is not set"):
        load_scene(kind, None)


def test_unknown_kind():
    with pytest.raises(ValueError, match="data.kind=nerf is not a scene format"):
        load_scene("nerf", "/tmp")


def test_corrupt_image(tmp_path):
    _llff_scene(tmp_path, n=3, res=8)
    (tmp_path / "images" / "IMG_001.png").write_bytes(b"\x89PNG\r\n\x1a\nthis is not a png")
    with pytest.raises(ValueError, match="IMG_001.png"):
        load_scene("llff", str(tmp_path))
    bad = tmp_path / "x.jpg"
    bad.write_bytes(b"garbage")
    with pytest.raises(ValueError, match="x.jpg"):
        load_image(bad)


def test_missing_image_file(tmp_path):
    _blender_scene(tmp_path)
    (tmp_path / "train" / "r_1.png").unlink()
    with pytest.raises(B3dgsError, match=r"r_1.*does not exist.*\(fix: restore the image"):
        load_scene("transforms", str(tmp_path))


# ------------------------------------------------------------------------------------------------
# images and the pycolmap/PIL import-order hazard
# ------------------------------------------------------------------------------------------------


def test_png_roundtrip(tmp_path):
    from PIL import Image

    rng = np.random.default_rng(0)
    for arr in (
        rng.integers(0, 256, (7, 11, 3), dtype=np.uint8),
        rng.integers(0, 256, (5, 4), dtype=np.uint8),
        rng.integers(0, 256, (3, 9, 4), dtype=np.uint8),
    ):
        p = save_png(tmp_path / "x.png", arr)
        with Image.open(p) as im:
            assert np.array_equal(np.asarray(im), arr)
    t = torch.rand(6, 5, 3)
    save_png(tmp_path / "t.png", t)
    back = load_image(tmp_path / "t.png")
    assert np.abs(back - t.numpy()).max() <= 0.5 / 255 + 1e-6
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temp files left
    with pytest.raises(ValueError):
        encode_png(np.zeros((4, 4, 2)))


def test_16bit_png_roundtrips(tmp_path):
    """uint16 gray images are written as 16-bit PNGs (PIL) and read back exactly (value / 65535)."""
    from PIL import Image

    a = np.random.default_rng(1).integers(0, 65536, (5, 7), dtype=np.uint16)
    p = save_png(tmp_path / "d.png", a)
    with Image.open(p) as im:
        assert im.mode.startswith("I") and np.array_equal(np.asarray(im).astype(np.uint16), a)
    back = load_image(p)
    assert back.shape == (5, 7, 3) and np.allclose(back[..., 0], a / 65535.0, atol=1e-7)
    with pytest.raises(ValueError, match="uint8"):
        encode_png(np.zeros((4, 4, 3), dtype=np.uint16))  # PIL writes no 16-bit RGB PNG


def test_load_image_resize(tmp_path):
    img = np.zeros((40, 60, 3))
    img[:, 30:] = 1.0
    save_png(tmp_path / "a.png", img)
    out = load_image(tmp_path / "a.png", max_side=30)
    assert out.shape == (20, 30, 3) and out.dtype == np.float32
    assert np.allclose(out[:, :15], 0) and np.allclose(out[:, 15:], 1)  # area filter, no ringing
    assert load_image(tmp_path / "a.png", max_side=100).shape == (40, 60, 3)  # never upscales


def test_fit_size_is_the_one_long_side_rule():
    """b3dgs.types.fit_size / Camera.fit: data loading and scoring never upscale (at least 1 px), b3dgs-render's
    frames fit max_side both ways (at least 8 px), the viewer sizes a window's aspect."""
    import torch

    from b3dgs.types import Camera, fit_size

    assert fit_size(60, 40, 30) == (30, 20) and fit_size(60, 40, 100) == (60, 40) and fit_size(60, 40, None) == (60, 40)
    assert fit_size(1000, 3, 100) == (100, 1)
    assert fit_size(60, 40, 120, upscale=True) == (120, 80) and fit_size(600, 10, 64, upscale=True, min_side=8) == (64, 8)
    with pytest.raises(ValueError, match="max_side must be positive"):
        fit_size(60, 40, 0)
    K = torch.tensor([[50.0, 0, 30], [0, 50.0, 20], [0, 0, 1]])
    cam = Camera("c", K, torch.eye(4), 60, 40, torch.rand(40, 60, 3))
    small = cam.fit(30)
    assert (small.width, small.height, tuple(small.image.shape)) == (30, 20, (20, 30, 3))
    assert torch.allclose(small.K, torch.tensor([[25.0, 0, 15], [0, 25.0, 10], [0, 0, 1]]))
    assert cam.fit(None) is cam and cam.fit(64) is cam and cam.fit(64, upscale=True).width == 64


_ORDER_SCRIPT = """
import sys
{first}
{second}
import numpy as np
from b3dgs.data.images import save_png
arr = np.random.default_rng(0).integers(0, 256, (33, 47, 3), dtype=np.uint8)
save_png(sys.argv[1], arr)
np.save(sys.argv[2], arr)
from PIL import Image  # PIL decoding after both imports works too
assert np.array_equal(np.asarray(Image.open(sys.argv[1])), arr)
"""


@pytest.mark.parametrize(
    "first,second",
    [("import pycolmap", "import b3dgs.data"), ("import b3dgs.data", "import pycolmap")],
    ids=["pycolmap-first", "b3dgs-first"],
)
def test_import_order_save_png(tmp_path, first, second):
    from PIL import Image

    script = _ORDER_SCRIPT.format(first=first, second=second)
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    out, ref = tmp_path / "o.png", tmp_path / "o.npy"
    proc = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script), str(out), str(ref)],
        env=env, capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    with Image.open(out) as im:
        assert np.array_equal(np.asarray(im), np.load(ref))


def test_pycolmap_not_imported_eagerly():
    code = (
        "import sys, b3dgs.data, b3dgs.data.colmap, b3dgs.data.datamodule; "
        "from b3dgs.data import load_scene; load_scene('synthetic', None, n_views=2, resolution=4); "
        "assert 'pycolmap' not in sys.modules, 'pycolmap imported eagerly'"
    )
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]


# ------------------------------------------------------------------------------------------------
# DataModule
# ------------------------------------------------------------------------------------------------


def test_datamodule():
    import lightning as L

    from b3dgs.data.datamodule import SceneDataModule

    dm = SceneDataModule(kind="synthetic", path=None, max_side=16, test_every=4, background=[0, 0, 0],
                         name="syn", n_views=12, resolution=16)
    dm.setup("fit")
    assert dm.scene.name == "syn" and len(dm.scene.train) == 9 and len(dm.scene.test) == 3

    def epoch_order(loader):
        out = []
        for cam in loader:
            assert isinstance(cam, Camera) and cam.image.shape == (16, 16, 3)
            out.append(cam.name)
        return out

    L.seed_everything(0, verbose=False)
    loader = dm.train_dataloader()
    e1, e2 = epoch_order(loader), epoch_order(loader)
    assert sorted(e1) == sorted(c.name for c in dm.scene.train) == sorted(e2)
    assert e1 != e2  # reshuffled each epoch
    L.seed_everything(0, verbose=False)
    assert epoch_order(dm.train_dataloader()) == e1  # reproducible from the global seed
    assert [c.name for c in dm.val_dataloader()] == [c.name for c in dm.scene.test]
    assert [c.name for c in dm.test_dataloader()] == [c.name for c in dm.scene.test]


@pytest.mark.parametrize("from_train_only", [False, True])
def test_select_train_is_the_scene_a_second_read_would_give(monkeypatch, from_train_only):
    """An active-view study reads its scene once (the pool, then its initial views from the same read): the selected
    scene is the one a data module with ``train_indices`` would load, and nothing is read a second time."""
    import b3dgs.data.datamodule as dmod
    from b3dgs.errors import B3dgsError
    from b3dgs.lifecycle import data_module

    args = dict(kind="synthetic", max_side=16, test_every=4, n_views=16, resolution=16, name="syn")
    reads = []
    read_raw = dmod.read_raw  # the read from disk (read_scene then preprocesses what it gave)
    monkeypatch.setattr(dmod, "read_raw", lambda *a, **k: reads.append(1) or read_raw(*a, **k))
    full = data_module(dmod.SceneDataModule(**args), keep_raw=True)
    sel = full.select_train([0, 3, 5], init_points_from_train_only=from_train_only)
    assert len(reads) == 1
    ref = dmod.SceneDataModule(**args, train_indices=[0, 3, 5], init_points_from_train_only=from_train_only)
    ref.setup("fit")
    a, b = sel.scene, ref.scene
    assert a.name == b.name == "syn" and a.extent == b.extent
    for x, y in ((a.train, b.train), (a.test, b.test), (a.candidates, b.candidates)):
        assert [c.name for c in x] == [c.name for c in y]
        assert all(torch.equal(c.viewmat, d.viewmat) and torch.equal(c.K, d.K) for c, d in zip(x, y))
        assert all((c.image is None and d.image is None) or torch.equal(c.image, d.image) for c, d in zip(x, y))
    assert torch.equal(a.points, b.points) and torch.equal(a.point_colors, b.point_colors)
    assert sorted(c.name for c in full.scene.train) == sorted(c.name for c in [*a.train, *a.candidates])
    with pytest.raises(B3dgsError, match="keep_raw"):
        data_module(dmod.SceneDataModule(**args)).select_train([0])


# ------------------------------------------------------------------------------------------------
# input checks: intrinsics, mixed sizes, near plane, damaged COLMAP files
# ------------------------------------------------------------------------------------------------


def _transforms_scene(root: Path, meta_keys: dict, sizes: list[tuple[int, int]], scale: float = 1.0) -> Path:
    """A transforms.json scene of synthetic poses (positions x ``scale``) with one image per size."""
    import json

    raw = load_synthetic(n_views=len(sizes), resolution=16, seed=2)
    frames = []
    for i, (cam, (w, h)) in enumerate(zip(raw.cameras, sizes)):
        save_png(root / f"f_{i}.png", np.full((h, w, 3), 0.5))
        c2w = np.linalg.inv(cam.viewmat.double().numpy()) @ np.diag([1.0, -1, -1, 1])
        c2w[:3, 3] *= scale
        frames.append({"file_path": f"f_{i}.png", "transform_matrix": c2w.tolist()})
    (root / "transforms.json").write_text(json.dumps({**meta_keys, "frames": frames}))
    return root


@pytest.mark.parametrize("keys,text", [
    ({"fl_x": 0.0, "fl_y": 0.0, "cx": 8, "cy": 8, "w": 16, "h": 16}, "focal lengths fx=0"),
    ({"fl_x": -20.0, "fl_y": -20.0, "cx": 8, "cy": 8, "w": 16, "h": 16}, "focal lengths fx=-20"),
    ({"fl_x": float("nan"), "cx": 8, "cy": 8, "w": 16, "h": 16}, "focal lengths fx=nan"),
    ({"fl_x": 20.0, "cx": 40, "cy": 8, "w": 16, "h": 16}, "principal point (40, 8) outside"),
])
def test_bad_intrinsics_refused(tmp_path, keys, text):
    from b3dgs.errors import B3dgsError

    _transforms_scene(tmp_path, keys, [(16, 16)] * 4)
    with pytest.raises(B3dgsError, match=re.escape(text)) as ei:
        load_scene("transforms", str(tmp_path), test_every=0)
    assert "(fix: " in str(ei.value)


def test_mixed_sizes_without_wh_scale_shared_intrinsics(tmp_path, caplog):
    from b3dgs.errors import B3dgsError

    keys = {"fl_x": 40.0, "fl_y": 40.0, "cx": 16.0, "cy": 12.0}  # fit 32x24
    (tmp_path / "a").mkdir()
    _transforms_scene(tmp_path / "a", keys, [(32, 24), (16, 12), (32, 24), (16, 12)])
    with caplog.at_level(logging.WARNING):
        s = load_scene("transforms", str(tmp_path / "a"), test_every=0, normalize=False)
    by_w = {c.width: c.K for c in s.train}
    assert torch.allclose(by_w[32], torch.tensor([[40.0, 0, 16], [0, 40, 12], [0, 0, 1]]))
    assert torch.allclose(by_w[16], torch.tensor([[20.0, 0, 8], [0, 20, 6], [0, 0, 1]]))
    assert "no w/h" in caplog.text
    (tmp_path / "b").mkdir()
    _transforms_scene(tmp_path / "b", keys, [(32, 24), (16, 20), (32, 24)])  # not a rescale of 32x24
    with pytest.raises(B3dgsError, match="add .w. and .h."):
        load_scene("transforms", str(tmp_path / "b"), test_every=0)


def test_near_plane_guard(tmp_path, caplog):
    from b3dgs.errors import B3dgsError

    keys = {"fl_x": 20.0, "cx": 8, "cy": 8, "w": 16, "h": 16}
    _transforms_scene(tmp_path, keys, [(16, 16)] * 6, scale=1e-4)
    with pytest.raises(B3dgsError, match=r"near plane.*fix: data.normalize=true"):
        load_scene("transforms", str(tmp_path), test_every=0, normalize=False)
    s = load_scene("transforms", str(tmp_path), test_every=0, normalize=True)  # the fix works
    assert s.extent == pytest.approx(1.0)
    with caplog.at_level(logging.WARNING):  # a larger near plane than the depth warns first, then refuses
        load_scene("transforms", str(tmp_path), test_every=0, near_plane=0.05)
    assert "close to the renderer's near plane" in caplog.text
    with pytest.raises(B3dgsError, match="near plane"):
        load_scene("transforms", str(tmp_path), test_every=0, near_plane=1.0)


def test_load_scene_refuses_bad_max_side_and_background():
    from b3dgs.errors import B3dgsError

    for bad in (0, -3):
        with pytest.raises(B3dgsError, match="max_side"):
            load_scene("synthetic", None, max_side=bad, n_views=4, resolution=8)
    with pytest.raises(B3dgsError, match="background"):
        load_scene("synthetic", None, background=(2.0, -1.0, 0.5), n_views=4, resolution=8)


def _damaged_model(tmp_path: Path, name: str, keep) -> Path:
    import shutil

    d = tmp_path / "sparse" / "0"
    shutil.copytree(HEAD / "sparse" / "0", d)
    p = d / name
    data = p.read_bytes()
    p.chmod(0o644)
    p.write_bytes(data[: keep(len(data))])
    return d


@needs_head
@pytest.mark.parametrize("name,keep,text", [
    ("points3D.bin", lambda n: n // 2, "truncated"),
    ("points3D.bin", lambda n: 12, "3D points"),
    ("images.bin", lambda n: n - 10, "truncated"),
    ("cameras.bin", lambda n: 10, "truncated"),
    ("cameras.bin", lambda n: 4, "shorter than its 8-byte header"),
])
def test_damaged_colmap_files_refused_in_one_line(tmp_path, name, keep, text):
    from b3dgs.data.colmap import check_colmap_binary
    from b3dgs.errors import B3dgsError

    check_colmap_binary(HEAD / "sparse" / "0")  # the intact model passes
    d = _damaged_model(tmp_path, name, keep)
    with pytest.raises(B3dgsError, match=text) as ei:
        check_colmap_binary(d)
    assert name in str(ei.value)
    (tmp_path / "images").symlink_to(HEAD / "images")
    with pytest.raises(B3dgsError, match=text):  # the loader refuses it in the same line
        load_scene("colmap", str(tmp_path), max_side=16)


def test_initial_scale_knn_matches_brute_force():
    """cKDTree's k-NN mean distances equal the brute-force ones bit for bit (duplicates and tiny sets too)."""
    from b3dgs.init import knn_mean_dist

    g = torch.Generator().manual_seed(0)
    pts = torch.rand(3000, 3, generator=g)
    pts[10] = pts[11]  # a duplicate point: distance 0 to its twin, not to itself
    d = torch.cdist(pts.double(), pts.double())
    d.fill_diagonal_(float("inf"))
    want = d.topk(3, largest=False).values.mean(-1).float()
    assert torch.equal(knn_mean_dist(pts), want)
    assert float(knn_mean_dist(pts)[10]) > 0
    assert torch.equal(knn_mean_dist(pts[:2]), torch.full((2,), float((pts[0] - pts[1]).double().norm())))
    assert knn_mean_dist(pts[:1]).tolist() == [1.0]


def test_sector_split_holds_out_one_contiguous_side(tmp_path):
    """data.test_split=sector (issue 42's OOD split): the test views are the cameras farthest along one principal
    direction, a contiguous arc of a ring that no training camera sees from; the default split is unchanged."""
    import math

    from b3dgs.data import load_scene
    from b3dgs.data.scene import sector_split
    from b3dgs.errors import B3dgsError

    ang = [2 * math.pi * i / 24 for i in range(24)]
    ring = np.array([[3 * math.cos(a), 2 * math.sin(a), 0.1 * math.cos(3 * a)] for a in ang])  # longest along x
    train, test = sector_split(ring, 0.125)
    assert len(test) == 3 and sorted(train + test) == list(range(24))
    assert test == [0, 1, 23]  # the arc around +x, contiguous on the ring
    assert min(ring[test, 0]) > max(ring[train, 0])
    with pytest.raises(B3dgsError, match=r"data.test_fraction=1.0 is invalid: it must be a fraction in \(0, 1\)"):
        load_scene("synthetic", None, max_side=16, n_views=16, test_split="sector", test_fraction=1.0)
    a = load_scene("synthetic", None, max_side=16, n_views=16)
    b = load_scene("synthetic", None, max_side=16, n_views=16, test_split="sector", test_fraction=0.25)
    names = sorted(c.name for c in a.train + a.test)
    assert [c.name for c in a.test] == [names[0], names[8]]  # the default: every 8th view in name order
    assert len(b.test) == 4 and not {c.name for c in b.test} & {c.name for c in b.train}
    cent = lambda cams: np.stack([c.center.double().numpy() for c in cams])  # noqa: E731
    u = np.linalg.svd(cent(b.train + b.test) - cent(b.train + b.test).mean(0))[2][0]
    u = u if u[np.argmax(np.abs(u))] > 0 else -u
    assert (cent(b.test) @ u).min() > (cent(b.train) @ u).max()
    with pytest.raises(B3dgsError, match="data.test_split=diagonal is invalid"):
        load_scene("synthetic", None, max_side=16, n_views=16, test_split="diagonal")
    assert a.test_groups is None and b.test_groups is None
    # sector+interleaved: the sector and every 8th view of the rest, held out from one model, each kind named
    c = load_scene("synthetic", None, max_side=16, n_views=16, test_split="sector+interleaved", test_fraction=0.25)
    g = c.test_groups
    assert set(g["sector"]) == {x.name for x in b.test}
    assert set(g["interleaved"]) == {names[0], names[8]} - set(g["sector"]) and g["interleaved"]
    assert {x.name for x in c.test} == set(g["sector"]) | set(g["interleaved"])
    assert not {x.name for x in c.test} & {x.name for x in c.train} and len(c.train) + len(c.test) == 16


def test_cameras_at_one_point_are_refused():
    """Issue 46 (degenerate geometry): views whose centres all coincide (one pose repeated, or a rotation-only
    panorama) have no parallax and give the scene extent 0; preprocessing refuses them in one line. A scene whose
    cameras are spread (the synthetic ring) and one of two distinct centres pass."""
    import dataclasses

    from b3dgs.data.scene import preprocess

    raw = load_synthetic(n_views=8, resolution=8)
    preprocess(raw)  # spread cameras: accepted
    same = [dataclasses.replace(c, viewmat=raw.cameras[0].viewmat.clone()) for c in raw.cameras]
    with pytest.raises(B3dgsError, match=r"all 8 cameras are at one point .*extent is 0") as ei:
        preprocess(dataclasses.replace(raw, cameras=same))
    assert ei.value.fix and "different positions" in ei.value.fix
    # rotation only: every camera at the first one's centre, looking elsewhere
    c0 = raw.cameras[0].center.double()
    pano = []
    for c in raw.cameras:
        v = c.viewmat.clone().double()
        v[:3, 3] = -v[:3, :3] @ c0
        pano.append(dataclasses.replace(c, viewmat=v.float()))
    with pytest.raises(B3dgsError, match="at one point"):
        preprocess(dataclasses.replace(raw, cameras=pano))


def test_center64_is_the_fixed_order_float64_centre_on_any_cpu():
    """Camera.center64 (support distances in the report and bench.active_view) is -Rᵀt summed in float64 in a fixed
    order, so it equals plain Python floats' arithmetic, which no CPU's matmul kernel can change; ``center`` (float32
    matmul, kept for the renders' bits) lies within float32 round-off of it."""
    g = torch.Generator().manual_seed(3)
    for _ in range(20):
        q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
        vm = torch.eye(4)
        vm[:3, :3], vm[:3, 3] = q.float(), torch.randn(3, generator=g) * 5
        cam = Camera("c", torch.eye(3), vm, 4, 4)
        R, t = vm[:3, :3].double().tolist(), vm[:3, 3].double().tolist()
        want = [-(R[0][i] * t[0] + R[1][i] * t[1] + R[2][i] * t[2]) for i in range(3)]
        got = cam.center64
        assert got.dtype == np.float64 and got.tolist() == want
        assert np.allclose(cam.center.double().numpy(), got, rtol=0, atol=1e-5)
