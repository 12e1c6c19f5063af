"""b3dgs-process (issue 44 §2): photos without their poses become a COLMAP scene whose registered cameras match the
true poses up to a similarity, that b3dgs loads and trains with the printed command; a rerun skips every stage, a
changed option reruns only what depends on it, and bad input is one line. Every test but one runs on a fresh clone
(issue 52: SfM is exercised without ../shared), on photos the tests render from b3dgs.data.synthetic's world with a
noise albedo, and tiny videos they write; the one test on real photos, ten of flower's (../shared), checks the
registration against flower's original LLFF/COLMAP poses."""
import math
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
ENV = {**{k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"},
       "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
SHARED = Path(os.environ.get("B3DGS_SHARED") or ROOT.parent / "shared") / "data"
FLOWER = SHARED / "flower"
VIEWS, SIDE, MAX_SIDE = 10, 200, 128

#: the test on flower's photos (../shared); every other test runs on a fresh clone
needs_flower = pytest.mark.skipif(not (FLOWER / "sparse" / "0").is_dir(), reason=f"no shared scene at {FLOWER}")


def _cli(args, cwd=ROOT, timeout=600):
    return subprocess.run([sys.executable, "-m", "b3dgs.process", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd, env=ENV)


def _cfg(**kw):
    """conf/process.yaml with ``kw`` set, for b3dgs.process.process in this process."""
    from omegaconf import OmegaConf

    base = OmegaConf.load(ROOT / "conf" / "process.yaml")
    for key in ("defaults", "hydra"):
        base.pop(key)
    return OmegaConf.merge(base, kw)


def _photos(folder: Path, names, src=FLOWER / "images", side=SIDE) -> Path:
    """``names`` of ``src`` as JPEG photos with the long side ``side``, the way a user's folder holds them: no poses."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    for n in names:
        with Image.open(src / n) as im:
            im = im.convert("RGB")
            im.thumbnail((side, side), Image.LANCZOS)
            im.save(folder / f"{Path(n).stem}.jpg", quality=95)
    return folder


def umeyama(src: np.ndarray, dst: np.ndarray):
    """(s, R, t) minimising Σ|s R src_i + t - dst_i|² (Umeyama 1991, closed form by SVD, reflections excluded).

    SfM recovers cameras only up to a similarity (scale, rotation, translation), so registered centres are compared
    with the originals after this fit; scipy's ``procrustes`` standardises both sets and returns no transform, which
    the rotations need too."""
    ms, md = src.mean(0), dst.mean(0)
    xs, xd = src - ms, dst - md
    U, D, Vt = np.linalg.svd(xd.T @ xs / len(src))
    E = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ E @ Vt
    s = float(np.trace(np.diag(D) @ E) / (xs ** 2).sum(1).mean())
    return s, R, md - s * R @ ms


def _angle(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """The CLI run once on ten evenly spaced flower photos at 200 px (out of the 25)."""
    root = tmp_path_factory.mktemp("process")
    names = sorted(p.name for p in (FLOWER / "images").iterdir())
    pick = [names[i] for i in np.linspace(0, len(names) - 1, VIEWS).round().astype(int)]
    photos = _photos(root / "photos", pick)
    out = root / "flower_mine"
    t0 = time.perf_counter()
    res = _cli([f"images={photos}", f"out={out}", f"max_side={MAX_SIDE}"])
    seconds = time.perf_counter() - t0
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    print(f"b3dgs-process on {VIEWS} photos: {seconds:.1f} s\n{res.stdout}")
    return {"root": root, "photos": photos, "out": out, "stdout": res.stdout}


@needs_flower
def test_registered_poses_match_the_originals_up_to_a_similarity(made):
    from b3dgs.data.colmap import read_colmap

    assert f"{VIEWS} of {VIEWS} photos registered" in made["stdout"] or "9 of 10 photos registered" in made["stdout"]
    est = {Path(f.name).stem: f.viewmat for f in read_colmap(made["out"])[0]}
    gt = {Path(f.name).stem: f.viewmat for f in read_colmap(FLOWER)[0]}
    assert len(est) >= VIEWS - 1 and set(est) <= set(gt)
    names = sorted(est)

    def centre(v):
        return -v[:3, :3].T @ v[:3, 3]

    A = np.array([centre(est[n]) for n in names])
    B = np.array([centre(gt[n]) for n in names])
    s, R, t = umeyama(A, B)
    residual = np.linalg.norm(s * A @ R.T + t - B, axis=1)
    spread = np.linalg.norm(B - B.mean(0), axis=1).mean()
    assert residual.max() < 0.05 * spread, (residual / spread).round(4)
    # every camera's orientation after the same alignment: the 2° (measured 0.9°)
    errors = [_angle(gt[n][:3, :3] @ (est[n][:3, :3] @ R.T).T) for n in names]
    assert max(errors) < 2.0, np.round(errors, 2)


def test_the_output_reads_without_pycolmap_as_pycolmap_reads_it(synthetic):
    """b3dgs.data.colmap_model (the loader's NumPy reader) gives the model pycolmap gives: cameras, poses bit for bit,
    2D points, 3D points in pycolmap's order, colours and tracks."""
    from tests.test_colmap_reader import _assert_same, _numpy_view, _pycolmap_view

    model = synthetic["out"] / "sparse" / "0"
    _assert_same(_numpy_view(model, points2d=True), _pycolmap_view(model, points2d=True))


def test_the_scene_loads_and_trains_with_the_printed_command(synthetic, tmp_path):
    from b3dgs.data.scene import load_scene

    out = synthetic["out"]
    scene = load_scene("colmap", out, max_side=None)
    cams = list(scene.train) + list(scene.test)
    assert len(cams) == SYN_VIEWS and len(scene.test) >= 1
    assert all(max(c.width, c.height) <= MAX_SIDE for c in cams)
    assert max(max(c.width, c.height) for c in cams) == MAX_SIDE  # resized from the undistorted photos
    yaml = (out / "conf" / "scene" / "synthetic_mine.yaml").read_text()
    assert yaml.startswith("# @package _global_\n") and "override /data: colmap" in yaml
    line = next(ln for ln in synthetic["stdout"].splitlines() if ln.startswith("train it: "))
    argv = shlex.split(line.removeprefix("train it: "))
    assert argv[:2] == ["b3dgs-train", "scene=synthetic_mine"], argv
    res = subprocess.run([sys.executable, "-m", "b3dgs.train", *argv[1:], "trainer.max_steps=3",
                          "trainer.eval_every=100", "trainer.enable_progress_bar=false", "logger=none", "threads=1",
                          f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True, timeout=600,
                         cwd=tmp_path, env=ENV)
    assert res.returncode == 0, res.stderr[-3000:]
    import json

    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["scene"] == "synthetic_mine" and metrics["num_train_views"] + metrics["num_test_views"] == len(cams)


def test_a_rerun_skips_every_stage(synthetic):
    out = synthetic["out"]
    before = {p: p.stat().st_mtime_ns for p in (out / "sparse" / "0").iterdir()}
    res = _cli([f"images={synthetic['photos']}", f"out={out}", f"max_side={MAX_SIDE}"])
    assert res.returncode == 0, res.stderr[-3000:]
    lines = res.stdout.splitlines()
    for i, stage in enumerate(("extract", "match", "map", "undistort")):
        assert any(ln.startswith(f"[{i + 1}/4] {stage}: done earlier") and ln.endswith("skipped") for ln in lines), lines
    assert {p: p.stat().st_mtime_ns for p in (out / "sparse" / "0").iterdir()} == before


def test_a_moved_copy_resumes_a_new_max_side_reruns_only_undistort_and_a_changed_folder_is_refused(synthetic,
                                                                                                      tmp_path):
    from b3dgs.errors import B3dgsError
    from b3dgs.process import process

    photos, out = tmp_path / "photos", tmp_path / "scene"
    shutil.copytree(synthetic["photos"], photos)  # copy2: same names, sizes and modification times
    shutil.copytree(synthetic["out"], out)
    w = process(_cfg(images=str(photos), out=str(out), max_side=64))
    assert [w["stages"][s]["skipped"] for s in ("extract", "match", "map", "undistort")] == [True, True, True, False]
    from PIL import Image

    assert all(max(Image.open(p).size) <= 64 for p in (out / "images").iterdir())
    assert 'path: "' + str(out) + '"' in (out / "conf" / "scene" / "scene.yaml").read_text()  # named after out
    first = sorted(photos.glob("view_*.png"))[0]
    first.unlink()
    with pytest.raises(B3dgsError, match="changed since .* was processed from it .0 added, 1 removed") as e:
        process(_cfg(images=str(photos), out=str(out)))
    assert "overwrite=true" in e.value.fix
    w = process(_cfg(images=str(photos), out=str(out), overwrite=True, max_side=64))
    assert not any(s["skipped"] for s in w["stages"].values()) and w["photos"] == SYN_VIEWS + 2 - 1


def test_bad_input_is_one_line(tmp_path):
    from b3dgs.errors import B3dgsError
    from b3dgs.process import process

    (tmp_path / "empty").mkdir()
    res = _cli([f"images={tmp_path / 'empty'}", f"out={tmp_path / 'o'}"], timeout=120)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1, res.stderr[-2000:]
    assert lines[0].startswith("b3dgs-process: error: images=") and "holds no photos" in lines[0] and "(fix: " in lines[0]
    assert not (tmp_path / "o").exists()
    two, three, broken = tmp_path / "two", tmp_path / "three", tmp_path / "broken"
    synthetic_photos(two, n=2, side=64)
    cases = [
        (dict(images=str(tmp_path / "nope")), "no such folder"),
        (dict(images=str(two)), "holds 2 photos; structure from motion needs at least 3"),
    ]
    synthetic_photos(three, n=3, side=64)
    synthetic_photos(broken, n=3, side=64)
    (broken / "zz.jpg").write_text("not a photo")
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "notes.txt").write_text("mine")
    cases += [
        (dict(images=str(three), out=str(tmp_path / "busy")), r"holds what b3dgs-process did not write \(notes.txt\)"),
        (dict(images=str(broken)), r"cannot read the photo .*zz.jpg"),
        (dict(images=str(three), matcher="exhaustiv"), "matcher=exhaustiv is not a matcher; did you mean exhaustive"),
        (dict(images=str(three), camera_model="OPENCV_FISHEYES"), "did you mean OPENCV_FISHEYE"),
        (dict(images=str(three), out=str(tmp_path)), "is inside out="),
        (dict(images=str(three), name="fern"), "name=fern is a scene b3dgs already has"),
    ]
    for kw, want in cases:
        with pytest.raises(B3dgsError, match=want) as e:
            process(_cfg(**{"out": str(tmp_path / "o"), **kw}))
        assert e.value.fix, kw
    assert not (tmp_path / "o").exists()


def test_too_few_registered_says_how_many_and_what_to_try(tmp_path):
    """Three photos of three unrelated scenes (smooth random blotches, each its own): SIFT finds features in each, but
    nothing to register; the refusal counts and names what to try."""
    from PIL import Image

    photos = tmp_path / "mixed"
    photos.mkdir()
    for i in range(3):
        blotches = np.random.default_rng(10 + i).integers(0, 256, (20, 20, 3), dtype=np.uint8)
        Image.fromarray(blotches).resize((160, 160), Image.BICUBIC).save(photos / f"scene_{i}.jpg", quality=95)
    res = _cli([f"images={photos}", f"out={tmp_path / 'o'}"], timeout=300)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]  # pycolmap's own log stays quiet
    assert res.returncode == 2 and len(lines) == 1, res.stderr[-2000:]
    assert re.search(r"only [0-2] of 3 photos registered after 3 mapping tries; b3dgs-process needs 3", lines[0])
    assert "more overlap" in lines[0] and "larger photos (these are at most 160 px)" in lines[0]


def test_sigterm_stops_at_once_with_one_line_and_the_rerun_resumes(synthetic, tmp_path):
    """SIGTERM while a stage's pycolmap call runs: exit 143 with one line (not glog's stack trace, which pycolmap
    installs for SIGTERM), no stage recorded half done; the same command then finishes the scene."""
    import json
    import signal

    out = tmp_path / "scene"
    args = [sys.executable, "-m", "b3dgs.process", f"images={synthetic['photos']}", f"out={out}",
            f"max_side={MAX_SIDE}"]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=ENV)
    for line in proc.stdout:
        if line.startswith("[1/4] extract"):  # printed just before the call into pycolmap
            proc.send_signal(signal.SIGTERM)
            break
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err[-2000:]
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("b3dgs-process: interrupted by SIGTERM during the "), err[-2000:]
    state = json.loads((out / ".b3dgs-process.json").read_text())
    assert "undistort" not in state["stages"] and not (out / "images").exists()
    res = _cli([f"images={synthetic['photos']}", f"out={out}", f"max_side={MAX_SIDE}"])
    assert res.returncode == 0, res.stderr[-2000:]
    assert (out / "sparse" / "0" / "images.bin").is_file()


# ---------------------------------------------------------------------------------------------- without ../shared
SYN_VIEWS, SYN_SIDE = 10, 160


class _Noise:
    """A non-repeating albedo: the sum of 24 random 3D sinusoids (about 1 cycle per 0.17 units). The synthetic world's
    own albedo (a few slow sinusoids) gives SIFT too little: 10 views at 160 px registered 0 of 10, this 10 of 10."""

    def __init__(self, rng: np.random.Generator, base: np.ndarray):
        self.base, self.freq = base, rng.normal(size=(24, 3)) * 6.0
        self.phase, self.weight = rng.uniform(0, 2 * np.pi, 24), rng.normal(size=(24, 3)) * 0.12

    def __call__(self, p: np.ndarray) -> np.ndarray:
        return np.clip(self.base + np.sin(2 * np.pi * p @ self.freq.T + self.phase) @ self.weight, 0.03, 0.97)


def synthetic_photos(folder: Path, n: int = SYN_VIEWS, side: int = SYN_SIDE) -> dict:
    """``n`` PNG photos of b3dgs.data.synthetic's world (seed 0, its albedo made :class:`_Noise`), on a 60° arc at 35°
    elevation, looking at its centre; returns their world-to-camera matrices by photo name."""
    from PIL import Image

    from b3dgs.data.synthetic import look_at, make_world

    world, rng = make_world(0), np.random.default_rng(1)
    for e in world.ellipsoids:
        e.albedo = _Noise(rng, e.albedo.base)
    world.disk_albedo = _Noise(rng, world.disk_albedo.base)
    f = 0.5 * side / math.tan(math.radians(50) / 2)
    K = np.array([[f, 0, side / 2], [0, f, side / 2], [0, 0, 1.0]])
    folder.mkdir(parents=True, exist_ok=True)
    poses = {}
    for i in range(n):
        az, el = math.radians(-30 + 60 * i / (n - 1)), math.radians(35)
        V = look_at(3.2 * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]),
                    np.array([0.0, 0.0, 0.35]))
        img, _ = world.render(K, V, side, side, depth=False)
        Image.fromarray((np.clip(img, 0, 1) * 255).round().astype(np.uint8)).save(folder / f"view_{i:02d}.png")
        poses[f"view_{i:02d}.png"] = V
    return poses


