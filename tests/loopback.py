"""What a fresh clone fetches, served here instead: this machine has no internet, so ``b3dgs-data get`` downloads from
a loopback ``http.server`` (127.0.0.1 only, in a thread), and the shipped registry is pointed at it through
``$B3DGS_DATA_REGISTRY`` with only each source's host replaced (same paths, files, layout steps and required files).
:func:`synthetic_fox` is a fox that trains: the registry's 67 frames rendered from b3dgs.data.synthetic's world on a
forward-facing arc, at 4x the size (the entry's layout step downscales them by 4), with the ``transforms.json`` of
their true poses."""
from __future__ import annotations

import http.server
import io
import json
import math
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
import yaml


class Handler(http.server.BaseHTTPRequestHandler):
    """GET of ``server.files[path]`` (Range honoured; a path in ``server.cut`` is cut half-way once); every request
    is logged as (path, Range) in ``server.log``."""

    def do_GET(self):  # noqa: N802 - http.server's name
        srv = self.server
        body = srv.files.get(self.path)
        rng = self.headers.get("Range")
        srv.log.append((self.path, rng))
        if body is None:
            self.send_error(404)
            return
        start = int(rng.split("=")[1].split("-")[0]) if rng else 0
        self.send_response(206 if rng else 200)
        if rng:
            self.send_header("Content-Range", f"bytes {start}-{len(body) - 1}/{len(body)}")
        self.send_header("Content-Length", str(len(body) - start))
        self.end_headers()
        payload = body[start:]
        if self.path in srv.cut:  # the first response stops half-way and the connection closes
            srv.cut.discard(self.path)
            payload = payload[:len(payload) // 2]
        self.wfile.write(payload)

    def log_message(self, *args):
        pass


@contextmanager
def serve() -> Iterator[http.server.ThreadingHTTPServer]:
    """A loopback server on a free port; ``.url`` is its base URL, ``.files`` what it serves (path -> bytes)."""
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    srv.files, srv.cut, srv.log = {}, set(), []
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    srv.url = f"http://127.0.0.1:{srv.server_address[1]}"
    try:
        yield srv
    finally:
        srv.shutdown()
        srv.server_close()


def registry_on(srv, out: Path, body: Callable[[str], bytes], name: str = "fox") -> Path:
    """The shipped registry (b3dgs/datasets.yaml) written to ``out`` with ``name``'s source hosts replaced by ``srv``,
    which serves ``body(file)`` for every file the entry names, at the path the registry gives it."""
    from b3dgs import datasets

    reg = yaml.safe_load(datasets.REGISTRY_FILE.read_text())
    for src in reg[name]["sources"]:
        assert src.get("files"), f"{name}: only sources of files are served here"
        path = src["url"].split("://", 1)[1].partition("/")[2]
        src["url"] = f"{srv.url}/{path}"
        for entry in src["files"]:
            file = entry.split("->")[0].strip()
            srv.files[f"/{path}{file}"] = body(file)
    out.write_text(yaml.safe_dump(reg))
    return out


def frame_names(name: str = "fox") -> list[str]:
    """The image files (``images/NNNN.jpg``) the shipped registry's entry fetches."""
    from b3dgs import datasets

    return [f for s in datasets.load_registry(datasets.REGISTRY_FILE)[name].sources for f in s.files
            if f.lower().endswith((".jpg", ".png"))]


def synthetic_fox(width: int = 144, height: int = 256, arc_deg: float = 120.0) -> dict[str, bytes]:
    """fox's files, as the registry names them (``data/nerf/fox/transforms.json``, ``LICENSE.txt``,
    ``images/NNNN.jpg``): b3dgs.data.synthetic's world (seed 0) seen from 67 cameras on a ``arc_deg`` arc at 25°
    elevation, portrait ``width`` x ``height`` JPEGs (fox's aspect), and the transforms.json of those cameras (NeRF
    camera-to-world, intrinsics at this size). Takes about 2 s."""
    from PIL import Image

    from b3dgs.data.synthetic import look_at, make_world

    world, names = make_world(0), frame_names()
    f = 0.5 * width / math.tan(math.radians(40) / 2)
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    files, frames = {}, []
    for i, name in enumerate(names):
        az, el = math.radians(arc_deg * (i / (len(names) - 1) - 0.5)), math.radians(25)
        V = look_at(3.5 * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]),
                    np.array([0.0, 0.0, 0.35]))
        img, _ = world.render(K, V, width, height, depth=False)
        buf = io.BytesIO()
        Image.fromarray((np.clip(img, 0, 1) * 255).round().astype(np.uint8)).save(buf, format="JPEG", quality=95)
        files[name] = buf.getvalue()
        c2w = np.linalg.inv(V)
        c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL/NeRF camera axes
        frames.append({"file_path": name, "transform_matrix": c2w.tolist()})
    files["data/nerf/fox/transforms.json"] = json.dumps(
        {"fl_x": f, "fl_y": f, "cx": width / 2, "cy": height / 2, "w": width, "h": height, "frames": frames}).encode()
    files["LICENSE.txt"] = b"A test fixture rendered by tests/loopback.py, standing in for instant-ngp's fox.\n"
    return files
