"""A headless Chromium driven through the DevTools protocol, with nothing but the ``chromium`` binary and the
``websockets`` package (installed with viser): for the viewer's browser test and its screenshots.

``Browser(url)`` starts Chromium on ``url`` (WebGL through SwiftShader, software rendering) and attaches to the
page; ``evaluate(js)`` runs JavaScript in it, ``screenshot()`` returns a PNG and ``click(x, y)`` sends real mouse
events (what a user's click produces). ``close()`` ends the browser.
"""
from __future__ import annotations

import base64
import itertools
import json
import re
import shutil
import subprocess
import tempfile
import time
import urllib.request
from typing import Any, Optional

__all__ = ["Browser", "chromium_path"]


def chromium_path() -> Optional[str]:
    return next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None)


class Browser:
    def __init__(self, url: str, width: int = 1280, height: int = 800, timeout: float = 60.0) -> None:
        from websockets.sync.client import connect

        exe = chromium_path()
        if exe is None:
            raise RuntimeError("chromium is not installed (apt-get install -y chromium)")
        self.profile = tempfile.mkdtemp(prefix="b3dgs-chromium-")
        flags = [exe, "--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--no-first-run",
                 "--no-default-browser-check", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                 "--ignore-gpu-blocklist", "--remote-debugging-port=0", "--remote-allow-origins=*",
                 f"--user-data-dir={self.profile}", f"--window-size={width},{height}", url]
        self.proc = subprocess.Popen(flags, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        port = None
        t0 = time.time()
        lines = []
        while time.time() - t0 < timeout:
            line = self.proc.stderr.readline()
            if not line:
                if self.proc.poll() is not None:
                    break
                continue
            lines.append(line)
            m = re.search(r"DevTools listening on ws://[^:]+:(\d+)/", line)
            if m:
                port = int(m.group(1))
                break
        if port is None:
            self.close()
            raise RuntimeError("chromium did not start its DevTools endpoint: " + "".join(lines)[-800:])
        page = None
        while time.time() - t0 < timeout and page is None:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5) as r:
                page = next((t for t in json.loads(r.read()) if t.get("type") == "page"), None)
            if page is None:
                time.sleep(0.2)
        if page is None:
            self.close()
            raise RuntimeError("chromium opened no page")
        self.ws = connect(page["webSocketDebuggerUrl"], max_size=64 * 2**20, open_timeout=timeout)
        self.ids = itertools.count(1)
        # drain what chromium logs on stderr so the pipe never fills
        import threading

        threading.Thread(target=lambda: [None for _ in iter(self.proc.stderr.readline, "")], daemon=True).start()

    def call(self, method: str, timeout: float = 60.0, **params) -> dict:
        i = next(self.ids)
        self.ws.send(json.dumps({"id": i, "method": method, "params": params}))
        t0 = time.time()
        while True:
            left = timeout - (time.time() - t0)
            if left <= 0:
                raise TimeoutError(f"DevTools {method} did not answer in {timeout} s")
            msg = json.loads(self.ws.recv(timeout=left))
            if msg.get("id") == i:
                if "error" in msg:
                    raise RuntimeError(f"DevTools {method}: {msg['error']}")
                return msg.get("result", {})

    def evaluate(self, expression: str) -> Any:
        res = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in res:
            raise RuntimeError(f"JavaScript error: {res['exceptionDetails'].get('text')} in {expression[:200]}")
        return res.get("result", {}).get("value")

    def wait_for(self, expression: str, timeout: float = 60.0, poll: float = 0.25) -> Any:
        """Poll ``expression`` until it is truthy; returns its value (TimeoutError after ``timeout``)."""
        t0 = time.time()
        while time.time() - t0 < timeout:
            v = self.evaluate(expression)
            if v:
                return v
            time.sleep(poll)
        raise TimeoutError(f"timed out after {timeout} s waiting for {expression[:200]}")

    def click(self, x: float, y: float) -> None:
        """A real left click (move, press, release) at page coordinates."""
        self.call("Input.dispatchMouseEvent", type="mouseMoved", x=x, y=y)
        for kind in ("mousePressed", "mouseReleased"):
            self.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left", clickCount=1)

    def choose(self, current: str, option: str, timeout: float = 30.0) -> None:
        """Pick ``option`` in the panel's drop-down menu that shows ``current`` now: a real click on the menu,
        then on the option, where they are drawn (as a user does)."""
        at = ("const r = e.getBoundingClientRect(); return [r.x + r.width / 2, r.y + r.height / 2];")
        menu = self.evaluate("(() => { const e = [...document.querySelectorAll('input[aria-haspopup=listbox]')]"
                             f".find(e => e.value === {json.dumps(current)}); if (!e) return null; {at} }})()")
        if menu is None:
            raise RuntimeError(f"no drop-down menu shows {current!r}")
        self.click(*menu)
        self.click(*self.wait_for("(() => { const e = [...document.querySelectorAll('[role=option]')]"
                                  f".find(e => e.innerText.trim() === {json.dumps(option)}); if (!e) return null; {at} }})()",
                                  timeout))

    def frame_text(self) -> Optional[str]:
        """The viewer panel's "Frame: ..." line (frame time, size, low or full pass), None before the first frame."""
        return self.evaluate("(() => { const p = [...document.querySelectorAll('p')]"
                             ".find(e => e.innerText.startsWith('Frame:')); return p ? p.innerText : null; })()")

    def wait_frame(self, *parts: str, timeout: float = 120.0) -> str:
        """Wait until the "Frame:" line holds every string of ``parts``; returns it."""
        t0 = time.time()
        while time.time() - t0 < timeout:
            text = self.frame_text()
            if text and all(p in text for p in parts):
                return text
            time.sleep(0.2)
        raise TimeoutError(f"no frame with {parts} in {timeout} s (last: {self.frame_text()!r})")

    def screenshot(self) -> bytes:
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])

    def close(self) -> None:
        try:
            if getattr(self, "ws", None) is not None:
                self.ws.close()
        except Exception:  # noqa: BLE001
            pass
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> "Browser":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
