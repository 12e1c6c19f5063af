"""b3dgs-view: the render modes (shapes, fixed scales, a known Gaussian's σ, depth and overlays), the
camera conversions, the run-dir checks (one-line errors) and a real browser (headless Chromium) driving
the viewer's GUI."""
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from b3dgs.types import Camera, Scene
from b3dgs.viewer.cameras import camera_pose, mat_to_wxyz, render_size, view_camera, wxyz_to_mat
from b3dgs.viewer.modes import MIN_ALPHA, MODES, ModeRenderer, colormap_lut

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
MODELS = ("standard", "niw", "dpmm", "mcmc")


# ------------------------------------------------------------------------------------ a known Gaussian
F, Z, SIZE, S_WORLD, OPACITY = 32.0, 2.0, 33, 0.1, 0.8


def one_gaussian_scene():
    """A 33 × 33 camera at the origin looking down +z with the principal point on pixel (16, 16)'s centre."""
    K = torch.tensor([[F, 0, SIZE / 2], [0, F, SIZE / 2], [0, 0, 1]], dtype=torch.float32)
    cam = Camera("c0", K, torch.eye(4), SIZE, SIZE, image=torch.zeros(SIZE, SIZE, 3))
    return Scene("one", [cam], [cam], points=torch.zeros(1, 3), point_colors=torch.ones(1, 3)), cam


def one_gaussian_module(blocks=None):
    """A module holding one isotropic Gaussian (std S_WORLD) at depth Z, opacity OPACITY, white."""
    from b3dgs.module import SplatModule
    from b3dgs.render.projection import rgb_to_sh0
    from b3dgs_plugins.strategy.default import AdaptiveDensityControl

    scene, cam = one_gaussian_scene()
    m = SplatModule(strategy=AdaptiveDensityControl(), posterior=blocks or {}, renderer="cpu", max_steps=100, sh_degree=0)
    m.scene = scene
    m._set_params({"means": torch.tensor([[0.0, 0.0, Z]]), "scales": torch.full((1, 3), math.log(S_WORLD)),
                   "quats": torch.tensor([[1.0, 0, 0, 0]]), "opacities": torch.logit(torch.tensor([OPACITY])),
                   "sh0": rgb_to_sh0(torch.ones(1, 1, 3)), "shN": torch.zeros(1, 0, 3)})
    m._init_states()
    m._loaded_step = 100
    m.eval()
    return m, scene, cam


def test_render_modes_shapes_and_fixed_scales():
    m, scene, cam = one_gaussian_module()
    mr = ModeRenderer(m, scene, samples=4)
    assert set(mr.available()) == {"rgb", "depth", "alpha", "proxy_sigma", "opacity"}
    assert set(mr.unavailable()) == {"native_sigma", "sh_sigma", "dp_activity", "pos_std"}  # SH degree 0: no sh_sigma
    small = view_camera(*camera_pose(cam), fov=2 * math.atan(0.5 * SIZE / F), width=20, height=12)
    for mode in mr.available():
        frame = mr.render(mode, small)
        assert frame.image.shape == (12, 20, 3) and frame.image.dtype == np.uint8
        if mode != "rgb":
            assert frame.values.shape == (12, 20)
    with pytest.raises(ValueError, match="not available for this run: model=standard has no posterior"):
        mr.render("native_sigma", cam)
    # the scale is fixed, not per frame: a value maps to the same colour in every view, as the legend states
    spec = mr.specs["proxy_sigma"]
    assert (spec.lo, spec.hi) == (0.0, 0.03) and "0.03" in spec.scale_text() and "fixed" in spec.scale_text()
    frame = mr.render("proxy_sigma", cam)
    lut = colormap_lut(spec.cmap)
    v = frame.values[16, 18].item()
    assert (frame.image[16, 18] == lut[int(round(min(v / 0.03, 1.0) * 255))]).all()
    mr.set_sigma_max(0.01)
    frame2 = mr.render("proxy_sigma", cam)
    assert torch.equal(frame.values, frame2.values)
    assert (frame2.image[16, 18] == lut[int(round(min(v / 0.01, 1.0) * 255))]).all()
    assert MODES["proxy_sigma"].hi == 0.03  # the module's table is never changed