def _poses(out: Path) -> dict:
    import pycolmap

    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    return {im.name: np.asarray(im.cam_from_world().matrix()) for im in rec.images.values() if im.has_pose}


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """The CLI on ten synthetic views plus a flat grey photo (no SIFT features), a photo of noise (features that
    match nothing) and a text file; then :func:`b3dgs.process.process` on the same folder into a second out=."""
    from PIL import Image

    from b3dgs.process import process

    root = tmp_path_factory.mktemp("synthetic")
    photos = root / "photos"
    truth = synthetic_photos(photos)
    Image.new("RGB", (SYN_SIDE, SYN_SIDE), (128, 128, 128)).save(photos / "zz_flat.png")
    noise = np.random.default_rng(2).integers(0, 256, (SYN_SIDE, SYN_SIDE, 3), dtype=np.uint8)
    Image.fromarray(noise).save(photos / "zz_noise.png")
    (photos / "notes.txt").write_text("not a photo")
    t0 = time.perf_counter()
    res = _cli([f"images={photos}", f"out={root / 'synthetic_mine'}", f"max_side={MAX_SIDE}"])
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    print(f"b3dgs-process on {SYN_VIEWS} + 2 synthetic photos: {time.perf_counter() - t0:.1f} s\n{res.stdout}")
    again = process(_cfg(images=str(photos), out=str(root / "again"), max_side=MAX_SIDE))
    return {"root": root, "photos": photos, "truth": truth, "out": root / "synthetic_mine", "stdout": res.stdout,
            "again": again}


