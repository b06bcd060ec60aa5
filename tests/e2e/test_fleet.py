"""A fleet on a real S3 API: three ``agilegs serve`` processes keeping their sessions in one
object store (moto's server on loopback), driven from outside with the client SDK."""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import httpx
import pytest
from conftest import SMALL_INTRINSICS, ServerProcess, ring_poses
from s3api import S3Api, s3_api

from agilegs.client import (
    Client,
    ConflictError,
    NotFoundError,
    SessionUnavailableError,
    ZenohClient,
)

BOUNDS = {"min": [-0.5] * 3, "max": [0.5] * 3}


@pytest.fixture(scope="module")
def api() -> Iterator[S3Api]:
    with s3_api() as running:
        yield running


def start_fleet(api: S3Api, root: Path, prefix: str, n: int = 3, *, zenoh: bool = False,
                env: dict[str, str] | None = None) -> list[ServerProcess]:
    servers = []
    for i in range(n):
        srv = ServerProcess(root / f"local-{i}", zenoh=zenoh,
                            env={**api.env, "AGILEGS_STATE_URL": api.url(prefix),
                                 "AGILEGS_INSTANCE_ID": f"i{i}", **(env or {})})
        servers.append(srv.start())
    return servers


def test_100_concurrent_creations_of_one_id_on_three_instances_make_one(
        api: S3Api, tmp_path: Path) -> None:
    servers = start_fleet(api, tmp_path, "race")
    try:
        outcomes: list[int] = []
        gate = threading.Barrier(100)
        body = {"id": "same", "intrinsics": SMALL_INTRINSICS, "bounds": BOUNDS,
                "init_gaussians": 20}

        def attempt(url: str) -> None:
            with httpx.Client(base_url=url, timeout=60) as http:
                gate.wait()
                outcomes.append(http.post("/v1/sessions", json=body).status_code)

        threads = [threading.Thread(target=attempt, args=(servers[i % 3].url,))
                   for i in range(100)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert sorted(set(outcomes)) == [200, 409] and outcomes.count(200) == 1, outcomes
        # the winner's session is whole in the store: a fresh instance loads it
        late = start_fleet(api, tmp_path / "late", "race", 1)[0]
        try:
            with Client(late.url) as c:
                assert [s.id for s in c.list_sessions().sessions] == ["same"]
                assert c.get_session("same").version == 1
                with pytest.raises(ConflictError):
                    c.create_session(SMALL_INTRINSICS, id="same", bounds=BOUNDS)
        finally:
            late.stop()
    finally:
        for srv in servers:
            srv.stop()


def start_mesh(api: S3Api, root: Path, prefix: str, n: int = 3) -> list[ServerProcess]:
    """``n`` instances of one fleet, Zenoh peers each connected to the ones before it."""
    servers: list[ServerProcess] = []
    for i in range(n):
        connect = ",".join(s.zenoh_endpoint for s in servers)
        srv = ServerProcess(root / f"local-{i}",
                            env={**api.env, "AGILEGS_STATE_URL": api.url(prefix),
                                 "AGILEGS_INSTANCE_ID": f"i{i}",
                                 **({"AGILEGS_ZENOH_CONNECT": connect} if connect else {})})
        servers.append(srv.start())
    return servers


def until(check: Callable[[], bool], what: str, timeout: float = 30.0) -> float:
    """Seconds until ``check()`` holds (AssertionError after ``timeout``)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        try:
            if check():
                return time.monotonic() - t0
        except Exception:
            pass
        time.sleep(0.05)
    raise AssertionError(f"not within {timeout} s: {what}")


def version_on(url: str, sid: str) -> int | None:
    r = httpx.get(f"{url}/v1/sessions/{sid}", timeout=10)
    return r.json()["version"] if r.status_code == 200 else None


def test_a_killed_owners_sessions_are_taken_over_and_a_paused_one_is_fenced(
        api: S3Api, tmp_path: Path) -> None:
    servers = start_mesh(api, tmp_path, "takeover")
    a, b, c = servers
    try:
        with Client(a.url) as ca:
            for k in range(4):
                ca.create_session(SMALL_INTRINSICS, id=f"s{k}", bounds=BOUNDS,
                                  init_gaussians=20, instance="i0",
                                  pool=ring_poses(6))
                ca.commit(f"s{k}", candidate_id=1)
        # a commit whose answer is lost, sent again after its owner died: applied once
        key = {"Idempotency-Key": "fleet-commit-0001"}
        first = httpx.post(f"{a.url}/v1/sessions/s0/views", json={"candidate_id": 3},
                           headers=key, timeout=30)
        assert first.status_code == 200, first.text
        acked = {f"s{k}": 3 if k == 0 else 2 for k in range(4)}
        with Client(b.url) as cb:  # what the store does not hold fails at once: no retries
            t0 = time.monotonic()
            with pytest.raises(NotFoundError) as missing:
                cb.get_session("never-made")
            assert not isinstance(missing.value, SessionUnavailableError)
            assert time.monotonic() - t0 < 5
        for sid, version in acked.items():  # every instance reaches every session
            assert version_on(b.url, sid) == version and version_on(c.url, sid) == version
        with ZenohClient([c.zenoh_endpoint], mode="client", timeout=30) as zc:
            a.kill()
            t0 = time.monotonic()
            # the clients ride through the takeover (their retry window), then everything
            # acknowledged is there
            with Client(b.url) as cb:
                assert {sid: cb.get_session(sid).version for sid in acked} == acked
            assert {sid: zc.get_session(sid).version for sid in acked} == acked
            assert time.monotonic() - t0 < 10
        again = httpx.post(f"{b.url}/v1/sessions/s0/views", json={"candidate_id": 3},
                           headers=key, timeout=30)
        assert again.status_code == 200 and again.json() == first.json(), again.text
        assert version_on(c.url, "s0") == acked["s0"]  # the new owner applied nothing
        owners = {sid: _owner(api, sid) for sid in acked}
        assert set(owners.values()) <= {"i1", "i2"}, owners  # taken over, epoch 2
        assert all(_epoch(api, sid) == 2 for sid in acked)
        # a paused owner: its sessions are taken over; resumed, it writes nothing
        victim = next(s for s in (b, c) if any(o == ("i1" if s is b else "i2")
                                              for o in owners.values()))
        other = c if victim is b else b
        mine = [sid for sid, o in owners.items() if o == ("i1" if victim is b else "i2")]
        assert victim.proc is not None
        victim.proc.send_signal(signal.SIGSTOP)
        try:
            until(lambda: all(_owner(api, sid) != ("i1" if victim is b else "i2")
                              for sid in mine), "the paused owner's sessions taken", 40)
        finally:
            victim.proc.send_signal(signal.SIGCONT)
        stale = httpx.post(f"{victim.url}/v1/sessions/{mine[0]}/views",
                           json={"candidate_id": 2}, timeout=30)
        # either it noticed on resuming and forwards to the new owner (200: the new owner
        # applied it), or it tries itself, is fenced and says so: its own write never lands
        assert stale.status_code in (200, 404), stale.text
        if stale.status_code == 404:
            assert stale.json()["error"]["code"] == "session_unavailable", stale.text
        until(lambda: "lost the lease" in victim.log(), "the paused owner logs its loss", 20)
        want = acked[mine[0]] + (1 if stale.status_code == 200 else 0)
        assert version_on(other.url, mine[0]) == want
        for sid in mine[1:]:
            assert version_on(other.url, sid) == acked[sid]
        assert _owner(api, mine[0]) != ("i1" if victim is b else "i2")
    finally:
        for srv in servers:
            srv.stop()


def _manifest(api: S3Api, sid: str) -> dict:
    import os

    from agilegs.service.store.blobs import open_blobs
    from agilegs.service.store.integrity import decode_manifest

    old = {k: os.environ.get(k) for k in api.env}
    os.environ.update(api.env)
    try:
        data, _ = open_blobs(api.url("takeover")).get(f"sessions/{sid}/manifest.json")
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return decode_manifest(data)


def _owner(api: S3Api, sid: str) -> str:
    return str(_manifest(api, sid)["lease"]["owner"])


def _epoch(api: S3Api, sid: str) -> int:
    return int(_manifest(api, sid)["lease"]["epoch"])