def test_depth_alpha_and_overlays_of_a_known_gaussian():
    m, scene, cam = one_gaussian_module()
    mr = ModeRenderer(m, scene)
    alpha = mr.render("alpha", cam).values
    assert alpha[16, 16].item() == pytest.approx(OPACITY, rel=1e-4)  # the centre pixel: G = 1
    depth = mr.render("depth", cam)
    covered = alpha >= MIN_ALPHA
    assert covered.sum() > 4 and torch.allclose(depth.values[covered], torch.tensor(Z), rtol=1e-4)
    assert depth.mask is not None and torch.equal(depth.mask, covered)
    assert mr.specs["depth"].hi == pytest.approx(2.0 * max(float(c.center.norm()) for c in scene.train), abs=0.1)
    # one Gaussian: the weighted mean of its value along every covered ray is its value
    op = mr.render("opacity", cam)
    assert torch.allclose(op.values[covered], torch.tensor(OPACITY), atol=1e-3)
    mr.extras["niw_pos_var"] = torch.tensor([3e-3 ** 2])  # tr Var[μ] / 3: std 3e-3 × extent (extent 1)
    pos = mr.render("pos_std", cam)
    assert torch.allclose(pos.values[covered], torch.tensor(3e-3), rtol=2e-2)
    assert mr.specs["pos_std"].log and "log scale" in mr.specs["pos_std"].scale_text()


def test_proxy_sigma_of_a_known_gaussian_matches_first_order_propagation():
    """Every centre jittered by N(0, τ² I): on the image row through the centre, the pixel's σ is, to first
    order, |∂I/∂u| · f τ / z with I = o · exp(−r² / (2 s²)) and s² = (f s_w / z)² + 0.3 (EWA's blur)."""
    m, scene, cam = one_gaussian_module()
    jitter = 0.002
    mr = ModeRenderer(m, scene, samples=600, jitter=jitter)
    sigma = mr.render("proxy_sigma", cam).values
    s2 = (F * S_WORLD / Z) ** 2 + 0.3
    for r in (1, 2):
        intensity = OPACITY * math.exp(-r * r / (2 * s2))
        expected = intensity * r / s2 * F * jitter * scene.extent / Z
        assert sigma[16, 16 + r].item() == pytest.approx(expected, rel=0.1)
        assert sigma[16, 16 - r].item() == pytest.approx(expected, rel=0.1)
    assert sigma[16, 16].item() < 0.1 * sigma[16, 17].item()  # the profile is flat at its peak
    assert sigma[0, 0].item() == 0.0  # nothing there


def test_native_sigma_is_the_posterior_spread_of_eq4():
    from b3dgs_plugins.posterior.niw import NIWBlock
    from b3dgs_plugins.uq.native import NativeUQ

    m, scene, cam = one_gaussian_module({"niw": NIWBlock()})
    mr = ModeRenderer(m, scene, samples=8)
    assert "native_sigma" in mr.available() and "pos_std" in mr.available()
    for count, positive in ((1e12, False), (5.0, True)):
        m.states["niw"]["N"].fill_(count)
        mr._regimes.clear()
        sigma = mr.render("native_sigma", cam).values
        ref = NativeUQ(samples=8, chunk=8, count_scale=0.1)  # uq=native's default count scale
        ref.fit([m], scene)
        _, u = ref.spread(cam, torch.Generator().manual_seed(0))
        assert torch.allclose(sigma, u.clamp_min(0).sqrt(), atol=1e-6)  # the b3dgs-eval regime, not a copy
        assert (sigma.max().item() > 1e-3) == positive
    # count_scale=None: the model's own posterior, narrower than N̂ <- 0.1·N̂ (fewer pseudo-counts)
    own = ModeRenderer(m, scene, samples=8, count_scale=None).render("native_sigma", cam).values
    assert 0 < own.max().item() < sigma.max().item()
    with pytest.raises(ValueError, match="count_scale"):
        ModeRenderer(m, scene, count_scale=0.0)


