"""A page in headless Chromium (Debian's ``chromium``): screenshots of the viewer for its
tests, for the README's screenshot and for ``agilegs view --screenshot``.

Chromium runs with a fresh profile in a temporary folder, no sandbox, no GPU (WebGL then
runs on SwiftShader, in software), no network beyond the page, and is driven over the
DevTools protocol (a websocket; ``websockets`` comes with viser).

Splats in software WebGL: viser's Gaussian splats draw in this browser, but only once
viser's sort worker has compiled its WebAssembly sorter and sent the first depth order,
then fade in over half a second: about 2 s after the page connects on a small map,
more on a large one. A screenshot taken at page load (``chromium --screenshot`` without a
virtual-time budget) shows the frustums and not yet the splats. :func:`capture` therefore
waits until the canvas holds something and stops changing.
"""

from __future__ import annotations

import base64
import io
import json
import logging
import shutil
import subprocess
import tempfile
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["CHROMIUM_FLAGS", "Browser", "canvas_fraction", "capture", "find_chromium", "pixels",
           "write_png"]

log = logging.getLogger(__name__)

CHROMIUM_FLAGS = (
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--hide-scrollbars", "--mute-audio",
    # WebGL on SwiftShader: chromium still falls back to it without this flag, with a
    # deprecation warning; the flag keeps it working once the fallback is gone (the
    # page is our own, on loopback)
    "--enable-unsafe-swiftshader",
)

_HIDE_OVERLAYS = """(() => {
  const canvas = document.querySelector('canvas');
  if (!canvas) return -1;
  let n = 0;
  for (const e of document.querySelectorAll('body *')) {
    if (e === canvas || e.contains(canvas) || canvas.contains(e)) continue;
    const p = getComputedStyle(e).position;
    if (p === 'fixed' || p === 'absolute') {
      e.dataset.agilegsHidden = '1'; e.style.visibility = 'hidden'; n++;
    }
  }
  return n;
})()"""

_SHOW_OVERLAYS = """(() => {
  const els = document.querySelectorAll('[data-agilegs-hidden]');
  els.forEach(e => { e.style.visibility = ''; delete e.dataset.agilegsHidden; });
  return els.length;
})()"""

_HIDE_NOTIFICATIONS = """(() => {
  const els = document.querySelectorAll('.mantine-Notifications-root');
  els.forEach(e => { e.style.visibility = 'hidden'; });
  return els.length;
})()"""


def find_chromium() -> str | None:
    """The path of a Chromium (or Chrome) executable, or None."""
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        path = shutil.which(name)
        if path:
            return path
    return None


