"""The viser app of ``b3dgs-view``: the render loop, the side panel, camera frusta.

A browser opens on an orbit view that frames the scene (:func:`home_view`: from the side the cameras look from, at
their median distance from the point they look at); "Home" in the panel returns there, and the camera list or a
click on a frustum looks through a camera. Frusta are thin outlines (the training photos on them with ``photos``).

One render thread serves every connected browser (a 2-core machine renders one frame at a time). Frames follow the
browser's canvas size up to ``max_side`` (the long side). A browser that moves its camera gets frames at a reduced
resolution, chosen from the measured cost of the current mode so that a frame takes about ``target_ms`` (the σ modes
draw S/4 samples then); once the camera has been still for ``still_ms`` the view is refined, doubling the long side
per frame up to the full size. The σ modes' colour scale is the 99th percentile of their first frame unless
``sigma_max`` (or the panel's number) fixes it. The panel states the last frame's time, size and pass.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from b3dgs.errors import B3dgsError
from b3dgs.viewer.cameras import camera_pose, fov_y, render_size, view_camera
from b3dgs.viewer.modes import (MIN_ALPHA, MODES, SIGMA_MODES, Frame, ModeRenderer, ModeSpec, colorize, colormap_lut, normalise,
                                robust_max)

log = logging.getLogger(__name__)

__all__ = ["ViewerApp", "ViewerSettings", "home_view"]

TRAIN_COLOUR, TEST_COLOUR = (150, 150, 160), (230, 60, 40)
CANDIDATE_COLOUR, ACQUIRED_COLOUR = (90, 90, 100), (40, 120, 240)
SUGGESTED_COLOUR = (40, 200, 90)  # b3dgs-suggest's poses, labelled with their rank


@dataclass
class ViewerSettings:
    host: str = "127.0.0.1"
    port: int = 8080
    max_side: Optional[int] = 1024  # cap on the render's long side (it follows the browser's canvas up to here)
    min_side: int = 32  # the low pass never goes below this long side
    target_ms: float = 100.0  # the low pass aims at this frame time
    still_ms: float = 250.0  # camera still this long -> refine to full resolution
    samples: int = 16  # S draws per σ frame
    jitter: float = 0.002  # proxy σ: centre jitter × scene extent
    sigma_max: Optional[float] = None  # σ modes' colour scale top (RGB units); None: 99th percentile of the first frame
    count_scale: Optional[float] = 0.1  # native σ: N̂ <- c·N̂ as uq=native draws it (None: the model's own)
    mode: str = "rgb"  # the mode shown first
    start: str = "orbit"  # orbit: a view framing the scene; camera: through the first listed camera
    frusta: bool = True  # the cameras shown first (a checkbox in the panel)
    photos: bool = False  # the training photos on the frusta (at most ``thumbnails`` cameras)
    thumbnails: int = 200
    jpeg_quality: int = 90


class _ClientState:
    def __init__(self, client) -> None:
        self.client = client
        self.version = 0  # bumped by every camera move or setting change
        self.shown_version = -1
        self.shown_side = 0  # long side of the frame shown now
        self.last_move = 0.0
        self.frusta: dict = {}  # camera name -> this browser's frustum handle
        self.hidden: Optional[str] = None  # the frustum of the camera it looks through


class ViewerApp:
    """``ViewerApp(run, settings).start()`` serves the viewer; ``stop()`` ends it."""

    def __init__(self, run, settings: ViewerSettings) -> None:
        import viser  # optional dependency: pip install -e ".[viewer]"

        self.run, self.s = run, settings
        self.scene = run.scene
        self.modes = ModeRenderer(run.module, run.scene, samples=settings.samples, jitter=settings.jitter,
                                  sigma_max=settings.sigma_max or 0.03, seed=0, count_scale=settings.count_scale)
        # σ modes whose scale comes from the data (the first frame's 99th percentile) until a number fixes it
        self.auto = {k: settings.sigma_max is None for k in SIGMA_MODES}
        self.ranged: set[str] = set()
        if settings.mode not in self.modes.available():
            why = self.modes.unavailable().get(settings.mode, f"modes: {', '.join(self.modes.specs)}")
            raise B3dgsError(f"viewer mode {settings.mode} is not available for this run: {why}",
                             fix=f"pass b3dgs-view mode= one of {', '.join(self.modes.available())}")
        self.cap = int(settings.max_side or 4096)
        self.cost: dict[str, float] = {}  # seconds per pixel, per mode (EMA)
        self.clients: dict[int, _ClientState] = {}
        self.lock = threading.Lock()
        self.wake = threading.Event()
        self.stopping = False
        self.server = viser.ViserServer(host=settings.host, port=settings.port, label="b3dgs-view", verbose=False)
        self.up = self._up_direction()
        self.server.scene.set_up_direction(tuple(self.up))
        self._cameras = self._camera_list()
        self.home = home_view(self.scene, self.up)
        ic = self.server.initial_camera  # the start pose and viser's "Reset View"
        ic.position, ic.look_at, ic.up, ic.fov = self.home["position"], self.home["look_at"], tuple(self.up), self.home["fov"]
        self._build_gui()
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(self._on_disconnect)
        self.thread = threading.Thread(target=self._loop, name="b3dgs-view-render", daemon=True)

    # ------------------------------------------------------------------ set-up
    def url(self) -> str:
        return f"http://{self.s.host}:{self.server.get_port()}"

    def _up_direction(self) -> np.ndarray:
        """The mean 'up' (−y of the cameras) of the training cameras, normalised."""
        ups = [-c.camtoworld[:3, 1].double().cpu().numpy() for c in self.scene.train] or [np.array([0.0, 0.0, 1.0])]
        up = np.mean(ups, axis=0)
        n = np.linalg.norm(up)
        return up / n if n > 1e-6 else np.array([0.0, 0.0, 1.0])

    def _camera_list(self) -> list[tuple[str, object, str]]:
        """(label, camera, kind) for the jump list: b3dgs-suggest's suggestions (rank order) and acquired views (pick
        order) first, then test, then train."""
        sc = self.scene
        pool = {c.name: c for c in list(sc.train) + list(getattr(sc, "candidates", None) or [])}
        out = [(f"suggested #{i + 1}: {c.name}", c, "suggested") for i, c in enumerate(getattr(self.run, "suggested", []))]
        for i, name in enumerate(self.run.acquired):
            if name in pool:
                out.append((f"acquired #{i + 1}: {name}", pool[name], "acquired"))
        out += [(f"test: {c.name}", c, "test") for c in sc.test]
        acq = set(self.run.acquired)
        out += [(f"train: {c.name}", c, "train") for c in sc.train if c.name not in acq]
        out += [(f"candidate: {c.name}", c, "candidate") for c in getattr(sc, "candidates", None) or []
                if c.name not in acq]
        return out

    def _build_gui(self) -> None:
        gui = self.server.gui
        avail = self.modes.available()
        labels = {MODES[k].label: k for k in avail}
        self.mode_key = self.s.mode
        with gui.add_folder("Render"):
            self.mode_dd = gui.add_dropdown("Mode", tuple(labels), initial_value=MODES[self.s.mode].label)
            self.sigma_in = gui.add_number("σ scale max", initial_value=float(self.s.sigma_max or 0.03), min=1e-5,
                                           max=10.0, step=1e-4, hint="upper end of the σ modes' colour scale (RGB "
                                           "units); a number typed here fixes it")
            self.sigma_in.disabled = self.s.mode not in self.auto  # greyed out outside the σ modes (rgb, depth, ...)
            auto = gui.add_button("σ scale: auto from this view", hint="99th percentile of the σ of the current view")
            self.samples_in = gui.add_slider("σ samples S", min=2, max=64, step=1, initial_value=int(self.s.samples))
            self.legend_img = gui.add_image(self._legend_image(self.modes.specs[self.s.mode]), label=None)
            self.legend_md = gui.add_markdown(self._legend_text(self.modes.specs[self.s.mode]))
            self.frame_md = gui.add_markdown("Frame: waiting for a browser")
            gone = self.modes.unavailable()
            if gone:
                gui.add_markdown("Not available for this run: " + "; ".join(
                    f"{MODES[k].label} ({why})" for k, why in gone.items()))
        with gui.add_folder("Cameras"):
            home = gui.add_button("Home view", hint="the orbit view framing the scene")
            self.cam_dd = gui.add_dropdown("Jump to", tuple(lbl for lbl, _, _ in self._cameras))
            go = gui.add_button("Go")
            self.show_cameras = gui.add_checkbox("Show cameras", initial_value=bool(self.s.frusta))
            n_acq = len(self.run.acquired)
            gui.add_markdown(f"Frusta: grey = train ({len(self.scene.train)}), **red = test** ({len(self.scene.test)})"
                             + (f", **blue = acquired** ({n_acq}, labelled in pick order)" if n_acq else "")
                             + (f", **green = suggested** ({len(self.run.suggested)}, b3dgs-suggest, labelled by rank)"
                                if getattr(self.run, "suggested", None) else "")
                             + ". Click a frustum to look through it; drag to orbit.")
        with gui.add_folder("Run"):
            gui.add_markdown(self._metrics_text())
            self._add_curve()

        @self.mode_dd.on_update
        def _(event) -> None:
            self.mode_key = labels[self.mode_dd.value]
            self._mode_changed()

        @self.sigma_in.on_update
        def _(event) -> None:
            v = float(self.sigma_in.value)
            key = self.mode_key if self.mode_key in self.auto else None
            if v > 0 and event.client is not None and key is not None:  # typed by a user (not set from here)
                self.auto[key] = False  # fixes the scale
                self.modes.set_scale(key, v)
                self._mode_changed()

        @auto.on_click
        def _(event) -> None:
            if self.mode_key in self.auto:
                self.auto[self.mode_key] = True
                self.ranged.discard(self.mode_key)
                self._mode_changed()

        def targets(event) -> list:
            return [event.client] if event.client is not None else [st.client for st in self.clients.values()]

        @home.on_click
        def _(event) -> None:
            for client in targets(event):
                self.go_home(client)

        @self.samples_in.on_update
        def _(event) -> None:
            self.modes.samples = int(self.samples_in.value)
            if self.mode_key.endswith("sigma"):
                self._touch_all()

        @self.show_cameras.on_update
        def _(event) -> None:
            self._show_frusta(bool(self.show_cameras.value))

        @go.on_click
        def _(event) -> None:
            hit = [cam for lbl, cam, _ in self._cameras if lbl == self.cam_dd.value]
            for client in targets(event) if hit else []:
                self.jump(client, hit[0])

    def _mode_changed(self) -> None:
        spec = self.modes.specs[self.mode_key]
        self.sigma_in.disabled = spec.key not in self.auto  # the σ scale applies to the σ modes only
        self.legend_img.image = self._legend_image(spec)
        self._show_scale(spec)
        self._touch_all()

    def _auto_range(self, frame: Frame) -> Frame:
        """A σ mode's first frame (or the first after "auto") sets its scale: the 99th percentile of its σ; the frame
        is coloured again on that scale."""
        key = frame.mode.key
        if not self.auto.get(key) or key in self.ranged or frame.values is None:
            return frame
        top = robust_max(frame.values, 99.0, frame.mask)
        self.ranged.add(key)
        if top is None:
            return frame
        self.modes.set_scale(key, top)
        spec = self.modes.specs[key]
        self._show_scale(spec)
        img = colorize(normalise(frame.values, spec), spec.cmap, frame.mask)
        return Frame(spec, img, frame.values, frame.mask, frame.seconds, frame.samples)

    def _show_scale(self, spec: ModeSpec) -> None:
        """The legend text of the mode shown, and its σ scale in the panel's number (not taken as a user's)."""
        if spec.key != self.mode_key:
            return
        self.legend_md.content = self._legend_text(spec)
        if spec.key in self.auto:
            self.sigma_in.value = float(spec.hi)

    def _metrics_text(self) -> str:
        m = self.run.metrics
        cfg = self.run.loaded.cfg

        def f(k, spec):
            v = m.get(k)
            return "n/a" if v is None else format(v, spec)

        rows = [("method", m.get("method")), ("scene", m.get("scene")), ("seed", m.get("seed")), ("steps", m.get("steps")),
                ("PSNR", f"{f('psnr', '.2f')} dB"), ("SSIM", f("ssim", ".4f")), ("LPIPS", f("lpips", ".4f")),
                ("Gaussians", f("num_gaussians", ",d")), ("train time", f"{f('train_time_s', '.1f')} s"),
                ("render FPS (eval)", f("render_fps", ".1f")),
                ("renderer", self.run.module.renderer.name), ("test / train views",
                                                               f"{m.get('num_test_views')} / {m.get('num_train_views')}")]
        body = "\n".join(f"| {k} | {v} |" for k, v in rows)
        data = cfg.data.get("path") or cfg.data.get("name")
        return f"**{self.run.path.name}**  \n{data}\n\n| | |\n|---|---|\n{body}"

    def _add_curve(self) -> None:
        pts = [p for p in self.run.curve if p.get("psnr") is not None and p.get("train_time_s") is not None]
        if len(pts) < 2:
            self.server.gui.add_markdown("No PSNR curve (curve.json has fewer than two points).")
            return
        x = np.array([float(p["train_time_s"]) for p in pts])
        y = np.array([float(p["psnr"]) for p in pts])
        try:
            import viser.uplot as uplot

            self.server.gui.add_uplot(
                (x, y), (uplot.Series(label="train time (s)"), uplot.Series(label="test PSNR (dB)", stroke="#e6553a", width=2)),
                title="Test PSNR against training time", aspect=1.4,
                scales={"x": uplot.Scale(time=False, auto=True), "y": uplot.Scale(auto=True)})
        except Exception as e:  # noqa: BLE001 - an older viser without uPlot: a static plot instead
            log.info("uPlot unavailable (%s); the curve is drawn as an image", e)
            self.server.gui.add_image(_curve_png(x, y))

    def _legend_image(self, spec: ModeSpec) -> np.ndarray:
        if spec.kind == "rgb":
            return np.full((12, 256, 3), 255, np.uint8)
        return np.repeat(colormap_lut(spec.cmap)[None], 12, axis=0)

    def _legend_text(self, spec: ModeSpec) -> str:
        if spec.kind == "rgb":
            return f"**{spec.label}**: {spec.what}."
        lo, hi = (f"{spec.lo:.3g}", f"{spec.hi:.3g}")
        mid = f" · middle {10 ** ((math.log10(spec.lo) + math.log10(spec.hi)) / 2):.3g}" if spec.log else ""
        extra = (" Pixel: compositing-weighted mean of the Gaussians' values (of log10 on a log scale); "
                 f"dark grey where α < {MIN_ALPHA}." if spec.kind == "gaussian" else "")
        if spec.key == "depth":
            extra = f" Dark grey where α < {MIN_ALPHA}."
        how = "fixed for the session"
        if spec.key in self.auto:
            how = ("auto: the 99th percentile of the first frame" if self.auto[spec.key] and spec.key in self.ranged
                   else "auto: set by the first frame" if self.auto[spec.key] else "set by hand")
        return (f"**{spec.label}**: left {lo} → right {hi}{mid} {spec.unit}; {'log' if spec.log else 'linear'} scale, "
                f"{how} ({spec.cmap}).  \n{spec.what}.{extra}")

    def _frustum_scale(self) -> float:
        """Frustum depth: a quarter of the median distance between neighbouring cameras (so that neighbours do
        not overlap), at most 0.05 × the scene extent."""
        centres = torch.stack([c.center.double().cpu() for _, c, _ in self._cameras])
        if len(centres) < 2:
            return 0.05 * float(self.scene.extent)
        d = torch.cdist(centres, centres)
        d.fill_diagonal_(float("inf"))
        return float(min(0.05 * float(self.scene.extent), d.min(1).values.median() / 4.0))

    def _add_frusta(self, st: "_ClientState") -> None:
        """The cameras' frusta in this browser's scene (per browser, so that the one it looks through is hidden)."""
        scene_api = st.client.scene
        scale = self._frustum_scale()
        thumbs = self.s.photos and len(self._cameras) <= self.s.thumbnails
        for i, (label, cam, kind) in enumerate(self._cameras):
            wxyz, pos = camera_pose(cam)
            colour = {"train": TRAIN_COLOUR, "test": TEST_COLOUR, "acquired": ACQUIRED_COLOUR,
                      "suggested": SUGGESTED_COLOUR}.get(kind, CANDIDATE_COLOUR)
            img = None
            if thumbs and cam.image is not None:
                step = max(1, max(cam.width, cam.height) // 48)
                img = (cam.image[::step, ::step].clamp(0, 1).cpu().numpy() * 255).astype(np.uint8)
            h = scene_api.add_camera_frustum(
                f"/cameras/{kind}_{i:04d}", fov=fov_y(cam), aspect=cam.width / cam.height, scale=scale,
                thickness=2.0 if kind in ("test", "acquired", "suggested") else 1.0, thickness_units="screen", color=colour,
                image=img, wxyz=wxyz, position=pos, visible=bool(self.show_cameras.value))
            if kind in ("acquired", "suggested"):
                scene_api.add_label(f"/cameras/{kind}_{i:04d}/pick", label.split(":")[0].replace(f"{kind} ", ""),
                                    position=(0.0, 0.0, 0.0))
            h.on_click(lambda event, cam=cam: self.jump(event.client, cam))
            st.frusta[cam.name] = h

    def _show_frusta(self, visible: bool) -> None:
        for st in list(self.clients.values()):
            for name, h in st.frusta.items():
                h.visible = visible and name != st.hidden

    # ------------------------------------------------------------------ clients
    def _on_connect(self, client) -> None:
        st = _ClientState(client)
        self._add_frusta(st)
        with self.lock:
            self.clients[client.client_id] = st

        @client.camera.on_update
        def _(_cam) -> None:
            st.version += 1
            st.last_move = time.time()
            self.wake.set()

        if self.s.start == "camera":
            self.jump(client, self._cameras[0][1])
        # else: the browser starts at viser's initial camera, the home view (set once in __init__)

    def _on_disconnect(self, client) -> None:
        with self.lock:
            self.clients.pop(client.client_id, None)

    def jump(self, client, cam) -> None:
        """Put ``client``'s camera at a b3dgs camera (its pose and vertical field of view); that camera's
        frustum is hidden in this browser until it jumps elsewhere."""
        st = self.clients.get(client.client_id)
        if st is not None:
            if st.hidden in st.frusta:
                st.frusta[st.hidden].visible = bool(self.show_cameras.value)
            if cam.name in st.frusta:
                st.frusta[cam.name].visible = False
            st.hidden = cam.name
        wxyz, pos = camera_pose(cam)
        R = cam.camtoworld[:3, :3].double().cpu().numpy()
        with client.atomic():
            client.camera.up_direction = tuple(-R[:, 1])
            client.camera.position = tuple(pos)
            client.camera.look_at = tuple(pos + R[:, 2] * max(float(self.scene.extent), 1e-3))
            client.camera.wxyz = tuple(wxyz)
            client.camera.fov = fov_y(cam)

    def go_home(self, client) -> None:
        """Put ``client``'s camera at the orbit view framing the scene (:func:`home_view`)."""
        st = self.clients.get(client.client_id)
        if st is not None and st.hidden in st.frusta:
            st.frusta[st.hidden].visible = bool(self.show_cameras.value)
            st.hidden = None
        with client.atomic():
            client.camera.up_direction = tuple(self.up)
            client.camera.position = tuple(self.home["position"])
            client.camera.look_at = tuple(self.home["look_at"])
            client.camera.fov = self.home["fov"]

    def _touch_all(self) -> None:
        now = time.time()
        for st in list(self.clients.values()):
            st.version += 1
            st.last_move = now
        self.wake.set()

    # ------------------------------------------------------------------ render loop
    def start(self) -> "ViewerApp":
        self.thread.start()
        return self

    def stop(self) -> None:
        self.stopping = True
        self.wake.set()
        if self.thread.is_alive():
            self.thread.join(timeout=30)
        self.server.stop()

    def full_side_of(self, client) -> int:
        """The long side of a full frame for ``client``: its canvas's, at most ``max_side``."""
        try:
            canvas = max(int(client.camera.image_width), int(client.camera.image_height))
        except (AssertionError, TypeError, ValueError):
            canvas = 0
        return max(self.s.min_side, min(self.cap, canvas or self.cap))

    def low_side(self, mode: str, aspect: float, full_side: int) -> int:
        """Long side of the quick pass: the most pixels the mode renders in ``target_ms``."""
        per_px = self.cost.get(mode)
        if per_px is None:
            return max(self.s.min_side, min(full_side, full_side // 4))
        w, h = render_size(aspect, full_side)
        pixels = (self.s.target_ms / 1000.0) / per_px
        side = int(full_side * math.sqrt(min(1.0, pixels / (w * h))))
        return max(self.s.min_side, min(full_side, side))

    def _loop(self) -> None:
        while not self.stopping:
            self.wake.wait(timeout=0.05)
            self.wake.clear()
            for st in list(self.clients.values()):
                if self.stopping:
                    break
                try:
                    self._serve(st)
                except Exception as e:  # noqa: BLE001 - a client that left mid-frame, or a bad camera
                    log.warning("frame for client %s failed: %s", st.client.client_id, e)

    def _serve(self, st: _ClientState) -> None:
        """One frame for a browser, if it needs one: a quick pass after every change (camera, mode, scale), then,
        once the camera is still, passes that double the long side up to the full size (the canvas's, capped)."""
        cam = st.client.camera
        try:
            aspect = cam.image_width / max(cam.image_height, 1)
            wxyz, pos, fov = np.array(cam.wxyz), np.array(cam.position), float(cam.fov)
        except AssertionError:  # no camera message from this browser yet
            return
        still = (time.time() - st.last_move) * 1000.0 >= self.s.still_ms
        mode, full_side = self.mode_key, self.full_side_of(st.client)
        if st.version != st.shown_version:
            side = self.low_side(mode, aspect, full_side)
        elif st.shown_side != full_side and still:
            side = full_side if st.shown_side > full_side else min(full_side, 2 * st.shown_side)
        else:
            if st.shown_side != full_side:
                self.wake.set()  # come back when the camera has been still long enough
                time.sleep(0.01)
            return
        version = st.version
        full = side >= full_side
        w, h = render_size(aspect, side)
        # σ modes also draw a quarter of the samples in the quick passes: their cost is mostly per Gaussian
        samples = None if full else max(2, self.modes.samples // 4)
        frame = self._auto_range(self.modes.render(mode, view_camera(wxyz, pos, fov, w, h), samples=samples))
        if frame.samples is None or full:  # the quick pass is sized from the cost per pixel at full S
            per_px = frame.seconds / (w * h)
            self.cost[mode] = per_px if mode not in self.cost else 0.5 * (self.cost[mode] + per_px)
        st.client.scene.set_background_image(frame.image, format="jpeg", jpeg_quality=self.s.jpeg_quality)
        st.shown_version, st.shown_side = version, side
        self._report(frame, w, h, full, still, full_side)
        self.wake.set()

    def _report(self, frame: Frame, w: int, h: int, full: bool, still: bool, full_side: int) -> None:
        s = f", S = {frame.samples}" if frame.samples else ""
        state = ("full resolution (camera still)" if full else
                 "refining (camera still)" if still else "low resolution (camera moving)")
        self.frame_md.content = (f"Frame: **{frame.seconds * 1000.0:.0f} ms** ({frame.mode.label}{s}) at {w}×{h} px, "
                                 f"{state}; full = {full_side} px long side (the window's, at most {self.cap})")


def home_view(scene, up) -> dict:
    """The orbit view that frames the scene: looking at the point the cameras look at
    (:func:`b3dgs.data.scene.look_at_point`) from their median distance to it, from the side they look from (their
    mean direction from it); for cameras all around the subject, from the first camera's azimuth at their mean
    elevation (at least 15°). The vertical field of view is the cameras' median. Returns position, look_at, fov."""
    from b3dgs.data.scene import look_at_point

    cams = list(scene.train) + list(scene.test)
    target, _ = look_at_point(np.stack([c.viewmat.double().cpu().numpy() for c in cams]))
    rel = np.stack([c.center.double().cpu().numpy() for c in cams]) - target
    dist = np.linalg.norm(rel, axis=1)
    unit = rel / np.maximum(dist, 1e-12)[:, None]
    mean = unit.mean(axis=0)
    up = np.asarray(up, np.float64)
    if np.linalg.norm(mean) >= 0.7:  # a forward-facing (or turntable) capture: from where the cameras are
        direction = mean / np.linalg.norm(mean)
    else:
        elev = float(np.clip((unit @ up).mean(), math.sin(math.radians(15)), 0.8))
        flat = unit[0] - (unit[0] @ up) * up
        flat = flat / max(np.linalg.norm(flat), 1e-12)
        direction = math.sqrt(1 - elev * elev) * flat + elev * up
    radius = float(np.median(dist)) if np.median(dist) > 1e-9 else 1.0
    fov = float(np.median([fov_y(c) for c in cams]))
    return {"position": target + radius * direction, "look_at": target, "fov": fov}


def _curve_png(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(3.2, 2.2), dpi=100)
    ax.plot(x, y, "-o", ms=3, color="#e6553a")
    ax.set_xlabel("training time (s)")
    ax.set_ylabel("test PSNR (dB)")
    fig.tight_layout()
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return img