def test_camera_conversions_round_trip():
    g = torch.Generator().manual_seed(0)
    for _ in range(20):
        q = torch.randn(4, generator=g).double().numpy()
        q /= np.linalg.norm(q)
        R = wxyz_to_mat(q)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.linalg.det(R) == pytest.approx(1.0)
        assert np.allclose(wxyz_to_mat(mat_to_wxyz(R)), R, atol=1e-10)
    quarter = [math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]  # 90 degrees about +z, (w, x, y, z) order
    assert np.allclose(wxyz_to_mat(quarter), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    assert np.allclose(mat_to_wxyz([[0, 1, 0], [-1, 0, 0], [0, 0, 1]]), [quarter[0], 0, 0, -quarter[3]])  # w >= 0
    _, cam = one_gaussian_scene()
    cam = Camera("c", cam.K, torch.tensor([[0.0, 0, 1, 0.3], [1, 0, 0, -0.2], [0, 1, 0, 2.0], [0, 0, 0, 1]]), SIZE, SIZE)
    wxyz, pos = camera_pose(cam)
    back = view_camera(wxyz, pos, 2 * math.atan(0.5 * SIZE / F), SIZE, SIZE)
    assert torch.allclose(back.viewmat, cam.viewmat, atol=1e-6)
    assert torch.allclose(back.K, cam.K, atol=1e-5)
    assert render_size(2.0, 128) == (128, 64) and render_size(0.5, 128) == (64, 128)


# ------------------------------------------------------------------------------------ trained runs
@pytest.fixture(scope="session")
def tiny_runs(tmp_path_factory):
    """One 40-step run of each model on the embedded scene at 32 px (one multirun process)."""
    root = tmp_path_factory.mktemp("viewer_runs")
    cmd = [sys.executable, "-m", "b3dgs.train", "-m", f"model={','.join(MODELS)}", "trainer.max_steps=40",
           "trainer.eval_every=20", "data.max_side=32", "+data.n_views=16", "trainer.enable_progress_bar=false", "logger=none",
           "renderer=cpu", f"hydra.sweep.dir={root}", "hydra.sweep.subdir=${model.name}"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=900, cwd=ROOT, env=ENV)
    assert res.returncode == 0, res.stderr[-3000:]
    return {m: root / m for m in MODELS}


@pytest.mark.parametrize("model", MODELS)
def test_viewer_opens_each_model_and_renders_every_mode(tiny_runs, model):
    from b3dgs.viewer.run import open_run

    run = open_run(tiny_runs[model])
    mr = ModeRenderer(run.module, run.scene, samples=4)
    expect = {"rgb", "depth", "alpha", "proxy_sigma", "opacity"}
    expect |= {"niw": {"native_sigma", "pos_std"}, "dpmm": {"native_sigma", "pos_std", "dp_activity"}}.get(model, set())
    assert set(mr.available()) == expect
    cam = view_camera(*camera_pose(run.scene.test[0]), fov=0.8, width=24, height=16)
    for mode in mr.available():
        frame = mr.render(mode, cam)
        assert frame.image.shape == (16, 24, 3)
        assert frame.image.std() > 0, f"{model} {mode}: a blank frame"
    assert run.metrics["method"] == model and len(run.curve) >= 2


def copy_run(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def test_run_dir_errors_are_one_line(tiny_runs, tmp_path):
    from b3dgs.errors import B3dgsError
    from b3dgs.viewer.run import open_run

    def refused(path, match):
        with pytest.raises(B3dgsError, match=match) as e:
            open_run(path)
        assert "\n" not in str(e.value) and "(fix: " in str(e.value)

    refused(tmp_path / "nope", "no run dir at")
    (tmp_path / "file").write_text("x")
    refused(tmp_path / "file", "is a file")
    (tmp_path / "empty").mkdir()
    refused(tmp_path / "empty", r"not a b3dgs run dir \(no config.yaml\)")
    unfinished = copy_run(tiny_runs["niw"], tmp_path / "unfinished")
    (unfinished / "metrics.json").unlink()
    refused(unfinished, "unfinished run: no metrics.json.*resume=auto")
    old = copy_run(tiny_runs["niw"], tmp_path / "old")
    m = json.loads((old / "metrics.json").read_text())
    del m["checkpoint"]
    (old / "metrics.json").write_text(json.dumps(m))
    refused(old, "another b3dgs version: its metrics.json has no checkpoint record")
    foreign = copy_run(tiny_runs["niw"], tmp_path / "foreign")
    cfg = (foreign / "config.yaml").read_text()
    (foreign / "config.yaml").write_text(cfg.replace("plugins.posterior.niw.NIWBlock", "plugins.posterior.niw.NIWBlockV9"))
    refused(foreign, "another b3dgs version: this code cannot rebuild it")
    stray = copy_run(tiny_runs["niw"], tmp_path / "stray")
    shutil.copy(tiny_runs["dpmm"] / "checkpoints" / "last.ckpt", stray / "checkpoints" / "last.ckpt")
    refused(stray, "cannot open")
    # a run that is still training: its lock is held by a live process
    from b3dgs.rundir import run_dir_lock

    busy = copy_run(tiny_runs["niw"], tmp_path / "busy")
    with run_dir_lock(busy):
        refused(busy, "still training")
    assert open_run(busy).metrics["method"] == "niw"
    # the folder above them (a sweep, outputs/train) names its finished runs (not the unfinished one) and one to pass
    refused(tmp_path, r"holds 4 finished run dirs \(busy, foreign, old, stray\), not a run \(fix: pass one of them, "
                      rf"e\.g\. run={tmp_path / 'stray'}\)")


def test_cli_refuses_in_one_line(tiny_runs, tmp_path):
    pytest.importorskip("viser", reason='viser not installed (fix: pip install -e ".[viewer]")')
    for args, match in ((["run=" + str(tmp_path / "missing")], "no run dir at"),
                        ([f"run={tiny_runs['standard']}", "mode=native_sigma"], "not available for this run"),
                        ([f"run={tiny_runs['standard']}", "mode=sigma"], "unknown viewer mode"),
                        ([f"run={tiny_runs['standard']}", "start=top"], "start=top is not a start view"),
                        ([f"run={tiny_runs['standard']}", "prot=9000"], "prot")):
        res = subprocess.run([sys.executable, "-m", "b3dgs.viewer.app", *args], capture_output=True, text=True,
                             timeout=300, cwd=tmp_path, env=ENV)
        assert res.returncode == 2, res.stderr[-2000:]
        lines = [ln for ln in res.stderr.splitlines() if ln.startswith("b3dgs-view: error:")]
        assert len(lines) == 1 and match in lines[0], res.stderr[-2000:]
    assert not any(tmp_path.iterdir())  # the viewer writes no files


@pytest.mark.parametrize("arg, match", [("port=70000", "port=70000 is not a TCP port (0-65535)"),
                                        ("host=10.255.255.1", "cannot serve on host=10.255.255.1"),
                                        ("host=no-such-host.invalid", "host=no-such-host.invalid is not a known host")])
def test_an_address_it_cannot_serve_on_ends_the_viewer_at_once(tmp_path, arg, match):
    """Refused before the run is opened or anything is served: one line, exit code 2. The run is an empty folder,
    so a refusal that came after opening it would name the run instead; the subprocess timeout catches a hang."""
    (tmp_path / "not_a_run").mkdir()
    res = subprocess.run([sys.executable, "-m", "b3dgs.viewer.app", f"run={tmp_path / 'not_a_run'}", arg],
                         capture_output=True, text=True, timeout=60, cwd=tmp_path, env=ENV)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1 and match in lines[0] and "(fix: " in lines[0], res.stderr[-2000:]


def test_duration_s_ends_the_viewer(tiny_runs, tmp_path):
    pytest.importorskip("viser", reason='viser not installed (fix: pip install -e ".[viewer]")')
    res = subprocess.run([sys.executable, "-m", "b3dgs.viewer.app", f"run={tiny_runs['standard']}", "port=0",
                          "duration_s=1"], capture_output=True, text=True, timeout=120, cwd=tmp_path, env=ENV)
    assert res.returncode == 0 and " at http://127.0.0.1:" in res.stdout, res.stderr[-2000:]


def test_help_lists_the_modes_and_options():
    from omegaconf import OmegaConf

    from b3dgs.train import CONF_DIR

    res = subprocess.run([sys.executable, "-m", "b3dgs.viewer.app", "--help"], capture_output=True, text=True,
                         timeout=60, cwd=ROOT, env=ENV)
    assert res.returncode == 0 and res.stdout.startswith("b3dgs-view: "), res.stderr[-2000:]  # its purpose first
    assert "\nusage: b3dgs-view run=DIR" in res.stdout, res.stdout[:2000]
    for key in MODES:
        assert re.search(rf"^  {key} +\S", res.stdout, re.M), key
    options = [k for k in OmegaConf.load(Path(CONF_DIR) / "view.yaml") if k not in ("defaults", "b3dgs", "hydra")]
    for key in options:
        assert re.search(rf"^  {key}=", res.stdout, re.M), key
    assert "Hydra" not in res.stdout and "hydra/" not in res.stdout  # not Hydra's boilerplate


def test_home_view_frames_what_the_cameras_look_at():
    """The orbit view looks at the cameras' common point from their median distance, at a positive elevation for
    cameras all around the subject (the synthetic scene), with their field of view."""
    from b3dgs.data.scene import load_scene, look_at_point
    from b3dgs.viewer.server import home_view

    scene = load_scene("synthetic", None, max_side=32, n_views=24)
    up = np.mean([-c.camtoworld[:3, 1].double().numpy() for c in scene.train], axis=0)
    up /= np.linalg.norm(up)
    home = home_view(scene, up)
    cams = scene.train + scene.test
    target, _ = look_at_point(np.stack([c.viewmat.double().numpy() for c in cams]))
    assert np.allclose(home["look_at"], target)
    dist = np.median([np.linalg.norm(c.center.double().numpy() - target) for c in cams])
    assert np.linalg.norm(home["position"] - target) == pytest.approx(dist)
    elev = (home["position"] - target) @ up / dist
    assert 0.25 < elev < 0.81
    cam = view_camera(mat_to_wxyz(_look_rotation(home["position"], target, up)), home["position"], home["fov"], 64, 64)
    x = cam.viewmat[:3, :3].double() @ torch.from_numpy(target) + cam.viewmat[:3, 3].double()
    assert x[2] > 0 and torch.allclose(x[:2] / x[2], torch.zeros(2, dtype=torch.float64), atol=1e-5)


def _look_rotation(pos, target, up) -> np.ndarray:
    """Camera-to-world rotation (OpenCV axes) of a camera at ``pos`` looking at ``target``."""
    z = (target - pos) / np.linalg.norm(target - pos)
    x = np.cross(z, -up)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def test_view_settings_count_scale():
    """conf/view.yaml's count_scale reaches the viewer; null means the model's own posterior; bad values refused."""
    from omegaconf import OmegaConf

    from b3dgs.errors import B3dgsError
    from b3dgs.train import CONF_DIR
    from b3dgs.viewer.app import settings_from_cfg

    cfg = OmegaConf.load(Path(CONF_DIR) / "view.yaml")
    cfg.pop("defaults")
    cfg.run = "RUN"  # as b3dgs-view composes it
    assert settings_from_cfg(cfg).count_scale == 0.1
    cfg.count_scale = None
    assert settings_from_cfg(cfg).count_scale is None
    for bad in (0, -1.0, True):
        cfg.count_scale = bad
        with pytest.raises(B3dgsError, match="count_scale"):
            settings_from_cfg(cfg)


# ------------------------------------------------------------------------------------ a real browser
def screenshot_pixels(png: bytes) -> np.ndarray:
    import io

    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.float64)


def render_area(png: bytes) -> np.ndarray:
    """The screenshot's pixels left of the side panel (the rendered view), as float RGB."""
    return screenshot_pixels(png)[160:-60, 20:900]  # below the notifications, left of the panel, above the axes gizmo


def centre_patch(png: bytes, half: int = 40) -> np.ndarray:
    """The pixels around the centre of the canvas (the page: the canvas fills it)."""
    img = screenshot_pixels(png)
    cy, cx = img.shape[0] // 2, img.shape[1] // 2
    return img[cy - half:cy + half, cx - half:cx + half]


def saturated_share(pixels: np.ndarray, cmap: str = "inferno") -> float:
    """The share of pixels at (JPEG-close to) the colour map's top colour."""
    top = colormap_lut(cmap)[-1].astype(np.float64)
    return float((np.abs(pixels - top).sum(axis=-1) < 40).mean())


def _serve_until_up(args, cwd) -> subprocess.Popen:
    """``b3dgs-view`` started with ``args``, once it prints its URL (stderr kept apart from stdout)."""
    proc = subprocess.Popen([sys.executable, "-m", "b3dgs.viewer.app", *args, "port=0", "duration_s=300"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd, env=ENV)
    for line in proc.stdout:
        if re.search(r" at http://127\.0\.0\.1:\d+ ", line):
            return proc
    proc.kill()
    raise AssertionError(f"the viewer did not start: {proc.stderr.read()[-2000:]}")


@pytest.mark.slow
def test_sigterm_stops_the_viewer_with_143_and_one_line(tmp_path):
    """On a COLMAP run (its scene was once read with pycolmap, whose import installs glog's SIGTERM handler: a
    20-line stack trace; now read without it), SIGTERM ends b3dgs-view with exit code 143 and one line on stderr."""
    pytest.importorskip("viser", reason='viser not installed (fix: pip install -e ".[viewer]")')
    from conftest import SHARED

    if not (SHARED / "data" / "flower").is_dir():
        pytest.skip(f"shared scene not found at {SHARED / 'data' / 'flower'}")
    run = tmp_path / "run"
    res = subprocess.run([sys.executable, "-m", "b3dgs.train", "scene=flower", f"data_root={SHARED / 'data'}",
                          "data.max_side=32", "data.max_images=8", "trainer.max_steps=10", "trainer.eval_every=10",
                          "trainer.enable_progress_bar=false", "logger=none", "trainer.save_renders=false",
                          f"hydra.run.dir={run}"], capture_output=True, text=True, timeout=600, cwd=ROOT, env=ENV)
    assert res.returncode == 0, res.stderr[-3000:]
    proc = _serve_until_up([f"run={run}"], tmp_path)
    try:
        time.sleep(0.5)
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=60)
    finally:
        proc.kill()
    err = proc.stderr.read()
    assert rc == 143 and err.splitlines() == ["b3dgs-view: stopped by SIGTERM"], (rc, err[-3000:])


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("chromium") is None and shutil.which("chromium-browser") is None,
                    reason="chromium not installed (apt-get install -y chromium)")