class Browser:
    """Headless Chromium driven over the DevTools protocol (a context manager).

    Args:
        width, height: the page's viewport in CSS pixels.
        executable: the browser (default :func:`find_chromium`).
    """

    def __init__(self, width: int = 1280, height: int = 800, executable: str | None = None
                 ) -> None:
        exe = executable or find_chromium()
        if exe is None:
            raise RuntimeError("no chromium found: apt-get install -y chromium")
        self._profile = tempfile.mkdtemp(prefix="agilegs-chromium-")
        self.proc = subprocess.Popen(
            [exe, *CHROMIUM_FLAGS, f"--user-data-dir={self._profile}",
             f"--window-size={width},{height}", "--remote-debugging-port=0", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.console: list[str] = []
        self._id = 0
        try:
            self._ws = self._connect(30.0)
            self.call("Runtime.enable")
            self.call("Page.enable")
            self.call("Emulation.setDeviceMetricsOverride", width=width, height=height,
                      deviceScaleFactor=1, mobile=False)
        except Exception:
            self.close()
            raise

    def _connect(self, timeout: float) -> Any:
        from websockets.sync.client import connect

        port_file = Path(self._profile) / "DevToolsActivePort"
        deadline = time.monotonic() + timeout
        while not (port_file.exists() and port_file.read_text().strip()):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("chromium did not start its DevTools endpoint")
            time.sleep(0.05)
        port = int(port_file.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
            targets = json.load(r)
        page = next(t for t in targets if t.get("type") == "page")
        return connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=10)

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        """One DevTools command; its result (console messages met meanwhile are kept)."""
        self._id += 1
        self._ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            msg = json.loads(self._ws.recv(timeout=60))
            if msg.get("id") == self._id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return dict(msg.get("result", {}))
            if msg.get("method") == "Runtime.consoleAPICalled":
                args = msg["params"].get("args", [])
                self.console.append(" ".join(str(a.get("value", a.get("description", "")))
                                             for a in args))
            elif msg.get("method") == "Runtime.exceptionThrown":
                d = msg["params"]["exceptionDetails"]
                self.console.append("exception: " + str(d.get("exception", {}).get(
                    "description", d.get("text"))))

    def open(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def evaluate(self, expression: str) -> Any:
        out = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        return out.get("result", {}).get("value")

    def screenshot(self, *, canvas_only: bool = False) -> bytes:
        """A PNG of the page; ``canvas_only``: the 3D canvas alone (the panel and every
        other overlay hidden for the shot), else the page without its notifications."""
        if not canvas_only:
            self.evaluate(_HIDE_NOTIFICATIONS)
            return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        self.evaluate(_HIDE_OVERLAYS)
        try:
            return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        finally:
            self.evaluate(_SHOW_OVERLAYS)

    def close(self) -> None:
        ws = getattr(self, "_ws", None)
        if ws is not None:
            try:
                ws.close()
            except Exception:
                log.debug("browser: closing the websocket failed", exc_info=True)
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        shutil.rmtree(self._profile, ignore_errors=True)

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def pixels(png: bytes) -> np.ndarray:
    """RGB uint8 [H, W, 3] of a PNG."""
    from PIL import Image

    with Image.open(io.BytesIO(png)) as img:
        return np.asarray(img.convert("RGB"))


def write_png(path: Path | str, png: bytes) -> Path:
    """Write a screenshot small: 256 colours, optimised (a few times smaller than the
    browser's PNG); the folder is created."""
    from PIL import Image

    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    with Image.open(io.BytesIO(png)) as img:
        img.convert("RGB").quantize(256, method=Image.Quantize.MEDIANCUT).save(out, optimize=True)
    return out


def canvas_fraction(png: bytes, tolerance: int = 24) -> float:
    """The fraction of pixels that differ from the background (the most common colour) by
    more than ``tolerance`` in some channel: 0 for an empty canvas."""
    rgb = pixels(png).reshape(-1, 3).astype(np.int16)
    colours, counts = np.unique(rgb, axis=0, return_counts=True)
    bg = colours[int(np.argmax(counts))]
    return float((np.abs(rgb - bg).max(axis=1) > tolerance).mean())


def capture(url: str, *, width: int = 1280, height: int = 800, canvas_only: bool = False,
            timeout: float = 90.0, settle: float = 1.5,
            ready: Callable[[bytes], bool] | None = None) -> bytes:
    """A screenshot of ``url`` once its canvas is drawn: the canvas holds something
    (``ready(canvas png)`` when given) and has not changed for ``settle`` s; RuntimeError
    (with the page's console) after ``timeout`` s."""
    ready = ready or (lambda png: canvas_fraction(png) > 0.002)
    with Browser(width, height) as browser:
        browser.open(url)
        deadline = time.monotonic() + timeout
        last: bytes | None = None
        since = time.monotonic()
        while time.monotonic() < deadline:
            time.sleep(0.5)
            shot = browser.screenshot(canvas_only=True)
            if shot != last:
                last, since = shot, time.monotonic()
                continue
            if ready(shot) and time.monotonic() - since >= settle:
                return shot if canvas_only else browser.screenshot()
        tail = "\n".join(browser.console[-20:])
        raise RuntimeError(f"the page at {url} drew nothing within {timeout:.0f} s; its "
                           f"console:\n{tail}")