def test_sfm_registers_synthetic_photos_at_their_true_poses(synthetic):
    """SfM without ../shared: every rendered view registered, its centre and orientation those it was rendered
    from up to a similarity."""
    est, truth = _poses(synthetic["out"]), synthetic["truth"]
    assert sorted(est) == sorted(truth), sorted(est)
    names = sorted(est)

    def centre(v):
        return -v[:3, :3].T @ v[:3, 3]

    A, B = np.array([centre(est[n]) for n in names]), np.array([centre(truth[n]) for n in names])
    s, R, t = umeyama(A, B)
    residual = np.linalg.norm(s * A @ R.T + t - B, axis=1)
    spread = np.linalg.norm(B - B.mean(0), axis=1).mean()
    assert residual.max() < 0.05 * spread, (residual / spread).round(4)
    # orientations relative to the first view's (free of the similarity, which centres on a 60° arc pin down
    # loosely about the arc's chord: the fitted R alone left a common 2° on every view)
    R0, T0 = est[names[0]][:3, :3], truth[names[0]][:3, :3]
    # measured: 0.2° per view, 1.8° at the far end of the arc (the focal length, fitted from 160 px photos, trades
    # against the arc's angle); a registration gone wrong is tens of degrees
    errors = [_angle((truth[n][:3, :3] @ T0.T) @ (est[n][:3, :3] @ R0.T).T) for n in names[1:]]
    assert max(errors) < 2.5, np.round(errors, 2)


