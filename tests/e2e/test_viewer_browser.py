"""The viewer in a real headless browser (Debian's chromium), over Zenoh, against a server
that stops and comes back; the decisions feed streamed by a real server and cut short by its
shutdown; the viewer's imports."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from conftest import SMALL_INTRINSICS, InProcess, ServerProcess, ring_poses
from conftest import gaussian_blob as blob

from agilegs.client import Client, ZenohClient
from agilegs.lab.scenes import bundled_scene
from agilegs.service.cli import main
from agilegs.service.launch import free_port
from agilegs.service.viewer.browser import Browser, canvas_fraction, find_chromium, pixels
from agilegs.service.viewer.live import SessionViewer

needs_chromium = pytest.mark.skipif(find_chromium() is None,
                                    reason="no chromium: the browser tests need Debian's chromium "
                                           "(apt-get install chromium; .ci/run installs it)")


def green(rgb: np.ndarray) -> np.ndarray:
    r, g, b = (rgb[..., i].astype(int) for i in range(3))
    return (g > 140) & (r < 120) & (b < 140)


def red(rgb: np.ndarray) -> np.ndarray:
    r, g, b = (rgb[..., i].astype(int) for i in range(3))
    return (r > 170) & (g < 110) & (b < 110)


def settled_canvas(browser: Browser, check: Callable[[np.ndarray], bool],
                   timeout: float = 90.0) -> np.ndarray:
    """The canvas (overlays hidden) once it has not changed for 1 s and passes ``check``."""
    deadline = time.monotonic() + timeout
    last: bytes | None = None
    since = time.monotonic()
    while time.monotonic() < deadline:
        time.sleep(0.4)
        png = browser.screenshot(canvas_only=True)
        if png != last:
            last, since = png, time.monotonic()
            continue
        if time.monotonic() - since >= 1.0 and check(pixels(png)):
            return pixels(png)
    got = pixels(last) if last else None
    raise AssertionError(f"the canvas never passed the check (green {green(got).mean() if got is not None else None}, "
                         f"red {red(got).sum() if got is not None else None}); console: "
                         f"{browser.console[-10:]}")


def new_id() -> str:
    return f"v-{uuid.uuid4().hex[:8]}"


# ============================================================================ the browser
@needs_chromium
def test_the_page_draws_the_map_as_splats_and_as_points(api: InProcess) -> None:
    with api.client() as c:
        c.create_session(SMALL_INTRINSICS, id="s", gaussians=blob(400, radius=0.6),
                         pool=ring_poses(10), defaults={"method": "agile", "shortlist_size": 3})
        with SessionViewer(api.client(), "s", port=free_port()) as v, Browser(1000, 700) as b:
            assert v.step()
            v.controls["pool"].value = False  # the map alone on the canvas
            b.open(v.url)
            # the splats draw in software WebGL (once viser's sorter has run)
            rgb = settled_canvas(b, lambda x: green(x).mean() > 0.01)
            assert canvas_fraction(b.screenshot(canvas_only=True)) > 0.01
            splat_area = green(rgb).mean()
            v.controls["map"].value = "points"
            rgb = settled_canvas(b, lambda x: 0.0005 < green(x).mean() < splat_area)
            v.controls["map"].value = "hidden"
            rgb = settled_canvas(b, lambda x: green(x).sum() == 0)
            assert canvas_fraction(b.screenshot(canvas_only=True)) == 0.0  # an empty canvas
            # the decision: the chosen view in red among the candidates
            v.controls["map"].value = "splats"
            v.controls["pool"].value = True
            c.select("s", commit=True)
            assert v.step(wait=2)
            settled_canvas(b, lambda x: red(x).sum() > 20 and green(x).mean() > 0.01)
            assert not [m for m in b.console if m.startswith("exception")], b.console


@needs_chromium
@pytest.mark.heavy
def test_the_demo_view_writes_its_screenshot(tmp_path: Path) -> None:
    # the README's screenshot comes from this command (without --quick)
    png = tmp_path / "view.png"
    out = subprocess.run(
        [sys.executable, "-m", "agilegs.service.cli", "demo", "--quick", "--view",
         "--view-port", str(free_port()), "--hold", "0", "--screenshot", str(png),
         "--out", str(tmp_path / "demo")], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    assert f"screenshot: {png}" in out.stdout
    rgb = pixels(png.read_bytes())
    assert rgb.shape == (800, 1280, 3)
    scene = rgb[80:720, 80:820].astype(int)  # left of the panel
    assert (np.abs(scene - 255).max(axis=-1) > 24).mean() > 0.01


@needs_chromium
@pytest.mark.heavy
def test_the_replay_command_writes_a_screenshot(tmp_path: Path) -> None:
    out = tmp_path / "bench"
    assert main(["bench", "run", "--scene", str(bundled_scene("spot")), "--methods",
                 "agile_plus", "--profile", "tiny", "--seeds", "0", "--out", str(out),
                 "--no-plots"]) == 0
    png = tmp_path / "replay.png"
    got = subprocess.run(
        [sys.executable, "-m", "agilegs.service.cli", "view", "--run", str(out),
         "--port", str(free_port()), "--screenshot", str(png)],
        capture_output=True, text=True, timeout=300)
    assert got.returncode == 0, got.stdout + got.stderr
    assert canvas_fraction(png.read_bytes()) > 0.02
    assert "websockets" not in got.stderr  # viser's connection chatter stays quiet


@needs_chromium
@pytest.mark.heavy
def test_the_view_command_follows_a_session_over_http_and_zenoh(server: ServerProcess,
                                                                tmp_path: Path) -> None:
    sid = new_id()
    with Client(server.url) as c:
        c.create_session(SMALL_INTRINSICS, id=sid, gaussians=blob(200, radius=0.6),
                         pool=ring_poses(8), defaults={"method": "agile", "shortlist_size": 3})
        c.select(sid, commit=True)
    for how in ([server.url], ["--zenoh", server.zenoh_endpoint]):
        png = tmp_path / f"{how[0].split(':')[0].strip('-')}.png"
        got = subprocess.run(
            [sys.executable, "-m", "agilegs.service.cli", "view", *how, "--session", sid,
             "--port", str(free_port()), "--screenshot", str(png)],
            capture_output=True, text=True, timeout=300)
        assert got.returncode == 0, got.stdout + got.stderr
        rgb = pixels(png.read_bytes())
        assert green(rgb).mean() > 0.005 and red(rgb).sum() > 20, how  # the map, the chosen view
    got = subprocess.run(
        [sys.executable, "-m", "agilegs.service.cli", "view", server.url, "--session",
         "no-such-session", "--port", str(free_port()), "--screenshot", str(tmp_path / "x.png"),
         "--timeout", "3"],
        capture_output=True, text=True, timeout=300)
    assert got.returncode == 1 and "no session `no-such-session`" in got.stderr


# ============================================================================ over Zenoh
def test_the_viewer_follows_the_decisions_published_over_zenoh(server: ServerProcess) -> None:
    sid = new_id()
    with Client(server.url) as c, ZenohClient([server.zenoh_endpoint], timeout=30) as zc:
        c.create_session(SMALL_INTRINSICS, id=sid, gaussians=blob(60), pool=ring_poses(8),
                         defaults={"method": "agile", "shortlist_size": 3})
        with SessionViewer(zc, sid, port=free_port(), decisions="zenoh") as v:
            assert v.step()
            d = c.select(sid, commit=True)
            deadline = time.monotonic() + 20
            while not v.decisions and time.monotonic() < deadline:
                v.step(wait=1)
            assert [x.chosen.id for x in v.decisions] == [d.chosen.id]
            np.testing.assert_allclose(v.canvas.chosen.position, d.chosen.pose.to_matrix()[:3, 3],
                                       atol=1e-6)
            assert len(v.canvas.views) == 1 and d.chosen.id not in v.canvas.pool
        # the feed as a Zenoh query: the server waits for the next decision
        later = threading.Timer(0.5, lambda: c.select(sid, seed=3))
        later.start()
        t0 = time.monotonic()
        out = zc.get_decisions(sid, after=1, wait=20)
        later.join(30)
        assert [e.seq for e in out.decisions] == [2] and time.monotonic() - t0 < 15


# ============================================================================ a server that stops
@pytest.mark.heavy
def test_the_viewer_survives_the_server_stopping_and_coming_back(server_factory: Any) -> None:
    srv = server_factory(zenoh=False).start()
    with Client(srv.url, timeout=10) as c, Client(srv.url, timeout=10) as vc, \
            SessionViewer(vc, "s", port=free_port(), where=srv.url) as v:
        c.create_session(SMALL_INTRINSICS, id="s", gaussians=blob(50), pool=ring_poses(6))
        first = c.select("s", method="random", commit=True)
        assert v.step() and len(v.decisions) == 1
        srv.stop()
        assert not v.step(wait=0.5)
        assert "does not answer" in v.status_md.content and srv.url in v.status_md.content
        srv.start()  # the same state folder and port: the session is back, its feed anew
        d = c.select("s", method="random", seed=4)
        assert v.step()
        assert v.problem is None and [x.chosen.id for x in v.decisions] == [d.chosen.id]
        assert len(v.canvas.views) == 1 and first.chosen.id not in v.canvas.pool


def test_the_event_stream_is_live_and_ends_when_the_server_stops(server_factory: Any) -> None:
    srv = server_factory(zenoh=False).start()
    with Client(srv.url) as c, httpx.Client(base_url=srv.url, timeout=60) as h:
        c.create_session(SMALL_INTRINSICS, id="s", gaussians=blob(50), pool=ring_poses(6))
        polled: list[Any] = []
        with h.stream("GET", "/v1/sessions/s/decisions", params={"wait": "30"},
                      headers={"accept": "text/event-stream"}) as r:
            assert r.status_code == 200
            lines = r.iter_lines()
            assert next(lines) == "event: feed"
            t0 = time.monotonic()
            d = c.select("s", method="random")
            got = []
            for line in lines:  # the decision comes while the stream is open
                got.append(line)
                if line.startswith("data: {\"seq\""):
                    break
            assert time.monotonic() - t0 < 20 and f'"id":{d.chosen.id},' in got[-1]
            assert any(x.startswith("id: ") and x.endswith(":1") for x in got)
            poll = threading.Thread(target=lambda: polled.append(
                Client(srv.url).get_decisions("s", after=1, wait=30)))
            poll.start()
            time.sleep(0.5)
            t0 = time.monotonic()
            stopper = threading.Thread(target=srv.stop)
            stopper.start()
            rest = list(lines)  # the stream ends: the server is stopping
            poll.join(30)
            stopper.join(60)
            took = time.monotonic() - t0
        assert not any(x.startswith("event: decision") for x in rest)
        assert polled and polled[0].decisions == [] and took < 8, took


# ============================================================================ imports
def test_the_viewer_needs_no_torch() -> None:
    code = ("import sys, viser, agilegs.service.viewer.live, agilegs.service.viewer.replay, "
            "agilegs.service.viewer.cli, agilegs.service.viewer.browser; "
            "bad = [m for m in ('torch', 'fastapi', 'uvicorn') if m in sys.modules]; "
            "print(bad); sys.exit(1 if bad else 0)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr


def test_the_view_command_does_not_log_each_request(server: ServerProcess) -> None:
    """``agilegs view`` long-polls the server; its HTTP client logs at WARNING, so the
    terminal shows no line per request."""
    sid = new_id()
    with Client(server.url) as c:
        c.create_session(SMALL_INTRINSICS, id=sid, gaussians=blob(50), pool=ring_poses(6))
        c.select(sid, method="random", commit=True)
    got = subprocess.run(
        [sys.executable, "-m", "agilegs.service.cli", "view", server.url, "--session", sid,
         "--port", str(free_port()), "--poll", "0.2", "--duration", "3"],
        capture_output=True, text=True, timeout=120)
    assert got.returncode == 0, got.stdout + got.stderr
    assert "HTTP Request" not in got.stdout + got.stderr, got.stderr[-2000:]
