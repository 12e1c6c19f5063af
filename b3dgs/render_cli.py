"""``b3dgs-render run=DIR [path=test|train|interpolate|orbit|spiral|FILE.json] [panel=native_sigma]``: a finished run
rendered along a camera path to PNG frames and an MP4 (``conf/render.yaml``).

The path is the run's test (or training) cameras in name order, a smooth closed loop through them
(:func:`interpolate_cameras`: centres on a periodic cubic spline, orientations by spherical interpolation, the first
camera's intrinsics), a circle around the point they look at (:func:`orbit_cameras`), a spiral in front of a
forward-facing capture (:func:`spiral_cameras`, LLFF's render path), or a nerfstudio camera-path JSON
(:func:`nerfstudio_path`, the format ``ns-render camera-path`` reads). A panel frame names both panels. ``panel=`` puts one of ``b3dgs-view``'s modes beside the RGB (:class:`b3dgs.viewer.modes.
ModeRenderer`), with one colour scale for the whole path (``panel_max``, by default the 99th percentile over the
frames) drawn under it. The video is encoded by imageio-ffmpeg's own ffmpeg binary. Known problems print one line
``b3dgs-render: error: ... (fix: ...)`` and exit with code 2; the last line says where the frames went.
"""
from __future__ import annotations

import logging
import sys
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import Optional, Sequence

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from b3dgs.data.scene import SceneTransform, look_at_point, scene_frame
from b3dgs.errors import B3dgsError, cli_main, known_errors
from b3dgs.io import atomic_path, read_json_dict, write_json
from b3dgs.train import CONF_DIR
from b3dgs.types import Camera
from b3dgs.viewer.modes import MODES, ModeRenderer, colorize, colormap_lut, normalise, robust_max

log = logging.getLogger(__name__)

__all__ = ["camera_path", "interpolate_cameras", "main", "nerfstudio_path", "orbit_cameras", "render_path",
           "spiral_cameras", "write_video"]

PATHS = ("test", "train", "interpolate", "orbit", "spiral")  # or a nerfstudio camera-path JSON file
MADE = ("interpolate", "orbit", "spiral")  # the paths made of ``frames`` new cameras


def interpolate_cameras(cams: Sequence[Camera], frames: int) -> list[Camera]:
    """``frames`` cameras on a closed loop through ``cams`` (in their order): centres on a periodic cubic spline,
    orientations by spherical linear interpolation between neighbours, the first camera's intrinsics and size."""
    from scipy.interpolate import CubicSpline
    from scipy.spatial.transform import Rotation, Slerp

    cams = list(cams)
    if len(cams) < 2:
        return [cams[0]] * frames if cams else []
    c2w = np.stack([c.camtoworld.double().cpu().numpy() for c in cams + cams[:1]])
    knots = np.arange(len(c2w), dtype=np.float64)
    centres = CubicSpline(knots, c2w[:, :3, 3], bc_type="periodic")
    turns = Slerp(knots, Rotation.from_matrix(c2w[:, :3, :3]))
    t = np.linspace(0.0, len(cams), frames, endpoint=False)
    R, C = turns(t).as_matrix(), centres(t)
    ref = cams[0]
    out = []
    for i, (r, c) in enumerate(zip(R, C)):
        view = np.eye(4)
        view[:3, :3], view[:3, 3] = r.T, -r.T @ c
        out.append(Camera(f"path_{i:05d}", ref.K.clone(), torch.from_numpy(view).float(), ref.width, ref.height))
    return out


