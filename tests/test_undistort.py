"""data.undistort: the distortion models against pycolmap's, the undistorted image of a synthetic pattern against its
pinhole render, the pinhole K' (no sample outside the source, the smallest such scale), the identity, the refusals, and
fox: the default load is the pre-change load, bit for bit, and never touches the images."""
from __future__ import annotations

import hashlib
import json
import logging

import numpy as np
import pytest
import torch

from b3dgs.data import load_scene
from b3dgs.data.images import import_pycolmap, save_png
from b3dgs.data.scene import FrameSpec, materialize
from b3dgs.data.transforms import load_transforms
from b3dgs.data.undistort import FISHEYE, MODELS, Distortion, _source, distort, pinhole_scale, sampling_grid, \
    undistort_image
from b3dgs.errors import B3dgsError
from conftest import SHARED

FOX = SHARED / "data" / "fox"
needs_fox = pytest.mark.skipif(not (FOX / "transforms.json").is_file(), reason="fox not available")

#: moderate coefficients per model (fox's own for transforms.json's OPENCV)
COEFFS = {
    "SIMPLE_RADIAL": (-0.1,),
    "RADIAL": (0.08, -0.03),
    "OPENCV": (-0.12, 0.03, 0.002, -0.001),
    "FULL_OPENCV": (0.05, 0.01, 0.001, 0.002, 0.003, 0.02, 0.01, 0.001),
    "OPENCV_FISHEYE": (0.05, -0.01, 0.002, 0.001),
    "SIMPLE_RADIAL_FISHEYE": (0.03,),
    "RADIAL_FISHEYE": (0.03, -0.01),
    "THIN_PRISM_FISHEYE": (0.02, 0.003, 0.001, -0.001, 0.001, 0.0005, 0.001, -0.002),
    "NERFSTUDIO_OPENCV": (0.0578421, -0.0805099, 0.01, 0.005, -0.000980296, 0.00015575),
}
W, H = 96, 64
K = np.array([[80.0, 0.0, 47.0], [0.0, 82.0, 33.0], [0.0, 0.0, 1.0]])


def test_every_model_has_test_coefficients():
    assert set(COEFFS) == set(MODELS) and all(len(COEFFS[m]) == len(MODELS[m]) for m in MODELS)


@pytest.mark.parametrize("model", [m for m in MODELS if m != "NERFSTUDIO_OPENCV"])
def test_forward_distortion_is_colmaps(model):
    """distort() is COLMAP's projection (pycolmap's img_from_cam), coefficient order included."""
    pycolmap = import_pycolmap()
    cam = pycolmap.Camera.create_from_model_name(1, model, 80.0, W, H)
    assert cam.params_info.split(", ")[-len(MODELS[model]):] == list(MODELS[model])
    cam.params = list(cam.params)[:len(cam.params) - len(MODELS[model])] + list(COEFFS[model])
    xy = np.random.default_rng(0).uniform(-0.6, 0.6, (200, 2))
    ref = cam.img_from_cam(np.c_[xy, np.ones(len(xy))])
    xd, yd = distort(Distortion(model, COEFFS[model]), xy[:, 0], xy[:, 1])
    mine = np.c_[cam.focal_length_x * xd + cam.principal_point_x, cam.focal_length_y * yd + cam.principal_point_y]
    assert np.abs(mine - ref).max() < 1e-10


def test_nerfstudio_opencv_is_the_r8_polynomial():
    k1, k2, k3, k4, p1, p2 = COEFFS["NERFSTUDIO_OPENCV"]
    x, y = np.array([0.3, -0.2]), np.array([0.1, 0.4])
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3 + k4 * r2**4
    xd, yd = distort(Distortion("NERFSTUDIO_OPENCV", COEFFS["NERFSTUDIO_OPENCV"]), x, y)
    assert np.allclose(xd, x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), atol=1e-15)
    assert np.allclose(yd, y * radial + 2 * p2 * x * y + p1 * (r2 + 2 * y * y), atol=1e-15)


