"""Generic fixtures: free ports, and a real ``agilegs serve`` subprocess on 127.0.0.1."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class ServerProcess:
    """``agilegs serve`` in a subprocess, on free ports, with its own state folder.

    ``env`` adds ``AGILEGS_*`` settings; ``zenoh=False`` serves HTTP only.
    """

    def __init__(self, state_dir: Path, *, zenoh: bool = True, env: dict[str, str] | None = None,
                 log_path: Path | None = None) -> None:
        self.state_dir = Path(state_dir)
        self.port = free_port()
        self.zenoh_port = free_port() if zenoh else None
        self.env = dict(env or {})
        self.log_path = log_path or self.state_dir.parent / f"serve-{self.port}.log"
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def zenoh_endpoint(self) -> str:
        assert self.zenoh_port is not None
        return f"tcp/127.0.0.1:{self.zenoh_port}"

    def start(self, timeout: float = 60.0) -> ServerProcess:
        cmd = [sys.executable, "-m", "agilegs.service.cli", "serve", "--host", "127.0.0.1",
               "--port", str(self.port), "--state-dir", str(self.state_dir)]
        if self.zenoh_port is None:
            cmd.append("--no-zenoh")
        else:
            cmd += ["--zenoh-listen", self.zenoh_endpoint]
        env = {k: v for k, v in os.environ.items() if not k.startswith("AGILEGS_")}
        # the background mapper is off unless a test asks for it: these tests check exact state
        env.update({"AGILEGS_TORCH_THREADS": "1", "AGILEGS_MAPPER": "0", **self.env})
        self._log = open(self.log_path, "ab")
        self.proc = subprocess.Popen(cmd, env=env, stdout=self._log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + timeout
        headers = {}
        if "AGILEGS_TOKEN" in self.env:
            headers["authorization"] = f"Bearer {self.env['AGILEGS_TOKEN']}"
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited with {self.proc.returncode}: "
                                   f"{self.log_path.read_text()[-3000:]}")
            try:
                if httpx.get(self.url + "/healthz", headers=headers, timeout=1).status_code == 200:
                    return self
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        self.stop()
        raise RuntimeError(f"server did not start: {self.log_path.read_text()[-3000:]}")

    def kill(self) -> None:
        """SIGKILL: no shutdown code runs."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(timeout=30)
        self.proc = None

    def stop(self) -> None:
        """SIGTERM, then SIGKILL after 20 s."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        self.proc = None

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    """One shared server (HTTP and Zenoh) for the tests that need no restart or token."""
    root = tmp_path_factory.mktemp("server")
    srv = ServerProcess(root / "state", env={"AGILEGS_MAX_BODY_BYTES": str(8 * 2**20)}).start()
    yield srv
    srv.stop()


@pytest.fixture
def server_factory(tmp_path: Path) -> Iterator[type[ServerProcess] | object]:
    """Build servers of one's own (``server_factory(zenoh=False, env={...})``); all are
    stopped at the end of the test."""
    started: list[ServerProcess] = []

    def make(state_dir: Path | None = None, **kwargs: object) -> ServerProcess:
        srv = ServerProcess(state_dir or tmp_path / f"state{len(started)}", **kwargs)  # type: ignore[arg-type]
        started.append(srv)
        return srv

    yield make
    for srv in started:
        srv.stop()


def ring_poses(n: int, radius: float = 2.0, height: float = -0.3) -> np.ndarray:
    """``n`` camera-to-world poses [n, 4, 4] (OpenCV axes) on a ring, looking at the origin
    (world up is -y)."""
    out = []
    for a in np.linspace(0.0, 2 * np.pi, n, endpoint=False):
        eye = np.array([radius * np.cos(a), height, radius * np.sin(a)])
        z = -eye / np.linalg.norm(eye)
        x = np.cross(np.array([0.0, 1.0, 0.0]), z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, eye
        out.append(m)
    return np.stack(out)


@pytest.fixture
def ring() -> object:
    """``ring(n)``: camera poses on a ring around the origin (see :func:`ring_poses`)."""
    return ring_poses


SMALL_INTRINSICS = {"fx": 28.0, "fy": 28.0, "cx": 16.0, "cy": 16.0, "width": 32, "height": 32}


@pytest.fixture
def small_intrinsics() -> dict[str, float]:
    """32x32 pinhole intrinsics (keeps server tests fast)."""
    return dict(SMALL_INTRINSICS)
