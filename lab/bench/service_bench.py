"""``agilegs bench service``: transport overhead of a selection, and throughput under load.

Starts ``agilegs serve`` in a subprocess on free loopback ports (or uses ``--url`` and
``--zenoh``), creates a session on a scene (default: the teapot subsampled to
``--max-gaussians``) with a pool of ``--pool`` candidates, then:

1. **Overhead.** ``--requests`` selections (no commit) over HTTP JSON, HTTP msgpack,
   Zenoh and ROS 2 (the ``select`` service as CDR on the keys of zenoh-bridge-ros2dds, a
   started server serving ``--ros2``; ``preset`` only), each timed by the client. Transport
   overhead = client round trip - the core's selection time (``latency_ms.total``); also
   shown: server time (``server_ms``) - core time, the part of the overhead spent inside the
   server (decode, validate, lock, encode), the core time itself, and the whole round trip.
   Two request shapes: the pool set beforehand (``preset``: a small body naming the
   session's 300 candidates) and the pool sent inside the select request (``inline``: 300
   poses in the body, persisted before the answer).
2. **Load.** ``--clients`` clients, each on a session of its own, select and commit
   ``--selections`` times at once over HTTP msgpack; reports selections per second, errors,
   and checks that every acknowledged commit is in the session afterwards.
3. **Noisy neighbour.** A quiet session selects and commits (``--load-method``)
   ``--neighbour-selections`` times back to back, alone, then again (a fresh session of the
   same state) while ``--flood-clients`` clients flood another session with
   ``--flood-method`` selects (each sent again as soon as it is answered or refused):
   the quiet session's p50 and p99 round trips, unloaded and loaded, and their ratios.
4. **Deadline.** Every selection method, ``--deadline-requests`` times after ``--warmup``
   untimed ones, over HTTP JSON with
   ``X-Deadline-Ms: --deadline-ms``: the answers' statuses and how long after the deadline
   the client had its answer (the overshoot: round trip - deadline), p50 and max.

``--phases`` picks which run (default all four).

With ``--instance ID`` (and ``--url`` / ``--zenoh`` of another instance of the same cluster)
the sessions are created on instance ``ID``: every request then goes through the instance the
benchmark talks to and is forwarded to the owner, and the overhead includes the forwarding.
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import os
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from agilegs.config.selection import METHODS
from agilegs.lab.scenes import bundled_scene
from agilegs.service.launch import ServerProcess

log = logging.getLogger(__name__)

DEFAULT_SCENE = str(bundled_scene("teapot"))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    a = parser.add_argument
    a("--url", help="a running server (default: start one)")
    a("--zenoh", help="its Zenoh endpoint, e.g. tcp/127.0.0.1:7447 (with --url)")
    a("--ros2", default=None, metavar="NAMESPACE",
      help="the ROS 2 namespace timed (default /bench/agilegs on a started server; with "
           "--url: only when given)")
    a("--token", help="bearer token (default: AGILEGS_TOKEN)")
    a("--zenoh-credentials", metavar="CLIENT_JSON",
      help="the server's <state-dir>/zenoh/client.json (a server with a token admits no Zenoh "
           "peer without it; default: that of the server started here)")
    a("--scene", default=DEFAULT_SCENE, help=".splat / .ply scene (random Gaussians if absent)")
    a("--max-gaussians", type=int, default=2000, help="subsample the scene to this many")
    a("--pool", type=int, default=300, help="candidates per pool")
    a("--size", type=int, default=64, help="candidate image width and height (px)")
    a("--method", default="random", help=f"selection method timed for the overhead (one of "
      f"{', '.join(METHODS)})")
    a("--requests", type=int, default=200, help="timed selections per transport and shape")
    a("--warmup", type=int, default=20, help="untimed selections first")
    a("--clients", type=int, default=8, help="concurrent clients in the load phase")
    a("--selections", type=int, default=10, help="select + commit per client")
    a("--load-method", default="agile", help="selection method of the load phase")
    a("--instance", help="create the sessions on this instance of a cluster (requests to "
      "--url's instance are then forwarded to it)")
    a("--phases", default="overhead,load,neighbour,deadline",
      help="which phases run: overhead, load, neighbour, deadline (comma-separated)")
    a("--flood-clients", type=int, default=8, help="clients flooding the noisy session")
    a("--flood-method", default="full_eig", help="selection method of the flood")
    a("--neighbour-selections", type=int, default=30,
      help="select + commit of the quiet session, unloaded and loaded")
    a("--deadline-ms", type=float, default=50.0,
      help="the deadline phase's X-Deadline-Ms (milliseconds)")
    a("--deadline-requests", type=int, default=5,
      help="selections per method in the deadline phase")
    a("--json", dest="json_out", help="also write the results here")


def _scene_arrays(path: str, max_gaussians: int) -> dict[str, np.ndarray] | None:
    if not Path(path).is_file():
        return None
    from agilegs.service.nbv import load_scene

    g = load_scene(path, max_gaussians=max_gaussians, seed=0)
    return {k: v.detach().cpu().numpy() for k, v in g.items()}


def _pool(n: int, radius: float = 1.6) -> np.ndarray:
    """``n`` camera-to-world poses on three rings around the origin, looking at it."""
    out = []
    per = int(np.ceil(n / 3))
    for ring, elev in enumerate((-0.5, -0.15, 0.25)):
        for a in np.linspace(0, 2 * np.pi, per, endpoint=False) + ring * 0.1:
            eye = radius * np.array([np.cos(a) * np.cos(elev), np.sin(elev),
                                     np.sin(a) * np.cos(elev)])
            z = -eye / np.linalg.norm(eye)
            x = np.cross(np.array([0.0, 1.0, 0.0]), z)
            x /= np.linalg.norm(x)
            m = np.eye(4)
            m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, np.cross(z, x), z, eye
            out.append(m)
    return np.stack(out[:n])


def _stats(xs: list[float]) -> dict[str, float]:
    s = sorted(xs)
    return {
        "p50": statistics.median(s),
        "p99": s[min(len(s) - 1, int(round(0.99 * (len(s) - 1))))],
        "mean": statistics.fmean(s),
    }


def _time_selects(select: Callable[[], Any], n: int, warmup: int) -> dict[str, Any]:
    for _ in range(warmup):
        select()
    gc.collect()
    gc.freeze()  # as a long-running robot process would: full collections skip the imports
    rtt, server, core, whole = [], [], [], []
    for _ in range(n):
        t = time.perf_counter()
        r = select()
        dt = (time.perf_counter() - t) * 1e3
        total = r.latency_ms["total"]
        rtt.append(dt - total)
        server.append((r.server_ms or 0.0) - total)
        core.append(total)
        whole.append(dt)
    return {"overhead_ms": _stats(rtt), "server_overhead_ms": _stats(server),
            "core_ms": _stats(core), "round_trip_ms": _stats(whole), "requests": n}


def check_methods(args: argparse.Namespace) -> None:
    """SystemExit with a one-line message naming a ``--method`` / ``--load-method`` that is
    not a selection method of the server."""
    for flag, name in (("--method", args.method), ("--load-method", args.load_method),
                       ("--flood-method", args.flood_method)):
        if name not in METHODS:
            raise SystemExit(f"{flag}: unknown method {name!r} (known: {', '.join(METHODS)})")


def run(args: argparse.Namespace) -> int:
    from agilegs.client import AgileGSError, Client, ZenohClient
    from agilegs.service.settings import Credentials

    check_methods(args)
    args.token = args.token or Credentials().token_value()

    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per request otherwise
    server = None
    url, zenoh_ep = args.url, args.zenoh
    tmp = tempfile.TemporaryDirectory(prefix="agilegs-bench-")
    if url is None:
        env = {"AGILEGS_TOKEN": args.token} if args.token else {}
        args.ros2 = args.ros2 or "/bench/agilegs"
        server = ServerProcess(Path(tmp.name) / "state", env=env,
                               args=["--ros2", args.ros2]).start()
        url, zenoh_ep = server.url, server.zenoh_endpoint
        args.zenoh_credentials = args.zenoh_credentials or server.zenoh_credentials
    results: dict[str, Any] = {"pool": args.pool, "method": args.method,
                               "gaussians": args.max_gaussians, "size": args.size,
                               "instance": args.instance}
    clients: dict[str, Any] = {}
    try:
        clients["http-json"] = Client(url, token=args.token, encoding="json")
        clients["http-msgpack"] = Client(url, token=args.token, encoding="msgpack")
        if zenoh_ep:
            clients["zenoh"] = ZenohClient([zenoh_ep], token=args.token,
                                           credentials=args.zenoh_credentials)
        c = clients["http-msgpack"]
        phases = {p.strip() for p in args.phases.split(",") if p.strip()}
        unknown = phases - {"overhead", "load", "neighbour", "deadline"}
        if unknown:
            raise SystemExit(f"--phases: unknown phase(s) {', '.join(sorted(unknown))}")
        f = args.size / 2 / np.tan(np.radians(25))
        intr = {"fx": f, "fy": f, "cx": args.size / 2, "cy": args.size / 2,
                "width": args.size, "height": args.size}
        arrays = _scene_arrays(args.scene, args.max_gaussians)
        bounds = {"min": [-0.5] * 3, "max": [0.5] * 3}
        poses = _pool(args.pool)
        scene: dict[str, Any] = ({"gaussians": arrays} if arrays is not None else
                                 {"bounds": bounds, "init_gaussians": args.max_gaussians})
        sid = f"bench-{os.getpid()}"
        c.create_session(intr, id=sid, pool=poses, instance=args.instance, **scene)
        if zenoh_ep and args.ros2 and "overhead" in phases:
            clients["ros2"] = _Ros2Client(args.ros2, zenoh_ep, sid, args.token,
                                          args.zenoh_credentials)
        results["overhead"] = {}
        for name, client in clients.items() if "overhead" in phases else ():
            for shape in ("preset",) if name == "ros2" else ("preset", "inline"):
                log.info("timing %s, %s pool", name, shape)
                if shape == "preset":
                    def select(cl: Any = client) -> Any:
                        return cl.select(sid, method=args.method)
                else:
                    def select(cl: Any = client) -> Any:
                        return cl.select(sid, method=args.method, pool=poses)
                results["overhead"][f"{name}/{shape}"] = _time_selects(
                    select, args.requests, args.warmup)
        if "deadline" in phases:
            results["deadline"] = _deadline(url, args, sid)
        c.delete_session(sid)
        if "load" in phases:
            results["load"] = _load(url, args, intr, scene, poses)
        if "neighbour" in phases:
            results["neighbour"] = _neighbour(url, args, intr, scene, poses)
    except AgileGSError as exc:
        log.error("benchmark failed: %s", exc)
        return 1
    finally:
        for cl in clients.values():
            cl.close()
        if server is not None:
            server.stop()
        tmp.cleanup()
    _print(results)
    if args.json_out:
        Path(args.json_out).write_text(json.dumps(results, indent=2))
    ld = results.get("load", {"errors": 0, "lost": 0})
    nb = results.get("neighbour", {"errors": 0})
    return 0 if ld["errors"] == 0 and ld["lost"] == 0 and nb["errors"] == 0 else 1


class _Ros2Client:
    """``select`` over the ROS 2 service (CDR), with the client's answer shape."""

    def __init__(self, namespace: str, endpoint: str, sid: str, token: str | None,
                 credentials: Any = None) -> None:
        from agilegs.client.ros2.robot import Ros2Robot

        self.robot = Ros2Robot(namespace, connect=[endpoint], credentials=credentials)
        self.robot.token = token or ""
        opened = self.robot.open_session(sid)
        if opened.status.status != 200:
            self.robot.close()
            raise SystemExit(f"--ros2 {namespace}: open_session refused: "
                             f"{opened.status.message}")

    def select(self, sid: str, method: str) -> Any:
        from types import SimpleNamespace

        r = self.robot.select(method=method)
        if r.status.status != 200:
            raise SystemExit(f"ros2 select refused: {r.status.message}")
        return SimpleNamespace(latency_ms={"total": r.latency_ms}, server_ms=r.server_ms)

    def close(self) -> None:
        self.robot.close()