def _pattern(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth pattern on the normalised image plane (float64 (..., 3) in [0, 1])."""
    return np.stack([0.5 + 0.25 * np.sin(6 * x) + 0.2 * np.cos(5 * y), 0.5 + 0.4 * np.sin(4 * x + 3 * y),
                     0.5 + 0.4 * np.cos(7 * x * y + 2 * x)], -1)


def _undistort_points(d: Distortion, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Newton's inverse of distort() (float64, numerical Jacobian): the test's reference, not the loader's code."""
    x, y = xd.copy(), yd.copy()
    h = 1e-7
    for _ in range(30):
        fx, fy = distort(d, x, y)
        ax, ay = distort(d, x + h, y)
        bx, by = distort(d, x, y + h)
        j11, j12, j21, j22 = (ax - fx) / h, (bx - fx) / h, (ay - fy) / h, (by - fy) / h
        ex, ey = fx - xd, fy - yd
        det = j11 * j22 - j12 * j21
        x, y = x - (j22 * ex - j12 * ey) / det, y - (-j21 * ex + j11 * ey) / det
    assert np.abs(np.stack(distort(d, x, y)) - np.stack([xd, yd])).max() < 1e-12
    return x, y


@pytest.mark.parametrize("model", list(MODELS))
def test_undistorted_pattern_matches_its_pinhole_render(model):
    """Render a pattern through the distorted lens (float64 inverse), undistort it, compare with the pattern rendered
    through the pinhole K' directly."""
    d = Distortion(model, COEFFS[model])
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    x, y = _undistort_points(d, (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1])
    distorted = _pattern(x, y).astype(np.float32)
    out, Kp = undistort_image(distorted, K, d)
    want = _pattern((u - Kp[0, 2]) / Kp[0, 0], (v - Kp[1, 2]) / Kp[1, 1])
    assert out.shape == (H, W, 3) and out.dtype == np.float32
    err = np.abs(out - want).max()
    ignored = np.abs(distorted - _pattern((u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1])).max()
    assert err < 5e-3 and err < 0.2 * ignored, (err, ignored)  # the lens did move the pattern; undistortion undoes it
    assert Kp[0, 0] / K[0, 0] == pytest.approx(Kp[1, 1] / K[1, 1], rel=1e-12) and np.array_equal(Kp[:2, 2], K[:2, 2])


@pytest.mark.parametrize("model", list(MODELS))
def test_k_prime_samples_inside_the_source_and_is_the_smallest_that_does(model):
    d = Distortion(model, COEFFS[model])
    Kp, grid = sampling_grid(d, K, W, H)
    assert grid.shape == (1, H, W, 2) and grid.dtype == torch.float32
    assert float(grid.abs().max()) <= 1.0
    s = Kp[0, 0] / K[0, 0]
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    U, V = _source(d, K, s, u, v)
    assert U.min() >= 0.5 - 1e-6 and U.max() <= W - 0.5 + 1e-6 and V.min() >= 0.5 - 1e-6 and V.max() <= H - 0.5 + 1e-6
    U, V = _source(d, K, s * (1 - 1e-4), u, v)  # a wider view would sample outside
    assert U.min() < 0.5 or U.max() > W - 0.5 or V.min() < 0.5 or V.max() > H - 0.5


@pytest.mark.parametrize("model", list(MODELS))
def test_zero_coefficients_are_the_identity_for_perspective_models(model):
    img = np.random.default_rng(1).uniform(0, 1, (H, W, 3)).astype(np.float32)
    out, Kp = undistort_image(img, K, Distortion(model, (0.0,) * len(MODELS[model])))
    if model in FISHEYE:  # an equidistant lens, not a pinhole one: still undistorted (wider than tan)
        assert Kp[0, 0] < K[0, 0] and not np.array_equal(out, img)
        return
    assert np.array_equal(Kp, K) and out is img
    tiny = Distortion(model, (1e-12,) * len(MODELS[model]))  # through the grid: s = 1, the pixels themselves
    out, Kp = undistort_image(img, K, tiny)
    assert np.allclose(Kp, K, rtol=1e-8) and np.abs(out - img).max() < 1e-5


def test_refusals_are_one_line():
    with pytest.raises(B3dgsError, match="non-finite") as e:
        Distortion("OPENCV", (float("nan"), 0.0, 0.0, 0.0), where="COLMAP camera 3")
    assert "COLMAP camera 3" in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(B3dgsError, match="takes 4 coefficients"):
        Distortion("OPENCV", (0.1,))
    with pytest.raises(B3dgsError, match="cannot be undistorted"):
        Distortion("FOV", (0.5,))
    for coeffs in ((1000.0,), (-50.0,)):  # too strong a pincushion; a barrel that folds back even at 5x the focal
        with pytest.raises(B3dgsError, match=r"camera 7: .*too strong.*data\.undistort=false") as e:
            pinhole_scale(Distortion("SIMPLE_RADIAL", coeffs, where="camera 7"), K, W, H)
        assert "\n" not in str(e.value)


def test_frames_sharing_a_lens_share_one_grid_and_are_not_changed(tmp_path, monkeypatch):
    """materialize: one grid per (lens, K, size); the frames keep their lens and K (a second call reads the files
    and undistorts them again, identically: never an undistorted image undistorted twice)."""
    import b3dgs.data.undistort as und

    calls = []
    real = und.sampling_grid
    monkeypatch.setattr(und, "sampling_grid", lambda *a: calls.append(a[2:]) or real(*a))
    img = np.random.default_rng(2).uniform(0, 1, (H, W, 3))
    lens = Distortion("OPENCV", COEFFS["OPENCV"])
    frames = []
    for i in range(3):
        save_png(tmp_path / f"{i}.png", img)
        frames.append(FrameSpec(f"{i}", tmp_path / f"{i}.png", K.copy(), np.eye(4), W, H, lens))
    a = materialize(frames)
    assert calls == [(W, H)]
    half = materialize(frames, max_side=W // 2)
    assert calls == [(W, H), (W // 2, H // 2)]
    assert all(f.distortion is lens and np.array_equal(f.K, K) for f in frames)
    b = materialize(frames)
    assert all(torch.equal(x.image, y.image) and torch.equal(x.K, y.K) for x, y in zip(a, b))
    # resize first, then undistort with the resized K: the same lens at half the size gives (nearly) half the focal
    assert float(half[0].K[0, 0]) == pytest.approx(float(a[0].K[0, 0]) / 2, rel=2e-2)


def _write_transforms(root, frame_keys, top):
    (root / "images").mkdir(parents=True)
    frames = []
    for i in range(2):
        save_png(root / "images" / f"{i}.png", np.random.default_rng(i).uniform(0, 1, (H, W, 3)))
        c2w = np.eye(4)
        c2w[0, 3] = i
        frames.append({"file_path": f"images/{i}.png", "transform_matrix": c2w.tolist(), **frame_keys})
    (root / "transforms.json").write_text(json.dumps({"fl_x": 80.0, "fl_y": 82.0, "cx": 47.0, "cy": 33.0, "w": W,
                                                      "h": H, **top, "frames": frames}))


def test_transforms_fisheye_is_undistorted_by_default_and_bad_coefficients_refused(tmp_path, caplog):
    _write_transforms(tmp_path / "f", {}, {"camera_model": "OPENCV_FISHEYE", "k1": 0.05, "k2": -0.01})
    with caplog.at_level(logging.WARNING, logger="b3dgs.data"):
        s = load_transforms(tmp_path / "f")
    assert s.cameras[0].K[0, 0] < 80.0 and not [r for r in caplog.records if "distortion" in r.getMessage()]
    assert s.extras["distortion"] == {}
    off = load_transforms(tmp_path / "f", undistort=False)
    assert float(off.cameras[0].K[0, 0]) == 80.0 and off.extras["distortion"] == {"k1": 0.05, "k2": 0.01}
    _write_transforms(tmp_path / "n", {"k1": float("nan")}, {})
    load_transforms(tmp_path / "n")  # null: ignored, as before (never read as a lens)
    with pytest.raises(B3dgsError, match=r"transforms\.json frame 'images/0\.png'.*non-finite") as e:
        load_transforms(tmp_path / "n", undistort=True)
    assert "\n" not in str(e.value)
    _write_transforms(tmp_path / "e", {}, {"camera_model": "EQUIRECTANGULAR"})
    with pytest.raises(B3dgsError, match="EQUIRECTANGULAR cannot be undistorted"):
        load_transforms(tmp_path / "e", undistort=True)


def test_undistort_setting_is_checked_before_reading(tmp_path):
    from b3dgs.data.datamodule import SceneDataModule

    with pytest.raises(B3dgsError, match=r"data\.undistort=yes is invalid"):
        SceneDataModule(kind="synthetic", undistort="yes")
    with pytest.raises(B3dgsError, match=r"data\.undistort=true: data=synthetic has no lens distortion setting"):
        SceneDataModule(kind="synthetic", undistort=True)
    assert SceneDataModule(kind="synthetic", undistort=None).kind_kwargs == {}


def _digest(cameras) -> str:
    h = hashlib.sha256()
    for c in cameras:
        for t in (c.K, c.viewmat, c.image):
            h.update(np.ascontiguousarray(t.numpy()).tobytes())
        h.update(f"{c.name}{c.width}{c.height}".encode())
    return h.hexdigest()[:16]


@needs_fox
def test_fox_default_is_the_pre_change_load_and_never_touches_its_images(monkeypatch, caplog):
    """Archived fox runs reproduce bit for bit: the default (null) loads exactly what the loader gave before
    data.undistort existed (digest computed with the code of 6fd8f10), the same as data.undistort=false, without
    entering the undistortion; the warning now names data.undistort=true; true changes K and the images."""
    import b3dgs.data.scene as scene_mod

    def never(*a, **k):
        raise AssertionError("the default fox load must not undistort")

    monkeypatch.setattr(scene_mod, "undistort_image", never)
    with caplog.at_level(logging.WARNING, logger="b3dgs.data"):
        default = load_transforms(FOX, max_side=64)
    assert _digest(default.cameras) == "93f8f112859192e9"
    warnings = [r.getMessage() for r in caplog.records if "distortion" in r.getMessage()]
    assert len(warnings) == 1 and "k1=0.0578" in warnings[0] and "data.undistort=true undistorts them" in warnings[0]
    off = load_transforms(FOX, max_side=64, undistort=False)
    assert _digest(off.cameras) == "93f8f112859192e9"
    monkeypatch.undo()
    on = load_transforms(FOX, max_side=64, undistort=True)
    assert on.extras["distortion"] == {}
    for a, b in zip(on.cameras, default.cameras):
        assert torch.equal(a.viewmat, b.viewmat) and torch.equal(a.K[:2, 2], b.K[:2, 2])
        assert float(a.K[0, 0]) > float(b.K[0, 0]) and not torch.equal(a.image, b.image)
    s = load_scene("transforms", str(FOX), max_side=64, test_every=8)
    assert _digest(s.train[:1]) == _digest(load_scene("transforms", str(FOX), max_side=64, test_every=8,
                                                      undistort=False).train[:1])


def test_colmap_non_finite_coefficients_are_refused_unless_ignored(tmp_path):
    from test_data import _write_colmap

    _write_colmap(tmp_path, "OPENCV", [50.0, 50.0, 32.0, 24.0, float("nan"), 0.0, 0.0, 0.0], 64, 48, None)
    with pytest.raises(B3dgsError, match=r"COLMAP camera 1 \(image 'a\.png'\).*non-finite.*data\.undistort=false") as e:
        load_scene("colmap", str(tmp_path), test_every=0)
    assert "\n" not in str(e.value)
    assert load_scene("colmap", str(tmp_path), test_every=0, undistort=False).train[0].K[0, 0] == 50.0


def test_poses_only_reads_the_cameras_a_full_read_gives_without_a_pixel(tmp_path, monkeypatch):
    """Within poses_only no image is decoded; names, poses, sizes, the split and the extent equal a full read's
    (a fisheye scene: the full read undistorts, so K is the one thing that differs); outside it reads are full."""
    from b3dgs.data import images
    from b3dgs.data.scene import poses_only

    _write_transforms(tmp_path / "f", {}, {"camera_model": "OPENCV_FISHEYE", "k1": 0.05, "k2": -0.01})
    full = load_scene("transforms", tmp_path / "f", test_every=2)
    decoded = []
    real = images.load_image
    monkeypatch.setattr("b3dgs.data.scene.load_image", lambda *a, **k: decoded.append(a[0]) or real(*a, **k))
    with poses_only():
        light = load_scene("transforms", tmp_path / "f", test_every=2)
    assert decoded == []
    for a, b in zip(full.train + full.test, light.train + light.test, strict=True):
        assert (a.name, a.width, a.height) == (b.name, b.width, b.height) and torch.equal(a.viewmat, b.viewmat)
        assert b.image is None and a.image is not None
    assert light.extent == full.extent and [c.name for c in light.test] == [c.name for c in full.test]
    load_scene("transforms", tmp_path / "f")
    assert len(decoded) == 2  # the context ended: the next read decodes
