"""``agilegs bench edge``: what slow clients and large bodies cost a real ``agilegs serve``.

Starts ``agilegs serve`` (HTTP only, the default limits but for ``--header-timeout`` and
``--body-timeout``, and ``--env``), creates a small session, then runs two phases:

- ``connections``: opens ``--connections`` connections at once, a third sending nothing, a
  third trickling a request's headers and a third a body, a byte a second. It prints how long
  the server took to close them (each should within its deadline, plus the loop's slack),
  and the latency of another client's ``get_session`` (p50 / p99 of ``--probes`` requests)
  with the server idle and during the phase.
- ``bodies`` (another server, the default deadlines): ``--bodies`` clients post a
  ``--body-mib`` MiB body each at once (a body the server reads, then refuses for what it
  holds). It prints how many were read and how many
  refused for the budget of bodies in flight (503), the server's resident memory idle, its
  peak during the phase beside ``max_inflight_body_bytes``, and its resident memory
  ``--settle`` seconds later.

The last line says whether each target held: every connection closed within its deadline,
the p99 during at most twice the idle p99, the peak over idle within the budget, and the
memory after the settle within 20 % of idle.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from .bigmap import proc_memory, reset_peak

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    a = parser.add_argument
    a("--phases", default="connections,bodies", help="connections, bodies (comma-separated)")
    a("--connections", type=int, default=1000, help="slow or idle connections at once")
    a("--header-timeout", type=float, default=5.0, help="the server's header_timeout (s)")
    a("--body-timeout", type=float, default=5.0, help="the server's body_timeout (s)")
    a("--probes", type=int, default=200, help="get_session requests timed idle and during")
    a("--bodies", type=int, default=64, help="concurrent large bodies")
    a("--body-mib", type=float, default=60.0, help="MiB per body")
    a("--settle", type=float, default=60.0, help="seconds before the memory is read again")
    a("--env", action="append", default=[], metavar="AGILEGS_X=VALUE",
      help="a server setting (repeatable)")
    a("--json", dest="json_out", help="also write the results here")


def _say(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def _percentiles(ms: list[float]) -> dict[str, float]:
    ms = sorted(ms)
    return {"p50": statistics.median(ms), "p99": ms[min(len(ms) - 1, int(0.99 * len(ms)))],
            "n": len(ms)}


def _probe(url: str, sid: str, n: int, stop: threading.Event | None = None) -> list[float]:
    """Latencies (ms) of ``n`` get_session requests one after another (until ``stop``)."""
    import httpx

    out: list[float] = []
    with httpx.Client(base_url=url, timeout=60) as h:
        h.get(f"/v1/sessions/{sid}")
        while len(out) < n and not (stop is not None and stop.is_set()):
            t0 = time.perf_counter()
            r = h.get(f"/v1/sessions/{sid}")
            out.append((time.perf_counter() - t0) * 1e3)

            r.raise_for_status()
            time.sleep(0.01)
    return out


async def _slow_connection(port: int, kind: str, sid: str, deadline: float) -> float:
    """Seconds until the server closes a connection that sends ``kind`` slowly."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    t0 = time.monotonic()
    if kind == "body":
        writer.write(f"POST /v1/sessions/{sid}/observations HTTP/1.1\r\nHost: x\r\n"
                     "Content-Type: application/json\r\nContent-Length: 100000\r\n\r\n"
                     .encode())
    trickle = b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Slow: " + b"a" * 200
    i = 0
    try:
        while time.monotonic() - t0 < deadline:
            try:
                data = await asyncio.wait_for(reader.read(65536), 1.0)
                if not data:
                    return time.monotonic() - t0
            except TimeoutError:
                pass
            if kind != "idle":
                writer.write(b"{" if kind == "body" else trickle[i % len(trickle):][:1])
                i += 1
    except (ConnectionResetError, BrokenPipeError):
        return time.monotonic() - t0
    finally:
        writer.close()
    return float("inf")


def _slow_main(port: int, kinds: list[str], sid: str, limit: float) -> list[float]:
    """Open a connection per kind at once and time each until the server closes it."""
    async def main() -> list[float]:
        tasks = [asyncio.create_task(_slow_connection(port, k, sid, limit)) for k in kinds]
        return list(await asyncio.gather(*tasks))

    return asyncio.run(main())