def _deadline(url: str, args: argparse.Namespace, sid: str) -> dict[str, Any]:
    """Each method's selections (no commit) with ``X-Deadline-Ms``: statuses (str -> count)
    and the overshoot past the deadline (ms, p50 and max) per method."""
    import httpx

    headers = {"x-deadline-ms": f"{args.deadline_ms:g}"}
    if args.token:
        headers["authorization"] = f"Bearer {args.token}"
    out: dict[str, Any] = {"deadline_ms": args.deadline_ms, "methods": {}}
    with httpx.Client(base_url=url, timeout=600.0, headers=headers) as h:
        for method in METHODS:
            log.info("deadline: %s", method)
            statuses: dict[str, int] = {}
            over: list[float] = []
            for _ in range(args.warmup):  # a process's first calls compile or load kernels
                h.post(f"/v1/sessions/{sid}/select", json={"method": method})
            for _ in range(args.deadline_requests):
                t = time.perf_counter()
                r = h.post(f"/v1/sessions/{sid}/select", json={"method": method})
                over.append((time.perf_counter() - t) * 1e3 - args.deadline_ms)
                statuses[str(r.status_code)] = statuses.get(str(r.status_code), 0) + 1
            out["methods"][method] = {"statuses": statuses, "overshoot_ms": {
                "p50": statistics.median(over), "max": max(over)}}
    return out