def test_viewer_in_headless_chromium(tiny_runs, tmp_path):
    """Start b3dgs-view on 127.0.0.1, open it in headless Chromium and wait until the scene has drawn at full
    resolution: it opens on the orbit view with the scene at the centre of the canvas (not the background, not a
    frustum). Every mode of the DPMM run, picked with real mouse clicks on the panel's mode menu, shows a drawn view
    that differs from the RGB one; native σ's automatic scale leaves it unsaturated. Then drag the view (a
    low-resolution pass, then full again). ``target_ms=1``: every moving frame takes the low pass.
    ``B3DGS_VIEWER_SHOTS=DIR`` keeps the screenshots there."""
    pytest.importorskip("viser", reason='viser not installed (fix: pip install -e ".[viewer]")')
    from tests.browser import Browser

    shots = Path(os.environ.get("B3DGS_VIEWER_SHOTS", tmp_path))
    shots.mkdir(parents=True, exist_ok=True)
    proc = subprocess.Popen([sys.executable, "-m", "b3dgs.viewer.app", f"run={tiny_runs['dpmm']}", "port=0",
                             "max_side=320", "target_ms=1", "samples=8", "duration_s=900"], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, cwd=tmp_path, env=ENV)
    browser = None
    try:
        url = None
        for line in proc.stdout:  # the viewer prints its URL once it serves
            found = re.search(r" at (http://127\.0\.0\.1:\d+) ", line)
            if found:
                url = found.group(1)
                break
        assert url is not None and proc.poll() is None, "the viewer did not start"
        threading.Thread(target=proc.stdout.read, daemon=True).start()  # keep the pipe drained
        browser = Browser(url + "/")
        browser.wait_for("document.querySelector('canvas') !== null", 120)
        browser.wait_frame("(RGB", "full resolution", "full = 320 px")  # the window's size, capped at max_side
        time.sleep(2.0)  # the page's fade-in
        rgb = browser.screenshot()
        (shots / "rgb.png").write_bytes(rgb)
        centre = centre_patch(rgb)
        assert centre.mean() > 25 and centre.std() > 3, "the centre of the opening view is not the scene"
        assert render_area(rgb).std() > 5, "a blank screenshot"
        current = "RGB"
        labels = {"depth": "Depth", "alpha": "Alpha", "native_sigma": "Native σ", "proxy_sigma": "Proxy σ",
                  "dp_activity": "DP activity E[a_k]", "pos_std": "Posterior position std", "opacity": "Opacity"}
        for key, label in labels.items():
            browser.choose(current, label)  # real mouse clicks on the panel's mode menu, then on the option
            current = label
            browser.wait_frame(f"({label}", "full resolution", timeout=300)
            time.sleep(1.0)
            png = browser.screenshot()
            (shots / f"{key}.png").write_bytes(png)
            area = render_area(png)
            assert area.std() > 5, f"{key}: a blank screenshot"
            assert np.abs(area - render_area(rgb)).mean() > 5, f"{key}: the same picture as RGB"
            if key == "native_sigma":
                text = browser.evaluate("document.body.innerText")
                top = re.search(r"Native σ: left 0 → right ([0-9.e-]+) .*auto: the 99th percentile", text)
                assert top and float(top.group(1)) > 0, text[:1500]
                assert saturated_share(area) < 0.05, "native σ is saturated"
                assert np.median(centre_patch(png).sum(axis=-1)) > 60, "native σ shows nothing at the centre"
        # drag the view: frames at low resolution while moving, then full resolution once still
        seen = set()
        browser.call("Input.dispatchMouseEvent", type="mousePressed", x=400, y=400, button="left", clickCount=1)
        for i in range(12):
            browser.call("Input.dispatchMouseEvent", type="mouseMoved", x=400 + 15 * i, y=400, button="left")
            time.sleep(0.05)
            seen.add(browser.frame_text())
        browser.call("Input.dispatchMouseEvent", type="mouseReleased", x=580, y=400, button="left", clickCount=1)
        if not any(s and "low resolution" in s for s in seen):
            browser.wait_frame("low resolution", timeout=60)
        browser.wait_frame("full resolution", timeout=300)
    finally:
        if browser is not None:
            browser.close()
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()