def test_the_same_photos_and_seed_give_the_same_scene(synthetic):
    """Issue 52: the same photos twice (all threads) give the same registered photos and the same poses. COLMAP's
    extractor numbered photos in the order its threads finished them (000.jpg was image 1 in one run, 2 in the next),
    which reorders each pair's matches and so RANSAC's samples and the mapper's ties, and geometric verification
    seeded each RANSAC at random: 25 of flower's photos registered 25, 24, 25, 24. With the ids in name order and
    RANSAC seeded by seed=, two runs measured equal to the last bit; the tolerance (1e-9) leaves room only for a
    multi-threaded sum added in another order, far below the 0.12 the unseeded runs differed by."""
    a, b = _poses(synthetic["out"]), _poses(synthetic["root"] / "again")
    assert sorted(a) == sorted(b) and len(a) == SYN_VIEWS
    assert max(float(np.abs(a[n] - b[n]).max()) for n in a) < 1e-9
    assert (synthetic["out"] / "sparse" / "0" / "points3D.bin").read_bytes() == \
        (synthetic["root"] / "again" / "sparse" / "0" / "points3D.bin").read_bytes()


def test_the_summary_names_every_photo_left_out_and_why(synthetic):
    lines = synthetic["stdout"].splitlines()
    assert f"{SYN_VIEWS} of {SYN_VIEWS + 2} photos registered" in synthetic["stdout"]
    assert "left out (no SIFT features found): 1 photo: zz_flat.png" in lines, lines[-8:]
    assert any(ln.startswith("left out (") and ln.endswith("1 photo: zz_noise.png") for ln in lines), lines[-8:]
    assert "not read (not a photo: .jpg .jpeg .png .bmp .tif .tiff): notes.txt" in lines, lines[-8:]
    left = synthetic["again"]["left_out"]
    assert sorted(left) == ["zz_flat.png", "zz_noise.png"] and synthetic["again"]["not_photos"] == ["notes.txt"]


