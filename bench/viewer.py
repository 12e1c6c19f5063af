"""b3dgs-view frame times per render mode, and the user guide's screenshot (RGB beside native σ in a real browser).

    python -m bench.viewer --runs RUN [RUN ...] [--threads 2] [--screenshot docs/viewer_ethiopian_head.png]

For every run and every mode it offers: the median render + colour-map time of the first test view's pose at
the viewer's full resolution (the training image's long side) and at the moving-camera pass's size for the
default 100 ms target (σ modes with S/4 draws there, as the viewer does), measured in this process (what the viewer's render thread does per frame; the JPEG
encoding and the websocket add a few ms). With --screenshot, the first run is served on 127.0.0.1, opened in
headless Chromium (software WebGL), switched from RGB to native σ through the panel's menu with mouse
clicks, and the two screenshots are written side by side (cameras hidden; the RGB one without the panel). Writes bench/results/viewer.{json,md}.
"""
from __future__ import annotations

import argparse
import io
import math
import time
from pathlib import Path

import torch

from bench.common import load_file, machine, median_ms, table, write_results

from b3dgs.viewer.cameras import camera_pose, fov_y, render_size, view_camera  # noqa: E402
from b3dgs.viewer.modes import ModeRenderer  # noqa: E402
from b3dgs.viewer.run import open_run  # noqa: E402

PANEL_PX = 345  # viser's side panel (320 px) and its margin, at the right of the window


def frame_times(run_dir: str, samples: int, target_ms: float, repeats: int) -> list[dict]:
    run = open_run(run_dir)
    mr = ModeRenderer(run.module, run.scene, samples=samples)
    cam = run.scene.test[0]
    wxyz, pos = camera_pose(cam)
    aspect = cam.width / cam.height
    full = max(cam.width, cam.height)
    rows = []
    for mode in mr.available():
        w, h = render_size(aspect, full)
        view = view_camera(wxyz, pos, fov_y(cam), w, h)
        ms = median_ms(lambda: mr.render(mode, view), repeats=repeats, warmup=1)
        low = max(32, min(full, int(full * math.sqrt(min(1.0, target_ms / ms)))))
        lw, lh = render_size(aspect, low)
        low_view = view_camera(wxyz, pos, fov_y(cam), lw, lh)
        low_s = max(2, samples // 4) if mode.endswith("sigma") else None  # the viewer's moving pass draws S/4
        low_ms = median_ms(lambda: mr.render(mode, low_view, samples=low_s), repeats=repeats, warmup=1)
        rows.append({"run": Path(run_dir).name, "model": run.metrics.get("method"), "gaussians": run.module.num_gaussians,
                     "mode": mode, "full": f"{w}x{h}", "full_ms": ms, "low": f"{lw}x{lh}", "low_ms": low_ms,
                     "samples": samples if mode.endswith("sigma") else None})
        print(rows[-1], flush=True)
    return rows


def screenshot_pair(run_dir: str, out: Path, width: int, height: int) -> dict:
    from PIL import Image

    from b3dgs.viewer.server import ViewerApp, ViewerSettings

    Browser = load_file(Path(__file__).resolve().parents[1] / "tests" / "browser.py").Browser  # the tests' client

    app = ViewerApp(open_run(run_dir), ViewerSettings(port=0, frusta=False)).start()
    shots, texts = [], []
    try:
        with Browser(app.url() + "/", width=width, height=height) as b:
            b.wait_for("document.querySelector('canvas') !== null", 120)
            for current, option in ((None, "RGB"), ("RGB", "Native σ")):
                if current is not None:
                    b.choose(current, option)
                texts.append(b.wait_frame(f"({option}", "full resolution", timeout=300))
                time.sleep(2.0)  # the page's fade-in
                # the "software WebGL" notice covers the view in a headless browser: hidden for the picture
                b.evaluate("document.querySelectorAll('.mantine-Notification-root').forEach(e => e.remove())")
                time.sleep(0.3)
                shots.append(Image.open(io.BytesIO(b.screenshot())).convert("RGB"))
    finally:
        app.stop()
    w, h = shots[0].size
    left = shots[0].crop((0, 0, w - PANEL_PX, h))  # the RGB view without the panel; the σ one with its legend
    pair = Image.new("RGB", (left.width + 8 + w, h), (255, 255, 255))
    pair.paste(left, (0, 0))
    pair.paste(shots[1], (left.width + 8, 0))
    pair = pair.resize((pair.width * 3 // 4, pair.height * 3 // 4), Image.LANCZOS).quantize(colors=192)
    out.parent.mkdir(parents=True, exist_ok=True)
    pair.save(out, optimize=True)
    return {"screenshot": str(out), "frames": texts, "bytes": out.stat().st_size}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", nargs="+", required=True)
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--target-ms", type=float, default=100.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--screenshot", type=Path, default=None)
    ap.add_argument("--window", type=int, nargs=2, default=(1000, 760))
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    rows = [r for run in args.runs for r in frame_times(run, args.samples, args.target_ms, args.repeats)]
    payload = {"machine": machine(), "samples": args.samples, "target_ms": args.target_ms, "rows": rows}
    text = ("# b3dgs-view frame times (render + colour map, median of "
            f"{args.repeats}; {torch.get_num_threads()} threads; σ modes with S = {args.samples})\n\n"
            + table(rows, ["run", "model", "gaussians", "mode", "full", "full_ms", "low", "low_ms"]))
    if args.screenshot:
        payload["screenshot"] = screenshot_pair(args.runs[0], args.screenshot, *args.window)
        text += "\n\nScreenshot " + payload["screenshot"]["screenshot"] + ": " + " | ".join(payload["screenshot"]["frames"])
    write_results("viewer", payload, text)


if __name__ == "__main__":
    main()