def test_acquired_views_are_listed_first_in_pick_order(tiny_runs, tmp_path):
    """An active-view row's selection.json (in the run dir, or acquired=ROW) puts its picks first, in order."""
    pytest.importorskip("viser", reason='viser not installed (fix: pip install -e ".[viewer]")')
    from b3dgs.errors import B3dgsError
    from b3dgs.viewer.run import open_run
    from b3dgs.viewer.server import ViewerApp, ViewerSettings

    run_dir = copy_run(tiny_runs["niw"], tmp_path / "row")
    names = [c.name for c in open_run(run_dir).scene.train]
    picks = [names[5], names[2]]
    (run_dir / "selection.json").write_text(json.dumps({"policy": "native", "selected": picks}))
    run = open_run(run_dir)
    assert run.acquired == picks
    app = ViewerApp(run, ViewerSettings(port=0))
    try:
        labels = [(lbl, kind) for lbl, _, kind in app._cameras]
        assert labels[:2] == [(f"acquired #1: {picks[0]}", "acquired"), (f"acquired #2: {picks[1]}", "acquired")]
        assert [k for _, k in labels].count("test") == len(run.scene.test)
        assert len(labels) == len(run.scene.train) + len(run.scene.test)  # an acquired view is listed once
    finally:
        app.stop()
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(B3dgsError, match="not an active-view selection"):
        open_run(tiny_runs["niw"], acquired=str(tmp_path / "bad.json"))