def _load(url: str, args: argparse.Namespace, intr: dict[str, Any], scene: dict[str, Any],
          poses: np.ndarray) -> dict[str, Any]:
    from agilegs.client import AgileGSError, Client

    ids = [f"load-{os.getpid()}-{i}" for i in range(args.clients)]
    with Client(url, token=args.token) as c:
        for sid in ids:
            c.create_session(intr, id=sid, pool=poses, instance=args.instance, **scene)
    acked: dict[str, list[int]] = {sid: [] for sid in ids}
    errors: list[str] = []
    barrier = threading.Barrier(args.clients)

    def robot(sid: str) -> None:
        with Client(url, token=args.token) as c:
            barrier.wait()
            for _ in range(args.selections):
                try:
                    r = c.select(sid, method=args.load_method, commit=True)
                    assert r.committed is not None
                    acked[sid].append(r.committed.id)
                except AgileGSError as exc:
                    errors.append(f"{sid}: {exc}")

    threads = [threading.Thread(target=robot, args=(sid,)) for sid in ids]
    t = time.perf_counter()
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    elapsed = time.perf_counter() - t
    lost = 0
    with Client(url, token=args.token) as c:
        for sid in ids:
            stored = {v.id for v in c.list_views(sid).views}
            lost += sum(1 for v in acked[sid] if v not in stored)
            c.delete_session(sid)
    done = sum(len(v) for v in acked.values())
    return {"clients": args.clients, "method": args.load_method, "selections": done,
            "seconds": elapsed, "selections_per_s": done / elapsed, "errors": len(errors),
            "lost": lost, "error_samples": errors[:3]}