def _video(path: Path, frames: int = 10, fps: int = 5, **kw) -> Path:
    """A tiny MP4 (64 x 48, ``frames`` frames at ``fps``) written with imageio-ffmpeg from synthetic frames."""
    import imageio_ffmpeg

    rng = np.random.default_rng(0)
    w = imageio_ffmpeg.write_frames(str(path), (64, 48), fps=fps, macro_block_size=16, ffmpeg_log_level="error", **kw)
    w.send(None)
    for i in range(frames):
        f = np.zeros((48, 64, 3), np.uint8)
        f[..., 0] = (np.arange(64) * 4 + 20 * i) % 256
        f[..., 1] = rng.integers(0, 256, (48, 64))
        w.send(np.ascontiguousarray(f))
    w.close()
    return path


def test_video_frames_are_extracted_whole_and_a_broken_video_is_one_line(tmp_path):
    """video= fps=: ffmpeg decodes every frame (2 s at fps=2: 4 frames, 64 x 48 JPEGs, dated like the video so a
    second extraction lists the same); a truncated clip (its index first, as +faststart writes it, so ffmpeg opens
    it and runs out of data) and a file that is no video are refused in one line, and so are a missing video and
    images= with video=."""
    from PIL import Image

    from b3dgs.errors import B3dgsError
    from b3dgs.process import extract_frames, process

    clip = _video(tmp_path / "clip.mp4", output_params=["-movflags", "+faststart"])
    assert extract_frames(clip, tmp_path / "f", 2.0) == 4
    frames = sorted((tmp_path / "f").iterdir())
    assert [f.name for f in frames] == [f"frame_{i:05d}.jpg" for i in range(1, 5)]
    assert all(Image.open(f).size == (64, 48) for f in frames)
    assert {f.stat().st_mtime_ns for f in frames} == {clip.stat().st_mtime_ns}
    data = clip.read_bytes()
    (tmp_path / "cut.mp4").write_bytes(data[: int(len(data) * 0.7)])
    with pytest.raises(B3dgsError, match=r"cannot decode video=.*cut.mp4 whole \([0-3] frames read\): ") as e:
        extract_frames(tmp_path / "cut.mp4", tmp_path / "g", 2.0)
    assert "re-encode" in e.value.fix
    (tmp_path / "junk.mp4").write_text("not a video")
    res = _cli([f"video={tmp_path / 'junk.mp4'}", f"out={tmp_path / 'o'}"], timeout=120)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1, res.stderr[-2000:]
    assert lines[0].startswith("b3dgs-process: error: cannot decode video=") and "(fix: re-encode" in lines[0]
    assert not (tmp_path / "o" / "images").exists()
    cases = [(dict(video=str(tmp_path / "nope.mp4")), "video=.*nope.mp4: no such file"),
             (dict(video=str(clip), images=str(tmp_path / "f")), "both images=.* and video=.* given"),
             (dict(), "no photos given"),
             (dict(video=str(clip), fps=0), "fps=0 is invalid: it must be a frame rate")]
    for kw, want in cases:
        with pytest.raises(B3dgsError, match=want):
            process(_cfg(**{"out": str(tmp_path / "o2"), **kw}))
    assert not (tmp_path / "o2").exists()