def _connections(srv: Any, sid: str, args: argparse.Namespace) -> dict[str, Any]:
    import subprocess

    idle = _probe(srv.url, sid, args.probes)
    limit = max(args.header_timeout, args.body_timeout) * 4 + 10
    kinds = [("idle", "headers", "body")[i % 3] for i in range(args.connections)]
    # the slow clients in a process of their own: the probe's latency is the server's
    code = ("import json, sys; from agilegs.lab.bench.edge import _slow_main; "
            "a = json.loads(sys.argv[1]); "
            "print(json.dumps(_slow_main(a['port'], a['kinds'], a['sid'], a['limit'])))")
    t0 = time.monotonic()
    child = subprocess.Popen(
        [sys.executable, "-c", code, json.dumps({"port": srv.port, "kinds": kinds, "sid": sid,
                                                 "limit": limit})],
        stdout=subprocess.PIPE, text=True)
    time.sleep(1.0)  # the connections open
    during: list[float] = []
    stop = threading.Event()
    thread = threading.Thread(target=lambda: during.extend(_probe(srv.url, sid, 10 ** 9, stop)))
    thread.start()
    out_text, _ = child.communicate(timeout=limit + 60)
    stop.set()
    thread.join()
    wall = time.monotonic() - t0
    closed = [float(c) for c in json.loads(out_text)]
    out: dict[str, Any] = {"connections": args.connections, "wall_s": wall,
                           "idle_ms": _percentiles(idle),
                           "during_ms": _percentiles(during) if during else None}
    for kind, timeout in (("idle", args.header_timeout), ("headers", args.header_timeout),
                          ("body", args.body_timeout)):
        secs = [c for c, k in zip(closed, kinds, strict=True) if k == kind]
        out[f"closed_{kind}_s"] = {"min": min(secs), "max": max(secs), "timeout": timeout,
                                   "open": sum(1 for c in secs if c == float("inf"))}
    return out