def _neighbour(url: str, args: argparse.Namespace, intr: dict[str, Any],
               scene: dict[str, Any], poses: np.ndarray) -> dict[str, Any]:
    """The quiet session's select + commit round trips, alone and beside a flooded one."""
    from agilegs.client import AgileGSError, APIError, Client

    tag = f"{os.getpid()}"
    noisy = f"noisy-{tag}"
    errors: list[str] = []
    with Client(url, token=args.token) as c:
        c.create_session(intr, id=noisy, pool=poses, instance=args.instance, **scene)

    def quiet_run(sid: str) -> list[float]:
        with Client(url, token=args.token) as c:
            c.create_session(intr, id=sid, pool=poses, instance=args.instance, **scene)
            for _ in range(3):  # warm: the selection, the commit and its write
                c.select(sid, method=args.load_method, commit=True)
            out = []
            for _ in range(args.neighbour_selections):
                t = time.perf_counter()
                try:
                    r = c.select(sid, method=args.load_method, commit=True)
                    assert r.committed is not None
                except AgileGSError as exc:
                    errors.append(f"{sid}: {exc}")
                    continue
                out.append((time.perf_counter() - t) * 1e3)
            c.delete_session(sid)
        return out

    unloaded = quiet_run(f"quiet-a-{tag}")
    stop = threading.Event()
    flood = {"answered": 0, "refused": 0}

    def flooder() -> None:
        with Client(url, token=args.token, timeout=600) as c:
            while not stop.is_set():
                try:
                    c.select(noisy, method=args.flood_method)
                    flood["answered"] += 1
                except APIError as exc:
                    flood["refused"] += 1
                    if exc.status not in (429, 503):
                        errors.append(f"flood: {exc}")
                        return
                    time.sleep(0.01)

    threads = [threading.Thread(target=flooder) for _ in range(args.flood_clients)]
    for th in threads:
        th.start()
    time.sleep(1.0)  # the flood under way
    loaded = quiet_run(f"quiet-b-{tag}")
    stop.set()
    for th in threads:
        th.join()
    with Client(url, token=args.token) as c:
        c.delete_session(noisy)
    a, b = _stats(unloaded or [float("nan")]), _stats(loaded or [float("nan")])
    return {"method": args.load_method, "flood_method": args.flood_method,
            "flood_clients": args.flood_clients, "selections": args.neighbour_selections,
            "unloaded_ms": a, "loaded_ms": b, "p50_ratio": b["p50"] / a["p50"],
            "p99_ratio": b["p99"] / a["p99"], "flood_answered": flood["answered"],
            "flood_refused": flood["refused"], "errors": len(errors),
            "error_samples": errors[:3]}


