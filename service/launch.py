"""``agilegs serve`` in a subprocess on 127.0.0.1 and free ports: the one launcher the
tests, the demo and ``agilegs bench service`` use.

The server runs with its own state folder and log file; :meth:`ServerProcess.start` waits
until ``/healthz`` answers (HTTP) or the Zenoh ``health`` query does (Zenoh only).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

__all__ = ["ServerProcess", "free_port", "wait_until"]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_until(ready: Any, timeout: float, *, alive: Any = None, what: str = "the server"
               ) -> None:
    """Poll ``ready()`` (True, or no exception) until it holds; RuntimeError after
    ``timeout`` seconds, or as soon as ``alive()`` returns False."""
    deadline = time.monotonic() + timeout
    last: Exception | None = None
    while time.monotonic() < deadline:
        if alive is not None and not alive():
            raise RuntimeError(f"{what} exited")
        try:
            if ready() is not False:
                return
        except Exception as exc:  # not up yet
            last = exc
        time.sleep(0.1)
    raise RuntimeError(f"{what} was not ready within {timeout:.0f} s ({last})")


class ServerProcess:
    """``agilegs serve`` in a subprocess on free ports, with its own state folder.

    Args:
        state_dir: the server's state folder.
        http: serve over HTTP (on a free port).
        zenoh: serve over Zenoh (listening on a free loopback port).
        env: ``AGILEGS_*`` settings; the process gets no other ``AGILEGS_*`` variable.
        log_path: where its output goes (default: ``serve-<port>.log`` beside the state).
        args: more ``agilegs serve`` arguments.
    """

    def __init__(self, state_dir: Path | str, *, http: bool = True, zenoh: bool = True,
                 env: dict[str, str] | None = None, log_path: Path | None = None,
                 args: list[str] | None = None) -> None:
        self.state_dir = Path(state_dir)
        self.http = http
        self.port = free_port()
        self.zenoh_port = free_port() if zenoh else None
        self.env = dict(env or {})
        self.args = list(args or [])
        self.log_path = log_path or self.state_dir.parent / f"serve-{self.port}.log"
        self.proc: subprocess.Popen[bytes] | None = None
        self._log: Any = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def zenoh_endpoint(self) -> str:
        assert self.zenoh_port is not None
        return f"tcp/127.0.0.1:{self.zenoh_port}"

    @property
    def zenoh_credentials(self) -> Path | None:
        """The Zenoh credentials a server with a token made (``zenoh/client.json`` in its
        state folder; ``ZenohClient(credentials=...)``), or None when it made none."""
        path = self.state_dir / "zenoh" / "client.json"
        return path if path.exists() else None

    def command(self) -> list[str]:
        cmd = [sys.executable, "-m", "agilegs.service.cli", "serve", "--host", "127.0.0.1",
               "--port", str(self.port), "--state-dir", str(self.state_dir)]
        if not self.http:
            cmd.append("--no-http")
        if self.zenoh_port is None:
            cmd.append("--no-zenoh")
        else:
            cmd += ["--zenoh-listen", self.zenoh_endpoint]
        return cmd + self.args

    def start(self, timeout: float = 60.0) -> ServerProcess:
        """Start it and wait until it answers; RuntimeError (with the log's end) if it exits
        or does not answer in time."""
        env = {k: v for k, v in os.environ.items() if not k.startswith("AGILEGS_")}
        env.update(self.env)
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._log = open(self.log_path, "ab")
        self.proc = subprocess.Popen(self.command(), env=env, stdout=self._log,
                                     stderr=subprocess.STDOUT)
        try:
            wait_until(self._answers, timeout, alive=self.alive, what="agilegs serve")
        except RuntimeError as exc:
            self.stop()
            raise RuntimeError(f"{exc}:\n{self.log()[-3000:]}") from None
        return self

    def _answers(self) -> bool:
        token = self.env.get("AGILEGS_TOKEN")
        if self.http:
            import httpx

            headers = {"authorization": f"Bearer {token}"} if token else {}
            return httpx.get(self.url + "/healthz", headers=headers, timeout=1).status_code == 200
        from agilegs.client import ZenohClient

        with ZenohClient([self.zenoh_endpoint], token=token, wait=0, timeout=1.0,
                         credentials=self.zenoh_credentials) as zc:
            zc.health()
        return True

    def wait_ready(self, timeout: float = 600.0) -> float:
        """Wait until ``/readyz`` answers 200 (the warm-up done); the seconds waited.
        RuntimeError if the server exits or is not ready in time."""
        import httpx

        t0 = time.perf_counter()
        token = self.env.get("AGILEGS_TOKEN")
        headers = {"authorization": f"Bearer {token}"} if token else {}
        wait_until(lambda: httpx.get(self.url + "/readyz", headers=headers,
                                     timeout=1).status_code == 200,
                   timeout, alive=self.alive, what="agilegs serve's /readyz")
        return time.perf_counter() - t0

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def kill(self) -> None:
        """SIGKILL: no shutdown code runs."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(timeout=30)
        self.proc = None
        self._close_log()

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
        self._close_log()

    def _close_log(self) -> None:
        if self._log is not None:
            self._log.close()
            self._log = None

    def log(self) -> str:
        """What the server printed so far."""
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def __enter__(self) -> ServerProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