def _bodies(srv: Any, sid: str, args: argparse.Namespace) -> dict[str, Any]:
    import httpx

    assert srv.proc is not None
    pid = srv.proc.pid
    payload = b"\x00" * int(args.body_mib * 2**20)
    time.sleep(1.0)
    idle = proc_memory(pid)
    reset_peak(pid)
    statuses: list[int] = []
    lock = threading.Lock()

    def post() -> None:
        with httpx.Client(base_url=srv.url, timeout=600) as h:
            try:
                r = h.post(f"/v1/sessions/{sid}/observations", content=payload,
                           headers={"content-type": "application/msgpack"})
                status = r.status_code
            except httpx.HTTPError:
                status = 0  # the server closed the connection of a refused body
        with lock:
            statuses.append(status)

    t0 = time.monotonic()
    threads = [threading.Thread(target=post) for _ in range(args.bodies)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.monotonic() - t0
    peak = proc_memory(pid)["VmHWM"]
    time.sleep(args.settle)
    after = proc_memory(pid)["VmRSS"]
    counts: dict[str, int] = {}
    for s in statuses:
        counts[str(s)] = counts.get(str(s), 0) + 1
    return {"bodies": args.bodies, "body_mib": args.body_mib, "wall_s": wall,
            "statuses": counts, "idle_rss_mib": idle["VmRSS"], "peak_rss_mib": peak,
            "after_settle_rss_mib": after, "settle_s": args.settle}


def run(args: argparse.Namespace) -> int:
    phases = [p.strip() for p in args.phases.split(",") if p.strip()]
    env = {"AGILEGS_HEADER_TIMEOUT": str(args.header_timeout),
           "AGILEGS_BODY_TIMEOUT": str(args.body_timeout), "AGILEGS_TORCH_THREADS": "1",
           "AGILEGS_MAPPER": "false"}
    for item in args.env:
        key, _, value = item.partition("=")
        env[key] = value
    results: dict[str, Any] = {}
    logging.getLogger("httpx").setLevel(logging.WARNING)
    if "connections" in phases:
        with _server(env) as (srv, sid):
            c = _connections(srv, sid, args)
        results["connections"] = c
        _say(f"{c['connections']} slow or idle connections ({c['wall_s']:.1f} s):")
        for kind in ("idle", "headers", "body"):
            k = c[f"closed_{kind}_s"]
            _say(f"  {kind:8s} closed after {k['min']:.2f}-{k['max']:.2f} s "
                  f"(timeout {k['timeout']:.1f} s), {k['open']} left open")
        i, d = c["idle_ms"], c["during_ms"]
        _say(f"  get_session idle    p50 {i['p50']:.1f} ms  p99 {i['p99']:.1f} ms "
              f"({i['n']} requests)")
        if d is not None:
            _say(f"  get_session during  p50 {d['p50']:.1f} ms  p99 {d['p99']:.1f} "
                  f"ms ({d['n']} requests): p99 {d['p99'] / i['p99']:.2f}x idle")
    if "bodies" in phases:
        # the default deadlines: a 60 MiB body among 64 takes more than a few seconds
        body_env = {k: v for k, v in env.items()
                    if k not in ("AGILEGS_HEADER_TIMEOUT", "AGILEGS_BODY_TIMEOUT")}
        with _server(body_env) as (srv, sid):
            b = _bodies(srv, sid, args)
            b["budget_mib"] = _budget(srv) / 2**20
        results["bodies"] = b
        _say(f"{b['bodies']} concurrent bodies of {b['body_mib']:.0f} MiB "
              f"({b['wall_s']:.1f} s): statuses {b['statuses']}")
        _say(f"  server RSS idle {b['idle_rss_mib']:.0f} MiB, peak "
              f"{b['peak_rss_mib']:.0f} MiB (+{b['peak_rss_mib'] - b['idle_rss_mib']:.0f}"
              f" MiB; max_inflight_body_bytes {b['budget_mib']:.0f} MiB), "
              f"{b['settle_s']:.0f} s later {b['after_settle_rss_mib']:.0f} MiB "
              f"({b['after_settle_rss_mib'] / b['idle_rss_mib'] - 1:+.0%} of idle)")
    results["targets"] = targets(results)
    _say("targets: " + ", ".join(f"{k} {'met' if v else 'MISSED'}"
                                  for k, v in results["targets"].items()))
    if args.json_out:
        Path(args.json_out).write_text(json.dumps(results, indent=2))
    return 0


@contextmanager
def _server(env: dict[str, str]) -> Iterator[tuple[Any, str]]:
    """``agilegs serve`` (HTTP only) with a small session, stopped at the end."""
    import httpx

    from agilegs.service.launch import ServerProcess

    with tempfile.TemporaryDirectory() as tmp:
        srv = ServerProcess(Path(tmp) / "state", zenoh=False, env=env).start()
        try:
            sid = "edge"
            with httpx.Client(base_url=srv.url, timeout=60) as h:
                h.post("/v1/sessions", json={
                    "id": sid, "bounds": {"min": [-0.5] * 3, "max": [0.5] * 3},
                    "intrinsics": {"fx": 60, "fy": 60, "cx": 32, "cy": 32, "width": 64,
                                   "height": 64}}).raise_for_status()
            yield srv, sid
        finally:
            srv.stop()


def _budget(srv: Any) -> int:
    """The server's ``max_inflight_body_bytes`` (its environment, else the default)."""
    from agilegs.service.settings import Settings

    value = srv.env.get("AGILEGS_MAX_INFLIGHT_BODY_BYTES")
    return int(value) if value else Settings.model_fields["max_inflight_body_bytes"].default


def targets(results: dict[str, Any]) -> dict[str, bool]:
    """Whether each target held (see the module docstring)."""
    out = {}
    c = results.get("connections")
    if c is not None:
        slack = 2.5  # the client polls each connection once a second
        out["closed within the deadline"] = all(
            c[f"closed_{k}_s"]["open"] == 0
            and c[f"closed_{k}_s"]["max"] <= c[f"closed_{k}_s"]["timeout"] + slack
            for k in ("idle", "headers", "body"))
        out["p99 within 2x idle"] = (c["during_ms"] is not None
                                     and c["during_ms"]["p99"] <= 2 * c["idle_ms"]["p99"])
    b = results.get("bodies")
    if b is not None:
        out["peak within the budget"] = (b["peak_rss_mib"] - b["idle_rss_mib"]
                                         <= b["budget_mib"])
        out["back within 20% of idle"] = b["after_settle_rss_mib"] <= 1.2 * b["idle_rss_mib"]
    return out


if __name__ == "__main__":  # pragma: no cover
    p = argparse.ArgumentParser()
    add_arguments(p)
    sys.exit(run(p.parse_args()))