def test_a_video_goes_on_as_photos_and_a_rerun_reuses_its_frames(tmp_path):
    """The frames land in out/.b3dgs-process/frames and the stages follow (SfM on 64 px frames of stripes is not
    expected to register: the refusal is the mapper's, after the frames and every earlier stage ran); a second run
    finds the frames (no new extraction), and another video into the same out= is refused."""
    from b3dgs.errors import B3dgsError
    from b3dgs.process import process

    clip = _video(tmp_path / "clip.mp4", frames=15)
    out = tmp_path / "o"
    with pytest.raises(B3dgsError, match="photos registered|no features|extracted no features"):
        process(_cfg(video=str(clip), fps=2, out=str(out)))
    frames = out / ".b3dgs-process" / "frames"
    assert sorted(p.name for p in frames.iterdir()) == [f"frame_{i:05d}.jpg" for i in range(1, 7)]
    before = {p.name: p.stat().st_ino for p in frames.iterdir()}
    with pytest.raises(B3dgsError, match="photos registered|no features|extracted no features"):
        process(_cfg(video=str(clip), fps=2, out=str(out)))
    assert {p.name: p.stat().st_ino for p in frames.iterdir()} == before
    other = _video(tmp_path / "other.mp4", frames=12)
    with pytest.raises(B3dgsError, match="was processed from video=.*clip.mp4 fps=2, not this video="):
        process(_cfg(video=str(other), fps=2, out=str(out)))