def _look_at(centre: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """World-to-camera (OpenCV: x right, y down, z forward) of a camera at ``centre`` looking at ``target``."""
    f = target - centre
    f = f / np.linalg.norm(f)
    r = np.cross(f, up)
    r = r / np.linalg.norm(r)
    d = np.cross(f, r)
    R = np.stack([r, d, f], axis=1)  # camera-to-world rotation, columns x, y, z
    view = np.eye(4)
    view[:3, :3], view[:3, 3] = R.T, -R.T @ centre
    return view


def orbit_cameras(cams: Sequence[Camera], frames: int) -> list[Camera]:
    """``frames`` cameras on a circle around the point the cameras look at (least squares over their optical axes,
    :func:`b3dgs.data.scene.look_at_point`; their mean centre when the axes are parallel), in the plane orthogonal to
    their mean up direction, at their mean distance from that axis and mean height along it, all looking at the point;
    the first camera's intrinsics and size. :func:`camera_path` passes every camera of the capture."""
    cams = list(cams)
    c2w = np.stack([c.camtoworld.double().cpu().numpy() for c in cams])
    centres = c2w[:, :3, 3]
    target, ok = look_at_point(np.stack([c.viewmat.double().cpu().numpy() for c in cams]))
    target = target if ok else centres.mean(0)
    up = -c2w[:, :3, 1].mean(0)  # OpenCV's y points down
    if not np.linalg.norm(up) > 1e-9:
        raise B3dgsError("path=orbit: the cameras have no common up direction", "pass path=interpolate")
    up = up / np.linalg.norm(up)
    rel = centres - target
    height = float((rel @ up).mean())
    flat = rel - np.outer(rel @ up, up)
    radius = float(np.linalg.norm(flat, axis=1).mean())
    if not radius > 1e-9:  # one camera, or every camera on the axis: no circle to draw
        raise B3dgsError("path=orbit: the cameras all lie on their own viewing axis, so there is no circle around it",
                         "pass path=spiral or path=interpolate")
    a = flat[0] / np.linalg.norm(flat[0]) if np.linalg.norm(flat[0]) > 1e-9 else np.cross(up, [1.0, 0.0, 0.0])
    a = a / np.linalg.norm(a)
    b = np.cross(up, a)
    ref = cams[0]
    out = []
    for i, t in enumerate(np.linspace(0.0, 2 * np.pi, frames, endpoint=False)):
        pos = target + height * up + radius * (np.cos(t) * a + np.sin(t) * b)
        out.append(Camera(f"orbit_{i:05d}", ref.K.clone(), torch.from_numpy(_look_at(pos, target, up)).float(),
                          ref.width, ref.height))
    return out


def spiral_cameras(cams: Sequence[Camera], frames: int, points: Optional[np.ndarray] = None,
                   rotations: float = 2.0) -> list[Camera]:
    """``frames`` cameras on LLFF's forward-facing render path: around the mean camera (mean centre, mean axes), in
    its image plane by the 90th percentile of the centres' offsets along its x and y and along its view axis at half
    the rate, ``rotations`` turns, all looking at the point the cameras look at (:func:`b3dgs.data.scene.look_at_point`
    where it lies in front of them; else the median depth of ``points`` (M, 3) in front; else 4 offsets ahead)."""
    cams = list(cams)
    c2w = np.stack([c.camtoworld.double().cpu().numpy() for c in cams])
    centres, mean = c2w[:, :3, 3], c2w[:, :3, 3].mean(0)
    z = c2w[:, :3, 2].mean(0)
    down = c2w[:, :3, 1].mean(0)
    if not (np.linalg.norm(z) > 1e-9 and np.linalg.norm(down) > 1e-9):
        raise B3dgsError("path=spiral: the cameras have no common view direction", "pass path=interpolate or orbit")
    z = z / np.linalg.norm(z)
    x = np.cross(down, z)
    x = x / np.linalg.norm(x)
    down = np.cross(z, x)
    rel = centres - mean
    rads = np.percentile(np.abs(rel @ np.stack([x, down, z], axis=1)), 90, axis=0)
    target, ok = look_at_point(np.stack([c.viewmat.double().cpu().numpy() for c in cams])) if len(cams) > 1 else (
        mean, False)
    depth = float((target - mean) @ z) if ok else 0.0
    if not depth > 0:
        ahead = None if points is None else (np.asarray(points, np.float64) - mean) @ z
        ahead = None if ahead is None else ahead[ahead > 0]
        depth = float(np.median(ahead)) if ahead is not None and len(ahead) else 4.0 * max(float(rads.max()), 0.05)
        target = mean + depth * z
    rads = np.maximum(rads, 0.02 * depth)  # one camera, or a capture along a line: a small circle still moves
    ref, out = cams[0], []
    for i, t in enumerate(np.linspace(0.0, 2 * np.pi * rotations, frames, endpoint=False)):
        pos = mean + rads[0] * np.cos(t) * x - rads[1] * np.sin(t) * down - rads[2] * np.sin(0.5 * t) * z
        out.append(Camera(f"spiral_{i:05d}", ref.K.clone(), torch.from_numpy(_look_at(pos, target, -down)).float(),
                          ref.width, ref.height))
    return out


def nerfstudio_path(file: Path, scene) -> list[Camera]:
    """The cameras of a nerfstudio camera-path JSON (the file ``ns-render camera-path`` reads): ``camera_path``, a
    list of ``{"camera_to_world": 16 numbers (4x4, row-major, OpenGL axes: x right, y up, z back), "fov": vertical
    field of view in degrees}``, with ``render_height`` and ``render_width`` (or each entry's ``aspect``). The poses
    are read in the scene's own frame (COLMAP's or transforms.json's: the frame of ``point_cloud.ply`` and of
    ``b3dgs-export``'s ``cameras.json``) and mapped into the run's normalised frame with ``scene.transform``."""
    import json

    fix = ("pass a camera-path JSON as nerfstudio's viewer exports it (camera_path with camera_to_world and fov, "
           "render_height), or path=test|train|interpolate|orbit|spiral")
    try:
        data = json.loads(Path(file).read_text())
        entries, H = data["camera_path"], int(data.get("render_height") or 0)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise B3dgsError(f"path={file} is not a readable nerfstudio camera path ({type(e).__name__}: {e})", fix) from None
    if not entries or H < 8:
        raise B3dgsError(f"path={file} is not a readable nerfstudio camera path "
                         f"({'no camera_path entries' if not entries else f'render_height {H} < 8'})", fix)
    try:
        out = []
        T = getattr(scene, "transform", None) or SceneTransform()
        Rn, s, t = np.asarray(T.rotation, np.float64), float(T.scale), np.asarray(T.translation, np.float64)
        for i, e in enumerate(entries):
            c2w = np.asarray(e["camera_to_world"], np.float64).reshape(4, 4)
            W = int(data.get("render_width") or round(H * float(e.get("aspect", 1.0))))
            fy = 0.5 * H / np.tan(0.5 * np.deg2rad(float(e["fov"])))
            R = Rn @ c2w[:3, :3] @ np.diag([1.0, -1.0, -1.0])  # OpenGL -> OpenCV axes, then into the normalised frame
            c = s * Rn @ c2w[:3, 3] + t
            view = np.eye(4)
            view[:3, :3], view[:3, 3] = R.T, -R.T @ c
            K = torch.tensor([[fy, 0.0, W / 2.0], [0.0, fy, H / 2.0], [0.0, 0.0, 1.0]], dtype=torch.float32)
            out.append(Camera(f"path_{i:05d}", K, torch.from_numpy(view).float(), W, H))
        return out
    except (ValueError, KeyError, TypeError, IndexError) as e:
        raise B3dgsError(f"path={file} is not a readable nerfstudio camera path ({type(e).__name__}: {e})", fix) from None


def check_path(path: str, frames) -> None:
    """``path`` names a camera path (or is a .json file) and, for a path it makes, ``frames`` is enough."""
    if str(path).endswith(".json"):
        return
    if path not in PATHS:
        raise B3dgsError(f"path={path} is not a camera path",
                         f"pass path= one of {', '.join(PATHS)}, or a nerfstudio camera-path .json file")
    if path in MADE and (not isinstance(frames, int) or isinstance(frames, bool) or frames < 2):
        raise B3dgsError(f"frames={frames} is too few for a path", "pass frames= an integer >= 2, e.g. frames=120")


def check_panel(panel: Optional[str]) -> None:
    """``panel`` is null or a mode drawn beside the RGB."""
    if panel and (panel not in MODES or panel == "rgb"):
        raise B3dgsError(f"panel={panel} is not a panel mode",
                         f"pass panel= one of {', '.join(k for k in MODES if k != 'rgb')}, or null")


def camera_path(scene, path: str, frames: int) -> list[Camera]:
    """The cameras of ``path`` (see the module doc), without images."""
    check_path(path, frames)
    if str(path).endswith(".json"):
        return nerfstudio_path(Path(path), scene)
    if path in ("spiral", "orbit"):  # the whole capture sets the point looked at, the mean pose and the spread
        every = [c.with_image(None) for c in sorted([*scene.train, *scene.test], key=lambda c: c.name)]
        if path == "spiral":
            return spiral_cameras(every, frames, getattr(scene, "points", None))
        if len(every) > 1 and scene_frame(every)["forward"]:
            log.warning("path=orbit: the capture is forward-facing (every camera on one side), so half the circle looks "
                        "at the scene from where no photo was taken; path=spiral stays in front of it")
        return orbit_cameras(every, frames)
    source = scene.train if path == "train" else (scene.test or scene.train)
    if path != "train" and not scene.test:
        log.info("path=%s: the run's scene has no test views (data.test_every=0): its training cameras instead", path)
    cams = [c.with_image(None) for c in sorted(source, key=lambda c: c.name)]
    if not cams:
        raise B3dgsError(f"the run's scene has no {path} cameras", "pass path=train")
    if path not in MADE:
        return cams
    return interpolate_cameras(cams, frames)


@lru_cache(maxsize=None)
def caption_font(size: int = 10):
    """The captions' font: DejaVu Sans, which matplotlib ships and which has σ and N̂ (PIL's built-in font draws σ as
    a missing-glyph box); PIL's own font where matplotlib's cannot be found."""
    from PIL import ImageFont

    try:
        from matplotlib import font_manager

        return ImageFont.truetype(font_manager.findfont("DejaVu Sans", fallback_to_default=False), size)
    except (ImportError, OSError, ValueError):
        return ImageFont.load_default()


def _legend(width: int, cmap: str, lo: float, hi: float, unit: str) -> np.ndarray:
    """A colour bar ``width`` px wide with its two ends written under it (uint8, (28, width, 3))."""
    from PIL import Image, ImageDraw

    bar = colormap_lut(cmap)[np.linspace(0, 255, width).round().astype(int)]
    img = np.full((28, width, 3), 255, np.uint8)
    img[2:12] = bar[None]
    pil = Image.fromarray(img)
    draw = ImageDraw.Draw(pil)
    font = caption_font()
    draw.text((1, 14), f"{lo:.3g}", fill=(0, 0, 0), font=font)
    right = f"{hi:.3g} {unit}".strip()
    draw.text((max(1, width - int(draw.textlength(right, font=font)) - 1), 14), right, fill=(0, 0, 0), font=font)
    return np.asarray(pil)


def _caption(height: int, width: int, text: str) -> np.ndarray:
    """A white strip (uint8 (height, width, 3)) with ``text`` written in it (under the RGB panel: what each panel is)."""
    from PIL import Image, ImageDraw

    pil = Image.fromarray(np.full((height, width, 3), 255, np.uint8))
    ImageDraw.Draw(pil).text((1, 8), text, fill=(0, 0, 0), font=caption_font())
    return np.asarray(pil)


def render_path(run, cams: Sequence[Camera], panel: Optional[str] = None, panel_max: Optional[float] = None,
                samples: int = 16, count_scale: Optional[float] = 0.1) -> tuple[list[np.ndarray], Optional[float]]:
    """The frames (uint8 (H, W', 3)) of ``run`` (a :class:`b3dgs.viewer.run.ViewedRun`) along ``cams``: the RGB,
    with the ``panel`` mode beside it on one colour scale for the path (and its colour bar under it). Returns the
    frames and the panel's scale top (None without a panel)."""
    from b3dgs.progress import progress

    modes = None
    check_panel(panel)
    if panel:
        modes = ModeRenderer(run.module, run.scene, samples=samples, count_scale=count_scale)
        why = modes.unavailable().get(panel)
        if why is not None:
            raise B3dgsError(f"panel={panel} is not available for this run: {why}", "pass panel=proxy_sigma, or null")
    rgbs, values = [], []
    for cam in progress(cams, desc="render", unit=" frames", file=sys.stdout, disable=len(cams) < 2):
        rgbs.append((run.module.render_eval(cam).cpu().numpy() * 255.0 + 0.5).astype(np.uint8))
        if modes is not None:
            fr = modes.render(panel, cam)
            values.append((fr.values, fr.mask))
    if modes is None:
        return rgbs, None
    spec = modes.specs[panel]
    top = panel_max
    if top is None and spec.kind == "pixel" and panel != "alpha":  # σ and depth: the path's own scale
        top = robust_max(torch.cat([v.reshape(-1) if m is None else v[m] for v, m in values]))
    if top is not None:
        from dataclasses import replace

        spec = replace(spec, hi=float(top))
    legend = _legend(rgbs[0].shape[1], spec.cmap, spec.lo, spec.hi, spec.unit.strip("()").split(",")[0])
    pad = _caption(legend.shape[0], rgbs[0].shape[1], f"left: RGB | right: {spec.label}")  # each panel named
    frames = []
    for rgb, (v, m) in zip(rgbs, values):
        side = np.concatenate([colorize(normalise(v, spec), spec.cmap, m), legend], axis=0)
        frames.append(np.concatenate([np.concatenate([rgb, pad], axis=0), side], axis=1))
    return frames, spec.hi


def write_video(path: Path, frames: Sequence[np.ndarray], fps: int) -> Path:
    """``frames`` as an H.264 MP4 (yuv420p, sizes padded to even numbers), written atomically."""
    try:
        import imageio_ffmpeg
    except ImportError:
        raise B3dgsError("writing the MP4 needs imageio-ffmpeg, which is not installed",
                         "pip install imageio-ffmpeg, or pass video=false") from None
    h, w = frames[0].shape[:2]
    H, W = h + h % 2, w + w % 2
    with atomic_path(path) as tmp:
        writer = imageio_ffmpeg.write_frames(str(tmp), (W, H), fps=float(fps), codec="libx264", pix_fmt_out="yuv420p",
                                             macro_block_size=1, quality=8, output_params=["-f", "mp4"],
                                             ffmpeg_log_level="error")
        writer.send(None)
        for f in frames:
            writer.send(np.ascontiguousarray(np.pad(f, ((0, H - h), (0, W - w), (0, 0)), mode="edge")))
        writer.close()
    return path


@contextmanager
def _claim(out: Path, names: Sequence[str]):
    """Make room for the frames and video ``names`` in ``out`` (never a run's ``checkpoints/``: :func:`render` checks):
    in a run dir, under its lock, the earlier frames its manifest lists in ``out`` go and ``names`` join the manifest
    before they are written; elsewhere, under the folder's own b3dgs-render lock, the files named as this command
    names frames (``frame_<5 digits>.png``).
    Nothing else is touched, and one of ``names`` that exists and is not b3dgs's is refused before anything goes."""
    from b3dgs.rundir import (FRAME_NAME, claim_in_run, holds_run, out_dir_lock, read_manifest, remove_listed,
                              run_files)

    q = out.resolve()
    owner = next((d for d in (q, *q.parents) if holds_run(d)), None)
    if owner is not None and read_manifest(owner, fix=_FIX_OUT) is not None:
        with claim_in_run(owner, out, names, "b3dgs-render", FRAME_NAME, check=lambda new: _refuse_foreign(out, new)):
            yield
        return
    with out_dir_lock(out, "b3dgs-render"):  # a second render into this folder is refused, not interleaved
        frames = [p.name for p in out.glob("frame_*.png") if FRAME_NAME.fullmatch(p.name)]
        # a video is b3dgs's where a record says so: the run's (written before manifests: the names its outputs had),
        # or outside a run the folder's RENDER_RECORD, written before the files
        theirs = set(run_files(owner)) if owner is not None else set()
        rel = "." if owner is None else q.relative_to(owner).as_posix()
        recorded = set((read_json_dict(out / RENDER_RECORD) or {}).get("files") or []) if owner is None else set()
        _refuse_foreign(out, [n for n in names if not FRAME_NAME.fullmatch(n) and n not in recorded
                              and (n if rel == "." else f"{rel}/{n}") not in theirs])
        remove_listed(out, frames)
        if owner is None:
            kept = {n for n in recorded if not FRAME_NAME.fullmatch(n) and (out / n).exists()}  # earlier paths' videos
            write_json(out / RENDER_RECORD, {"written_by": "b3dgs-render", "files": sorted(kept | set(names))})
        yield


RENDER_RECORD = ".b3dgs-render.json"  # outside a run dir: the videos b3dgs-render wrote into an out= folder


_FIX_OUT = "pass out=DIR to write the frames into another folder"


def _refuse_foreign(out: Path, names: Sequence[str]) -> None:
    """Refuse the files ``names`` of ``out`` that exist (b3dgs did not write them)."""
    there = [n for n in names if (out / n).exists() or (out / n).is_symlink()]
    if there:
        raise B3dgsError(f"out={out} holds {', '.join(there[:3])}, which b3dgs did not write and b3dgs-render would "
                         "replace", _FIX_OUT + " (or video=false)" if all(n.endswith(".mp4") for n in there) else _FIX_OUT)


def render(cfg: DictConfig) -> dict:
    """Render ``cfg.run`` along ``cfg.path`` into ``cfg.out``; returns what was written."""
    from b3dgs.data.images import save_png
    from b3dgs.validation import validate_config
    from b3dgs.viewer.run import open_run

    validate_config(cfg, app="render")
    check_path(str(cfg.path), cfg.get("frames"))  # what needs no run: refused before it loads
    check_panel(cfg.get("panel"))
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    fps, max_side, panel_max = cfg.fps, cfg.get("max_side"), cfg.get("panel_max")
    renderer = None
    if cfg.get("renderer"):
        from b3dgs.render.renderers import make_renderer

        renderer = make_renderer(str(cfg.renderer))
        renderer.check_available()
    run = open_run(Path(str(cfg.run)), renderer=renderer, data_path=OmegaConf.select(cfg, "data.path"))
    path = str(cfg.path)
    label = Path(path).stem if path.endswith(".json") else path  # the folder and video name of a path file
    out = Path(str(cfg.out)) if cfg.get("out") else run.path / "render" / label
    from b3dgs.rundir import read_manifest, refuse_in_checkpoints

    refuse_in_checkpoints(out, "b3dgs-render")
    if out.resolve().is_relative_to(run.path.resolve()):  # the frames join the run's manifest: check it first
        read_manifest(run.path, fix=_FIX_OUT)
    cams = [c.fit(max_side, upscale=True, min_side=8) for c in camera_path(run.scene, path, cfg.get("frames"))]
    frames, top = render_path(run, cams, cfg.get("panel"), panel_max, int(cfg.samples), cfg.get("count_scale"))
    with_video = cfg.get("video", True) and len(frames) > 1
    names = [f"frame_{i:05d}.png" for i in range(len(frames))] + ([f"{label}.mp4"] if with_video else [])
    with _claim(out, names):
        pngs = [save_png(out / n, f) for n, f in zip(names[:len(frames)], frames)]
        video = write_video(out / f"{label}.mp4", frames, fps) if with_video else None
    written = {"frames": [str(p) for p in pngs], "video": None if video is None else str(video), "panel_max": top}
    log.info("%s: %d frames of path=%s at %dx%d%s", run.path, len(frames), path, frames[0].shape[1], frames[0].shape[0],
             f", panel {cfg.get('panel')} 0 to {top:.3g}" if top is not None else "")
    return written


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="render")
def hydra_main(cfg: DictConfig) -> None:
    with known_errors("b3dgs-render", cfg, quiet=True):
        w = render(cfg)
        where = Path(w["frames"][0]).parent
        video = f" and {w['video']}" if w["video"] else ""
        print(f"b3dgs-render: wrote {len(w['frames'])} frames to {where}/frame_*.png{video}", flush=True)


main = cli_main("b3dgs-render", hydra_main, "render")


if __name__ == "__main__":
    main()
