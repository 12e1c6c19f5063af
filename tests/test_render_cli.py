"""b3dgs-render: a trained synthetic run rendered along its test cameras and an interpolated loop, to PNG frames and an
MP4 (with the native-σ panel beside the RGB), and its one-line refusals."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from b3dgs.types import Camera
from b3dgs.viewer.modes import colormap_lut

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}


def cli(*args, cwd=ROOT):
    return subprocess.run([sys.executable, "-m", "b3dgs.render_cli", *args], capture_output=True, text=True,
                          timeout=600, cwd=cwd, env=ENV)


@pytest.fixture(scope="module")
def niw_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("render") / "niw"
    res = subprocess.run([sys.executable, "-m", "b3dgs.train", "model=niw", "data.max_side=48", "+data.n_views=24",
                          "trainer.max_steps=20", "trainer.eval_every=20", "logger=none", "trainer.enable_progress_bar=false",
                          f"hydra.run.dir={run}"], capture_output=True, text=True, timeout=600, cwd=ROOT, env=ENV)
    assert res.returncode == 0, res.stderr[-3000:]
    return run


def video_frames(path: Path) -> tuple[int, tuple[int, int]]:
    import imageio_ffmpeg

    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    return sum(1 for _ in reader), tuple(meta["size"])


def test_interpolated_loop_passes_through_the_cameras():
    from b3dgs.render_cli import interpolate_cameras

    def cam(angle):
        c = np.array([3 * np.cos(angle), 3 * np.sin(angle), 0.5])
        z = -c / np.linalg.norm(c)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])  # rows: camera axes in world coordinates (w2c rotation)
        v = np.eye(4)
        v[:3, :3], v[:3, 3] = R, -R @ c
        return Camera(f"c{angle:.2f}", torch.tensor([[40.0, 0, 20], [0, 40, 15], [0, 0, 1]]), torch.from_numpy(v).float(), 40, 30)

    cams = [cam(a) for a in np.linspace(0, 2 * np.pi, 4, endpoint=False)]
    path = interpolate_cameras(cams, 16)
    assert len(path) == 16 and all((p.width, p.height) == (40, 30) for p in path)
    for i, c in enumerate(cams):  # every 4th frame is a source camera
        assert torch.allclose(path[4 * i].viewmat, c.viewmat, atol=1e-5)
    radii = [float(p.center[:2].norm()) for p in path]
    assert min(radii) > 2.5 and max(radii) < 3.5  # a smooth loop around the subject, not a polygon through its middle


def test_render_writes_pngs_and_an_mp4_of_the_test_path(niw_run, tmp_path):
    res = cli(f"run={niw_run}", "panel=native_sigma", "max_side=64")
    assert res.returncode == 0, res.stderr[-3000:]
    out = niw_run / "render" / "test"
    pngs = sorted(out.glob("frame_*.png"))
    assert len(pngs) == 3  # 24 views, every 8th a test view
    assert res.stdout.strip().splitlines()[-1] == f"b3dgs-render: wrote 3 frames to {out}/frame_*.png and {out / 'test.mp4'}"
    img = np.asarray(Image.open(pngs[0]).convert("RGB")).astype(float)
    h, w = img.shape[:2]
    assert w == 128 and h > 64  # RGB | native σ side by side at 64 px, the σ colour bar under them
    rgb, sigma = img[:64, :64], img[:64, 64:]
    assert rgb.std() > 5 and sigma.std() > 5
    top = colormap_lut("inferno")[-1].astype(float)
    saturated = (np.abs(sigma - top).sum(axis=2) < 30).mean()
    assert saturated < 0.05, f"{saturated:.0%} of the σ panel is at the top colour: its scale is not the path's own"
    n, size = video_frames(out / "test.mp4")
    assert n == 3 and size == (128, h + h % 2)
    from b3dgs.rundir import run_files

    assert {"render/test/test.mp4", *(f"render/test/{p.name}" for p in pngs)} <= set(run_files(niw_run))  # its own
    res = cli(f"run={niw_run}", "path=interpolate", "frames=10", f"out={tmp_path / 'loop'}", "fps=10")
    assert res.returncode == 0, res.stderr[-3000:]
    assert len(list((tmp_path / "loop").glob("frame_*.png"))) == 10
    assert video_frames(tmp_path / "loop" / "interpolate.mp4")[0] == 10
    frames = [np.asarray(Image.open(p)).astype(float) for p in sorted((tmp_path / "loop").glob("frame_*.png"))]
    assert all(np.abs(a - b).mean() > 0.5 for a, b in zip(frames, frames[1:]))  # the camera moves
    # a rerun into that folder replaces its own video (.b3dgs-render.json records it); a video it did not write stays
    res = cli(f"run={niw_run}", "path=interpolate", "frames=4", f"out={tmp_path / 'loop'}", "fps=10")
    assert res.returncode == 0 and video_frames(tmp_path / "loop" / "interpolate.mp4")[0] == 4, res.stderr[-2000:]
    assert len(list((tmp_path / "loop").glob("frame_*.png"))) == 4
    (tmp_path / "loop" / "orbit.mp4").write_bytes(b"mine")
    res = cli(f"run={niw_run}", "path=orbit", "frames=4", f"out={tmp_path / 'loop'}")
    assert res.returncode == 2 and "holds orbit.mp4, which b3dgs did not write" in res.stderr, res.stderr[-2000:]
    assert (tmp_path / "loop" / "orbit.mp4").read_bytes() == b"mine"


def test_render_refuses_in_one_line(niw_run, tmp_path):
    for args, match in ((["run=" + str(tmp_path / "missing")], "no run dir at"),
                        ([f"run={niw_run}", "path=helix"], "path=helix is not a camera path"),
                        ([f"run={niw_run}", "panel=pos"], "panel=pos is not a panel mode"),
                        ([f"run={niw_run}", "path=interpolate", "frames=1"], "frames=1 is too few"),
                        ([f"run={niw_run}", "fps=0"], "fps=0 is invalid: it must be a frame rate")):
        res = cli(*args, cwd=tmp_path)
        assert res.returncode == 2, res.stderr[-2000:]
        lines = [ln for ln in res.stderr.splitlines() if ln.startswith("b3dgs-render: error:")]
        assert len(lines) == 1 and match in lines[0] and "(fix: " in lines[0], res.stderr[-2000:]
    assert not any(tmp_path.iterdir())


def test_orbit_and_nerfstudio_camera_paths(tmp_path):
    """path=orbit: a closed circle around the point the capture's cameras look at, every frame looking at it, at the
    cameras' mean distance; path=FILE.json (nerfstudio's camera-path format, OpenGL axes, the scene's own frame): a scene's own
    cameras written in that format come back as the same cameras (poses and intrinsics); a bad file is one line."""
    import json

    from b3dgs.data import load_scene
    from b3dgs.data.scene import look_at_point
    from b3dgs.errors import B3dgsError
    from b3dgs.render_cli import camera_path

    scene = load_scene("synthetic", None, max_side=32, n_views=16)
    orbit = camera_path(scene, "orbit", 12)
    assert len(orbit) == 12
    target, _ = look_at_point(np.stack([c.viewmat.double().numpy() for c in [*scene.train, *scene.test]]))
    for c in orbit:
        c2w = c.camtoworld.double().numpy()
        to = target - c2w[:3, 3]
        assert np.dot(to / np.linalg.norm(to), c2w[:3, 2]) > 0.9999  # looks at the target
    d = [np.linalg.norm(c.center.double().numpy() - target) for c in orbit]
    assert max(d) - min(d) < 1e-4 * max(d)  # a circle
    # the scene's test cameras, in the scene's own frame and OpenGL axes, as nerfstudio writes a camera path
    T = scene.transform
    Rn, s, t = np.asarray(T.rotation), T.scale, np.asarray(T.translation)
    entries = []
    for c in scene.test:
        c2w = c.camtoworld.double().numpy()
        own = np.eye(4)
        own[:3, :3] = Rn.T @ c2w[:3, :3] @ np.diag([1.0, -1.0, -1.0])
        own[:3, 3] = Rn.T @ (c2w[:3, 3] - t) / s
        fov = float(np.rad2deg(2 * np.arctan(0.5 * c.height / float(c.K[1, 1]))))
        entries.append({"camera_to_world": own.reshape(-1).tolist(), "fov": fov, "aspect": c.width / c.height})
    f = tmp_path / "path.json"
    f.write_text(json.dumps({"camera_type": "perspective", "render_height": scene.test[0].height,
                             "render_width": scene.test[0].width, "camera_path": entries}))
    back = camera_path(scene, str(f), 0)
    for a, b in zip(back, scene.test):
        assert torch.allclose(a.viewmat, b.viewmat, atol=1e-5) and (a.width, a.height) == (b.width, b.height)
        assert torch.allclose(a.K[:2, :2], b.K[:2, :2], rtol=1e-4)
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(B3dgsError, match="not a readable nerfstudio camera path"):
        camera_path(scene, str(tmp_path / "bad.json"), 0)


def _forward_capture(n_side: int = 3, depth: float = 4.0):
    """A forward-facing capture: n_side x n_side cameras on a grid in the plane z = 0, all looking at (0, 0, depth)
    (OpenCV: +z forward, +y down = world +y), and points around it."""
    from types import SimpleNamespace

    from b3dgs.render_cli import _look_at

    K = torch.tensor([[40.0, 0, 20], [0, 40.0, 15], [0, 0, 1]])
    cams = []
    for i, (x, y) in enumerate((x, y) for x in np.linspace(-0.3, 0.3, n_side) for y in np.linspace(-0.2, 0.2, n_side)):
        view = _look_at(np.array([x, y, 0.0]), np.array([0.0, 0.0, depth]), np.array([0.0, -1.0, 0.0]))
        cams.append(Camera(f"c{i:02d}", K, torch.from_numpy(view).float(), 40, 30))
    pts = np.random.default_rng(0).normal([0.0, 0.0, depth], 0.2, size=(200, 3))
    return SimpleNamespace(train=cams[1:], test=cams[:1], points=pts)


def test_spiral_stays_in_front_of_a_forward_capture_and_orbit_warns(caplog):
    """path=spiral (LLFF's render path): every frame near the capture's plane, within its spread, looking at the point
    in front of it; path=orbit on such a capture says half its circle looks from where no photo was taken."""
    import logging

    from b3dgs.render_cli import camera_path

    scene = _forward_capture()
    spiral = camera_path(scene, "spiral", 24)
    centres = np.stack([c.center.double().numpy() for c in spiral])
    assert len(spiral) == 24 and np.linalg.norm(np.diff(centres, axis=0), axis=1).min() > 1e-3  # it moves each frame
    target = np.array([0.0, 0.0, 4.0])  # where the capture's axes meet
    for c in spiral:
        c2w, pos = c.camtoworld.double().numpy(), c.center.double().numpy()
        assert abs(pos[0]) <= 0.3 + 1e-6 and abs(pos[1]) <= 0.2 + 1e-6 and abs(pos[2]) < 0.2  # within the spread
        to = target - pos
        assert np.dot(to / np.linalg.norm(to), c2w[:3, 2]) > 0.9999  # looks at the point in front
        assert c2w[:3, 1] @ np.array([0.0, 1.0, 0.0]) > 0.99  # the capture's own down
    # parallel axes (no point where they meet): the points' median depth in front sets the point looked at
    from b3dgs.render_cli import spiral_cameras

    parallel = []
    for c in scene.train:
        view = torch.eye(4)
        view[:3, 3] = -c.center
        parallel.append(Camera(c.name, c.K, view, c.width, c.height))
    depth = float(np.median(scene.points[:, 2]))
    for c in spiral_cameras(parallel, 8, scene.points):
        to = np.array([0.0, 0.0, depth]) - c.center.double().numpy()
        assert np.dot(to / np.linalg.norm(to), c.camtoworld.double().numpy()[:3, 2]) > 0.99
    with caplog.at_level(logging.WARNING, logger="b3dgs.render_cli"):
        camera_path(scene, "orbit", 8)
    assert "the capture is forward-facing" in caplog.text and "path=spiral" in caplog.text


def test_a_second_render_into_one_out_folder_is_refused(niw_run, tmp_path):
    """Two renders into one out= folder outside a run would mix their frame sets: the second is refused in one line
    naming the first's pid, and the folder keeps the first's files."""
    from b3dgs.locks import process_lock

    out = tmp_path / "shared"
    out.mkdir()
    (out / "frame_00000.png").write_bytes(b"first")
    with process_lock(out / ".b3dgs-render.lock", remove=True):  # this process stands for a render that is writing there
        res = cli(f"run={niw_run}", "path=interpolate", "frames=4", f"out={out}")
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("b3dgs-render: error:")]
    assert res.returncode == 2 and lines == [f"b3dgs-render: error: out={out} is in use by another b3dgs-render "
                                             f"(pid {os.getpid()}) (fix: wait for it to finish, or pass another out)"], \
        res.stderr[-2000:]
    assert sorted(p.name for p in out.iterdir()) == ["frame_00000.png"] and (out / "frame_00000.png").read_bytes() == b"first"