def test_scene_file_false_writes_no_scene_file_and_takes_a_packaged_name(synthetic, tmp_path):
    """scene_file=false (what b3dgs-data get runs, for scenes with their own conf/scene/<name>.yaml): a packaged
    scene's name is accepted, no conf/ is written (an earlier run's scene file goes), and the printed command is
    data.path=; the default still refuses that name."""
    photos, out = tmp_path / "photos", tmp_path / "scene"
    shutil.copytree(synthetic["photos"], photos)
    shutil.copytree(synthetic["out"], out)  # holds conf/scene/synthetic_mine.yaml
    res = _cli([f"images={photos}", f"out={out}", f"max_side={MAX_SIDE}", "name=dtu_scan24"])
    assert res.returncode == 2 and "name=dtu_scan24 is a scene b3dgs already has" in res.stderr, res.stderr[-2000:]
    res = _cli([f"images={photos}", f"out={out}", f"max_side={MAX_SIDE}", "name=dtu_scan24", "scene_file=false"])
    assert res.returncode == 0, res.stderr[-3000:]
    assert not (out / "conf").exists() and (out / "sparse" / "0").is_dir()
    lines = res.stdout.splitlines()
    assert f"scene: {out}/images, {out}/sparse/0" in lines and f"train it: b3dgs-train data=colmap data.path={out}" in lines


def test_b3dgs_data_gets_a_photo_scene_of_a_packaged_name(synthetic, tmp_path, capsys):
    """The registry's `process` layout step (dtu_scan24, dtu_scan65, ethiopian_head on a fresh clone) makes the
    COLMAP scene under the scene's own name; b3dgs-process's lines naming its staging folder are not passed on. The
    SfM stages resume from a copy of the fixture's (same photos), so only the layout is new here."""
    from b3dgs.datasets import _process

    folder = tmp_path / "scene"
    shutil.copytree(synthetic["photos"], folder)
    shutil.copytree(synthetic["out"], tmp_path / "scene-sfm")
    got = _process(folder, {"images": ".", "pattern": "*.png", "max_side": MAX_SIDE}, "dtu_scan24")
    assert got == tmp_path / "scene-sfm" and not folder.exists() and not (tmp_path / "scene-photos").exists()
    assert sorted(p.name for p in got.iterdir()) == ["images", "sparse"]  # no scene file, no SfM work files
    said = capsys.readouterr().out.splitlines()
    assert said[0].startswith("dtu_scan24: structure from motion: ") and "scene_file=false" in said[0]
    assert any(s.startswith("b3dgs-process: ") and "photos registered" in s for s in said), said
    assert not any(s.startswith(("scene: ", "train it: ")) for s in said), said