def _print(results: dict[str, Any]) -> None:
    out = sys.stdout
    where = (f", sessions on instance {results['instance']} (forwarded)"
             if results.get("instance") else "")
    out.write(f"\nagilegs bench service: select ({results['method']}) over a "
              f"{results['pool']}-candidate pool, {results['gaussians']} Gaussians, "
              f"{results['size']}x{results['size']} px{where}\n\n")
    if results["overhead"]:
        out.write(f"{'transport / pool':<24}{'overhead p50':>14}{'p99':>10}"
                  f"{'in server p50':>15}{'p99':>10}{'core p50':>11}{'round trip p50':>16}\n")
    for name, r in results["overhead"].items():
        o, s, c = r["overhead_ms"], r["server_overhead_ms"], r["core_ms"]
        w = r["round_trip_ms"]
        out.write(f"{name:<24}{o['p50']:>11.2f} ms{o['p99']:>7.2f} ms{s['p50']:>12.2f} ms"
                  f"{s['p99']:>7.2f} ms{c['p50']:>8.2f} ms{w['p50']:>13.2f} ms\n")
    ld = results.get("load")
    if ld is not None:
        out.write(f"\nload: {ld['clients']} clients x "
                  f"{ld['selections'] // max(ld['clients'], 1)} select+commit ({ld['method']}), "
                  f"{ld['selections_per_s']:.1f} selections/s, {ld['errors']} errors, "
                  f"{ld['lost']} acknowledged commits lost\n")
    nb = results.get("neighbour")
    if nb is not None:
        a, b = nb["unloaded_ms"], nb["loaded_ms"]
        out.write(f"\nnoisy neighbour: {nb['selections']} select+commit ({nb['method']}) of a "
                  f"quiet session, alone and while {nb['flood_clients']} clients flood another "
                  f"with {nb['flood_method']} selects ({nb['flood_answered']} answered, "
                  f"{nb['flood_refused']} refused 429/503)\n")
        out.write(f"{'':<12}{'p50':>12}{'p99':>12}\n")
        out.write(f"{'unloaded':<12}{a['p50']:>9.1f} ms{a['p99']:>9.1f} ms\n")
        out.write(f"{'loaded':<12}{b['p50']:>9.1f} ms{b['p99']:>9.1f} ms\n")
        out.write(f"{'ratio':<12}{nb['p50_ratio']:>11.2f}x{nb['p99_ratio']:>11.2f}x"
                  f"   ({nb['errors']} errors)\n")
    dl = results.get("deadline")
    if dl is not None:
        out.write(f"\ndeadline: X-Deadline-Ms {dl['deadline_ms']:g}, answered after the "
                  f"deadline by (overshoot)\n")
        out.write(f"{'method':<12}{'statuses':<20}{'p50':>10}{'max':>12}\n")
        for method, m in dl["methods"].items():
            st = ", ".join(f"{k} x{v}" for k, v in sorted(m["statuses"].items()))
            o = m["overshoot_ms"]
            out.write(f"{method:<12}{st:<20}{o['p50']:>7.1f} ms{o['max']:>9.1f} ms\n")
    out.flush()
