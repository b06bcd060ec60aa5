"""The HTTP edge of a real ``agilegs serve`` (short deadlines): a connection that sends
nothing, half its headers or a body too slowly is closed within its deadline; an idle
connection after its keep-alive limit; a body beyond the budget of bodies in flight is
refused (503, Retry-After) before it is read; a client hanging up mid-body is logged once at
INFO and counted as 499, never as an error of the server."""

from __future__ import annotations

import re
import socket
import time
import uuid
from typing import Any

import httpx
from conftest import SMALL_INTRINSICS, gaussian_blob

from agilegs.client import Client

EDGE = {"AGILEGS_HEADER_TIMEOUT": "1.5", "AGILEGS_BODY_TIMEOUT": "2",
        "AGILEGS_KEEP_ALIVE_TIMEOUT": "1", "AGILEGS_MAX_INFLIGHT_BODY_BYTES": str(5 << 20)}


def _connect(port: int) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=30)
    return s


def _closed_after(s: socket.socket, trickle: bytes = b"", every: float = 0.25,
                  limit: float = 20.0) -> float:
    """Seconds until the server closes ``s``, sending ``trickle`` a byte at a time meanwhile
    (or nothing)."""
    t0 = time.monotonic()
    s.settimeout(every)
    i = 0
    while time.monotonic() - t0 < limit:
        try:
            data = s.recv(65536)
            if not data:
                return time.monotonic() - t0
            continue  # a response (e.g. 503 from the budget): keep reading until closed
        except TimeoutError:
            pass
        except ConnectionResetError:
            return time.monotonic() - t0
        if trickle:
            try:
                s.sendall(trickle[i % len(trickle): i % len(trickle) + 1])
            except (BrokenPipeError, ConnectionResetError):
                return time.monotonic() - t0
            i += 1
    raise AssertionError(f"the connection stayed open for {limit} s")


def _metric(text: str, status: str) -> float:
    return sum(float(v) for v in re.findall(
        rf'agilegs_requests_total{{[^}}]*status="{status}"[^}}]*}} ([0-9.e+]+)', text))


def _server_errors(text: str) -> float:
    return sum(float(v) for v in re.findall(
        r'agilegs_requests_total{[^}]*status="5\d\d"[^}]*} ([0-9.e+]+)', text))


def test_slow_and_idle_connections_are_closed_within_their_deadlines(
        server_factory: Any) -> None:
    srv = server_factory(zenoh=False, env=EDGE).start()
    # nothing sent; half a request line trickled in: closed after header_timeout
    assert 1.2 < _closed_after(_connect(srv.port)) < 4
    assert 1.2 < _closed_after(_connect(srv.port), b"GET /healthz HTTP/1.1\r\nHost: x\r\n") < 4
    # the headers, then a body at 4 bytes/s: closed after body_timeout
    s = _connect(srv.port)
    s.sendall(b"POST /v1/sessions HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
              b"Content-Length: 1000\r\n\r\n")
    assert 1.7 < _closed_after(s, b'{"id": "x", ') < 5
    # a request answered, then idle: closed after keep_alive_timeout
    s = _connect(srv.port)
    s.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
    assert s.recv(65536).startswith(b"HTTP/1.1 200")
    assert 0.7 < _closed_after(s) < 3
    with httpx.Client(base_url=srv.url) as h:  # the server still answers
        assert h.get("/healthz").status_code == 200
        metrics = h.get("/metrics").text
    assert _server_errors(metrics) == 0
    assert _metric(metrics, "499") == 1  # the slow body, cancelled
    assert "Traceback" not in srv.log() and "ERROR" not in srv.log()


def test_bodies_beyond_the_budget_in_flight_are_refused_before_they_are_read(
        server_factory: Any) -> None:
    srv = server_factory(zenoh=False, env=EDGE).start()
    sid = f"bud-{uuid.uuid4().hex[:6]}"
    with Client(srv.url, timeout=60) as c:
        c.create_session(SMALL_INTRINSICS, id=sid, gaussians=gaussian_blob(50))
    head = (f"POST /v1/sessions/{sid}/observations HTTP/1.1\r\nHost: x\r\n"
            "Content-Type: application/msgpack\r\nContent-Length: {n}\r\n\r\n")
    first = _connect(srv.port)  # 2 MiB announced, a part sent: held in the budget
    first.sendall(head.format(n=2 << 20).encode() + b"\x00" * 1000)
    time.sleep(0.3)
    with httpx.Client(base_url=srv.url) as h:
        r = h.post(f"/v1/sessions/{sid}/observations", content=b"\x00" * (1536 << 10),
                   headers={"content-type": "application/msgpack"})
        assert r.status_code == 503, r.text
        assert r.headers["retry-after"] == "1"
        assert r.json()["error"]["limit"] == "max_inflight_body_bytes"
        first.close()  # a hang-up mid-body: its bytes go back to the budget
        time.sleep(0.5)
        r = h.post(f"/v1/sessions/{sid}/observations", content=b"\x00" * (1536 << 10),
                   headers={"content-type": "application/msgpack"})
        assert 400 <= r.status_code < 500, r.text  # read, then refused for what it is
        assert h.get(f"/v1/sessions/{sid}").json()["num_views"] == 0
        metrics = h.get("/metrics").text
    assert _metric(metrics, "499") == 1 and _server_errors(metrics) == 1  # the 503 only


def test_hang_ups_mid_body_are_logged_once_and_counted_apart(server_factory: Any) -> None:
    srv = server_factory(zenoh=False, env=EDGE).start()
    sid = f"hup-{uuid.uuid4().hex[:6]}"
    with Client(srv.url, timeout=60) as c:
        c.create_session(SMALL_INTRINSICS, id=sid, gaussians=gaussian_blob(50))
    n = 40
    for i in range(n):
        s = _connect(srv.port)
        path = f"/v1/sessions/{sid}/observations" if i % 2 else "/v1/sessions"
        s.sendall(f"POST {path} HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                  f"Content-Length: 100000\r\n\r\n".encode() + b'{"observations": [' * 10)
        time.sleep(0.02)
        s.close()
    time.sleep(1.0)
    with httpx.Client(base_url=srv.url) as h:
        metrics = h.get("/metrics").text
        assert h.get(f"/v1/sessions/{sid}").json()["num_views"] == 0
    log = srv.log()
    assert _metric(metrics, "499") == n and _server_errors(metrics) == 0
    assert "Traceback" not in log and "ERROR" not in log
    assert log.count("the client disconnected") == n  # once each, at INFO
