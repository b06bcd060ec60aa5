"""``agilegs bench fleet``: a fleet of ``agilegs serve`` instances sharing an object store,
under a write load, with instances killed and paused.

Starts an S3 API on loopback (moto's server, ``pip install 'moto[server]'``; or
``--endpoint`` and ``--bucket`` of one already running, with the ``AWS_*`` variables) and
``--instances`` instances, Zenoh peers connected to each other, then runs:

- ``kill``: ``--sessions`` sessions placed by the policy, one writer per session committing a
  view every ``--interval`` s through one instance's HTTP (the client SDK, its retry window as
  documented); ``--kills`` times, the instance holding the most sessions is killed (SIGKILL;
  the writers moved to another instance first: a client's own endpoint dying is not what is
  measured), each of its sessions is polled until it answers again (takeover time), and the
  instance is started again. Then every session's views are read
  back and compared with the writes acknowledged: acknowledged writes lost, and the errors the
  writers saw (after the SDK's retries).
- ``pause``: the instance holding the most sessions is paused (SIGSTOP) until every one of
  them is taken over, then resumed and sent one commit per former session at once: how many
  were fenced (``session_unavailable``), forwarded to the new owner (applied once), and
  committed by the stale owner itself (writes through: must be 0), and whether it logged that
  it lost the lease.
- ``scale``: selections per second with 1, 2 and 3 instances of one compute thread each
  (``--selectors`` clients per instance, CPU-bound selects on sessions spread evenly).

It prints one line per figure and the targets of the fleet (takeover p99 under 5 s, nothing
lost, no stale write, no client error, two instances at least 1.8x one).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

__all__ = ["add_arguments", "run", "s3_server"]

INTRINSICS = {"fx": 28.0, "fy": 28.0, "cx": 16.0, "cy": 16.0, "width": 32, "height": 32}
BOUNDS = {"min": [-0.5] * 3, "max": [0.5] * 3}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    a = parser.add_argument
    a("--phases", default="kill,pause,scale", help="kill, pause, scale (comma-separated)")
    a("--instances", type=int, default=3, help="instances of the fleet")
    a("--sessions", type=int, default=6, help="sessions under the write load")
    a("--kills", type=int, default=3, help="instances killed (SIGKILL), one after the other")
    a("--interval", type=float, default=0.1, help="seconds between a writer's commits")
    a("--seconds", type=float, default=8.0, help="seconds of selections per fleet size")
    a("--selectors", type=int, default=2, help="selecting clients per instance")
    a("--gaussians", type=int, default=3000, help="Gaussians of a scale session")
    a("--endpoint", help="an S3 API already running (default: moto's server on loopback)")
    a("--bucket", default="agilegs-bench", help="its bucket (made on moto's server)")
    a("--json", dest="json_out", help="also write the results here")


def _say(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def _pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    v = sorted(values)
    return v[min(len(v) - 1, int(round(q * (len(v) - 1))))]


@contextmanager
def s3_server(bucket: str) -> Iterator[str]:
    """moto's S3 server (its server mode, which boto3 and s3fs test against) on 127.0.0.1 and
    a free port, with ``bucket`` made; its endpoint. Stopped on exit."""
    import httpx

    from agilegs.service.launch import free_port

    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p",
                             str(port)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            env={**os.environ, "MOTO_PORT": str(port)})
    endpoint = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                # a bucket is made by PUT /<bucket> (moto does not check signatures)
                if httpx.put(f"{endpoint}/{bucket}", timeout=2).status_code in (200, 409):
                    break
            except httpx.HTTPError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("moto's S3 server did not start (pip install 'moto[server]')")
            time.sleep(0.1)
        yield endpoint
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


class Fleet:
    """Instances of one fleet on ``url`` (each a :class:`~agilegs.service.launch.ServerProcess`)."""

    def __init__(self, root: Path, url: str, aws: dict[str, str], n: int,
                 env: dict[str, str] | None = None) -> None:
        from agilegs.service.launch import ServerProcess

        self.url = url
        self.aws = aws
        self.servers: list[Any] = []
        for i in range(n):
            connect = ",".join(s.zenoh_endpoint for s in self.servers)
            extra = {"AGILEGS_ZENOH_CONNECT": connect} if connect else {}
            self.servers.append(ServerProcess(
                root / f"i{i}", env={**aws, "AGILEGS_STATE_URL": url, "AGILEGS_INSTANCE_ID":
                                     f"i{i}", "AGILEGS_TORCH_THREADS": "1",
                                     "AGILEGS_MAPPER": "false", **extra, **(env or {})}))

    def start(self) -> Fleet:
        for srv in self.servers:
            srv.start()
        return self

    def stop(self) -> None:
        for srv in self.servers:
            if srv.proc is not None:
                srv.proc.send_signal(signal.SIGCONT)
            srv.stop()

    def owners(self) -> dict[str, str]:
        """session -> the owner its lease in the store names."""
        from agilegs.service.store.objects import ObjectSessionStore, open_store

        store = open_store(self.url)
        assert isinstance(store, ObjectSessionStore)
        out = {}
        for sid in store.session_ids():
            lease = store.lease(sid)
            if lease:
                out[sid] = str(lease.get("owner"))
        return out


def _environment(endpoint: str, ours: bool) -> dict[str, str]:
    """The ``AWS_*`` variables of the instances (this process reads the leases with them
    too): moto's made-up credentials, or for an S3 API of one's own those of the environment
    (inherited) and its endpoint."""
    aws = {"AWS_ENDPOINT_URL": endpoint}
    if ours:
        aws.update(AWS_ACCESS_KEY_ID="bench", AWS_SECRET_ACCESS_KEY="bench",
                   AWS_REGION="us-east-1")
    os.environ.update(aws)
    return aws


def _create(url: str, sid: str, *, pool: int, gaussians: int = 20,
            instance: str | None = None) -> None:
    import numpy as np

    from agilegs.client import Client

    from .bigmap import _sphere_poses

    with Client(url, timeout=120) as c:
        c.create_session(INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=gaussians,
                         pool=_sphere_poses(np.zeros(3), 2.0, pool), instance=instance)


# ============================================================================ kill
def _kill_phase(fleet: Fleet, args: argparse.Namespace) -> dict[str, Any]:
    import httpx

    from agilegs.client import Client

    servers = fleet.servers
    entry = [servers[0].url]  # where the writers send their requests (never the victim)
    sids = [f"w{k}" for k in range(args.sessions)]
    for sid in sids:
        _create(entry[0], sid, pool=400)
    acked: dict[str, set[int]] = {sid: set() for sid in sids}
    errors: list[str] = []
    stop = threading.Event()

    def writer(sid: str) -> None:
        clients: dict[str, Client] = {}
        cid = 0
        try:
            while not stop.is_set() and cid < 400:
                url = entry[0]
                c = clients.get(url) or clients.setdefault(url, Client(url, timeout=60))
                try:
                    c.commit(sid, candidate_id=cid)
                    acked[sid].add(cid)
                except Exception as exc:  # after the SDK's retries: visible to the client
                    errors.append(f"{sid}/{cid}: {type(exc).__name__}: {exc}")
                cid += 1
                stop.wait(args.interval)
        finally:
            for c in clients.values():
                c.close()

    threads = [threading.Thread(target=writer, args=(sid,), daemon=True) for sid in sids]
    for t in threads:
        t.start()
    takeovers: list[float] = []
    try:
        for k in range(args.kills):
            time.sleep(1.0)
            owners = fleet.owners()
            victim = max(servers, key=lambda s: sum(
                1 for o in owners.values() if o == s.env["AGILEGS_INSTANCE_ID"]))
            vid = victim.env["AGILEGS_INSTANCE_ID"]
            mine = [sid for sid, o in owners.items() if o == vid and sid in acked]
            entry[0] = next(s.url for s in servers if s is not victim)
            time.sleep(0.5)  # the writers' calls to the previous entry finish
            t0 = time.monotonic()
            victim.kill()
            left = set(mine)
            with httpx.Client(base_url=entry[0], timeout=10) as h:
                while left and time.monotonic() - t0 < 60:
                    for sid in sorted(left):
                        if h.get(f"/v1/sessions/{sid}").status_code == 200:
                            takeovers.append(time.monotonic() - t0)
                            left.discard(sid)
                    time.sleep(0.02)
            takeovers.extend([float("inf")] * len(left))
            worst = max(takeovers[-len(mine):]) if mine else 0.0
            _say(f"  kill {k + 1}: {vid} held {len(mine)} session(s) under writes; every one "
                 f"answered again within {worst:.2f} s")
            victim.start()
    finally:
        stop.set()
        for t in threads:
            t.join(timeout=120)
    lost, extra = 0, 0
    with Client(entry[0], timeout=60) as c:
        for sid in sids:
            present = {v.candidate_id for v in c.list_views(sid).views}
            lost += len(acked[sid] - present)
            extra += len(present - acked[sid])
    return {"sessions": len(sids), "kills": args.kills, "takeover_s": takeovers,
            "takeover_p50_s": _pct(takeovers, 0.5), "takeover_p99_s": _pct(takeovers, 0.99),
            "acked_writes": sum(len(a) for a in acked.values()), "acked_lost": lost,
            "unacked_present": extra, "client_errors": len(errors), "errors": errors[:5]}


# ============================================================================ pause
def _pause_phase(fleet: Fleet, args: argparse.Namespace) -> dict[str, Any]:
    import httpx

    sids = [f"p{k}" for k in range(args.sessions)]
    for sid in sids:
        _create(fleet.servers[0].url, sid, pool=50)
    owners = fleet.owners()
    victim = max(fleet.servers[1:] or fleet.servers, key=lambda s: sum(
        1 for sid in sids if owners.get(sid) == s.env["AGILEGS_INSTANCE_ID"]))
    vid = victim.env["AGILEGS_INSTANCE_ID"]
    mine = [sid for sid in sids if owners.get(sid) == vid]
    versions = {}
    with httpx.Client(timeout=30) as h:
        for sid in mine:
            versions[sid] = h.get(f"{fleet.servers[0].url}/v1/sessions/{sid}").json()["version"]
    t0 = time.monotonic()
    victim.proc.send_signal(signal.SIGSTOP)
    try:
        while time.monotonic() - t0 < 90:
            now = fleet.owners()
            if all(now.get(sid) != vid for sid in mine):
                break
            time.sleep(0.2)
        taken = time.monotonic() - t0
    finally:
        victim.proc.send_signal(signal.SIGCONT)
    statuses: list[int] = []
    codes: list[str] = []

    def stale_write(sid: str) -> None:
        r = httpx.post(f"{victim.url}/v1/sessions/{sid}/views", json={"candidate_id": 1},
                       timeout=60)
        statuses.append(r.status_code)
        if r.status_code != 200:
            codes.append(r.json()["error"]["code"])

    threads = [threading.Thread(target=stale_write, args=(sid,)) for sid in mine]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    time.sleep(3.0)
    through = 0
    now = fleet.owners()
    with httpx.Client(timeout=30) as h:
        for sid in mine:
            r = h.get(f"{fleet.servers[0].url}/v1/sessions/{sid}").json()
            # applied by the new owner: version + 1 under another owner; the stale owner's
            # own commit would have to replace the manifest: its id as the lease's owner
            if now.get(sid) == vid:
                through += 1
            assert r["version"] in (versions[sid], versions[sid] + 1)
    return {"paused": vid, "sessions": len(mine), "taken_over_after_s": taken,
            "stale_sent": len(mine), "fenced": codes.count("session_unavailable"),
            "forwarded": statuses.count(200), "writes_through": through,
            "logged_lost_lease": "lost the lease" in victim.log()}


# ============================================================================ scale
def _selector(url: str, sid: str, stop: threading.Event, lock: threading.Lock,
              count: list[int]) -> None:
    """Select (without commit) on ``sid`` until ``stop``, counting the answers."""
    import httpx

    with httpx.Client(base_url=url, timeout=120) as h:
        while not stop.is_set():
            if h.post(f"/v1/sessions/{sid}/select", json={}).status_code == 200:
                with lock:
                    count[0] += 1


def _scale_phase(root: Path, endpoint: str, aws: dict[str, str], bucket: str,
                 args: argparse.Namespace) -> dict[str, float]:

    out = {}
    for n in range(1, args.instances + 1):
        fleet = Fleet(root / f"scale{n}", f"s3://{bucket}/scale{n}", aws, n,
                      env={"AGILEGS_WORKERS": "1"}).start()
        try:
            sids = []
            for k in range(2 * n):
                sid = f"q{k}"
                _create(fleet.servers[k % n].url, sid, pool=64, gaussians=args.gaussians,
                        instance=f"i{k % n}")
                sids.append((fleet.servers[k % n].url, sid))
            count = [0]
            lock = threading.Lock()
            stop = threading.Event()
            threads = [threading.Thread(target=_selector, args=(*sids[k % len(sids)], stop,
                                                                 lock, count), daemon=True)
                       for k in range(args.selectors * n)]
            for t in threads:
                t.start()
            time.sleep(1.0)  # warm-up
            with lock:
                start = count[0]
            t0 = time.monotonic()
            time.sleep(args.seconds)
            with lock:
                done = count[0] - start
            rate = done / (time.monotonic() - t0)
            stop.set()
            for t in threads:
                t.join(timeout=120)
        finally:
            fleet.stop()
        out[str(n)] = rate
        _say(f"  {n} instance(s): {rate:.2f} selections/s")
    return out


# ============================================================================ main
def run(args: argparse.Namespace) -> int:
    phases = [p.strip() for p in args.phases.split(",") if p.strip()]
    logging.getLogger("httpx").setLevel(logging.WARNING)
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp, _store(args) as endpoint:
        root = Path(tmp)
        aws = _environment(endpoint, ours=not args.endpoint)
        if "kill" in phases or "pause" in phases:
            fleet = Fleet(root / "fleet", f"s3://{args.bucket}/fleet", aws,
                          args.instances).start()
            try:
                if "kill" in phases:
                    _say(f"kill: {args.sessions} sessions under writes, {args.kills} kills")
                    k = results["kill"] = _kill_phase(fleet, args)
                    _say(f"  takeover p50 {k['takeover_p50_s']:.2f} s, p99 "
                         f"{k['takeover_p99_s']:.2f} s ({len(k['takeover_s'])} takeovers)")
                    _say(f"  {k['acked_writes']} acknowledged writes, {k['acked_lost']} lost, "
                         f"{k['unacked_present']} present without an acknowledgement; "
                         f"{k['client_errors']} client-visible errors")
                if "pause" in phases:
                    p = results["pause"] = _pause_phase(fleet, args)
                    _say(f"pause: {p['paused']} paused holding {p['sessions']} session(s), all "
                         f"taken over after {p['taken_over_after_s']:.1f} s; resumed and sent "
                         f"{p['stale_sent']} writes: {p['fenced']} fenced, {p['forwarded']} "
                         f"forwarded to the new owner, {p['writes_through']} stale writes "
                         f"through; logged that it lost the lease: {p['logged_lost_lease']}")
            finally:
                fleet.stop()
        if "scale" in phases:
            _say(f"scale: selections/s, {args.selectors} clients per instance, one compute "
                 "thread each")
            results["scale"] = _scale_phase(root, endpoint, aws, args.bucket, args)
    results["targets"] = targets(results)
    _say("targets: " + ", ".join(f"{k} {'met' if v else 'MISSED'}"
                                  for k, v in results["targets"].items()))
    if args.json_out:
        Path(args.json_out).write_text(json.dumps(results, indent=2, default=str))
    return 0


@contextmanager
def _store(args: argparse.Namespace) -> Iterator[str]:
    if args.endpoint:
        yield args.endpoint
        return
    with s3_server(args.bucket) as endpoint:
        yield endpoint


def targets(results: dict[str, Any]) -> dict[str, bool]:
    """Whether each target of the fleet held (see the module docstring)."""
    out = {}
    k = results.get("kill")
    if k is not None:
        out["takeover p99 under 5 s"] = k["takeover_p99_s"] < 5.0
        out["no acknowledged write lost"] = k["acked_lost"] == 0
        out["no client-visible error"] = k["client_errors"] == 0
    p = results.get("pause")
    if p is not None:
        out["no stale write through"] = p["writes_through"] == 0 and p["logged_lost_lease"]
    s = results.get("scale")
    if s is not None and "2" in s:
        out["two instances at least 1.8x one"] = s["2"] >= 1.8 * s["1"]
    return out


if __name__ == "__main__":  # pragma: no cover
    p = argparse.ArgumentParser()
    add_arguments(p)
    raise SystemExit(run(p.parse_args()))

