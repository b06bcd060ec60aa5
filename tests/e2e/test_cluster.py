"""Several ``agilegs serve`` instances joined over Zenoh (service/transports/zenoh/cluster.py).

Two real server processes with their own state folders, joined on loopback endpoints with scouting off (B connects to A's
listener), are driven by one Zenoh client that knows only A's endpoint and by one HTTP client
per instance: sessions created on each are found and selected through either, a killed
instance's sessions fail with a clear error while the other's keep working, and restarting
it on the same state folder brings them back.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import SMALL_INTRINSICS, ServerProcess, ring_poses

from agilegs.client import (
    Client,
    ConflictError,
    NotFoundError,
    SessionUnavailableError,
    ValidationError,
    ZenohClient,
)
from agilegs.schemas import ObservationIn, SelectResponse
from agilegs.schemas.keys import instances_wildcard, parse_instance_key

BOUNDS = {"min": [-0.5] * 3, "max": [0.5] * 3}


# ============================================================================ two processes
class Pair:
    def __init__(self, a: ServerProcess, b: ServerProcess, zc: ZenohClient) -> None:
        self.a, self.b, self.zc = a, b, zc

    def owner_dir(self, sid: str) -> str:
        """Which instance's state folder holds ``sid``."""
        where = [name for name, srv in (("a", self.a), ("b", self.b))
                 if (srv.state_dir / "sessions" / sid).is_dir()]
        assert len(where) == 1, (sid, where)
        return where[0]


def _start_all(*servers: ServerProcess) -> None:
    errors: list[BaseException] = []

    def go(srv: ServerProcess) -> None:
        try:
            srv.start()
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=go, args=(s,)) for s in servers]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Pair]:
    root = tmp_path_factory.mktemp("cluster")
    a = ServerProcess(root / "a", env={"AGILEGS_INSTANCE_ID": "a"})
    b = ServerProcess(root / "b", env={"AGILEGS_INSTANCE_ID": "b",
                                       "AGILEGS_ZENOH_CONNECT": a.zenoh_endpoint})
    try:
        _start_all(a, b)
        # a Zenoh *client* that knows one endpoint, as a robot knows its router's
        with ZenohClient([a.zenoh_endpoint], mode="client", timeout=60) as zc:
            _until(lambda: _instances(zc) == {"a", "b"}, "both instances visible")
            yield Pair(a, b, zc)
    finally:
        b.stop()
        a.stop()


def _until(check: Callable[[], Any], what: str, timeout: float = 20.0) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        try:
            got = check()
            if got:
                return got
        except Exception:
            if time.monotonic() > deadline:
                raise
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for: {what}")
        time.sleep(0.1)


def _instances(zc: ZenohClient) -> set[str]:
    import zenoh

    replies = zc._session.get(instances_wildcard("health"), timeout=5,
                              consolidation=zenoh.ConsolidationMode.NONE)
    return {parse_instance_key(str(r.ok.key_expr))[0] for r in replies if r.ok is not None}


def _new(c: Client | ZenohClient, sid: str | None = None, **kwargs: Any) -> str:
    info = c.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=150,
                            pool=ring_poses(12), defaults={"shortlist_size": 4}, **kwargs)
    return info.id


def _comparable(r: SelectResponse) -> dict[str, Any]:
    return r.model_dump(exclude={"latency_ms", "core_ms", "server_ms", "time"})


def test_sessions_created_on_each_are_found_and_selected_through_either(pair: Pair) -> None:
    zc = pair.zc
    with Client(pair.a.url) as ca, Client(pair.b.url) as cb:
        # the policy: fewest sessions, ties by the smallest id
        s1 = _new(ca)                  # a: 0, b: 0 -> a
        s2 = _new(ca)                  # a: 1, b: 0 -> b (forwarded by a)
        s3 = _new(cb, "made-on-b")     # a: 1, b: 1 -> a (placed by b)
        s4 = _new(zc, instance="b")    # explicit, over Zenoh
        s5 = _new(ca, instance="b")    # explicit, over HTTP on the other instance (?instance=b)
        s6 = _new(zc)                  # @service: the coordinator (a) places it: a 2, b 3 -> a
        owners = {sid: pair.owner_dir(sid) for sid in (s1, s2, s3, s4, s5, s6)}
        assert owners == {s1: "a", s2: "b", s3: "a", s4: "b", s5: "b", s6: "a"}

        every = {s1, s2, s3, s4, s5, s6}  # each created exactly once (one coordinator)
        for c in (ca, cb, zc):
            listed = [s.id for s in c.list_sessions().sessions]
            assert sorted(listed) == sorted(every)
        assert ca.health().sessions == 3 and cb.health().sessions == 3  # per instance

        for sid in (s1, s2):  # each instance's session, through every client
            ca.commit(sid, 0)
            picks = [_comparable(c.select(sid, method="agile")) for c in (ca, cb, zc)]
            assert picks[0] == picks[1] == picks[2]
            assert zc.get_session(sid).num_views == cb.get_session(sid).num_views == 1

        # bodies are re-encoded on the way: a JSON request with an image (base64) to a,
        # forwarded as msgpack to b
        with Client(pair.a.url, encoding="json") as ja:
            img = np.arange(32 * 32 * 3, dtype=np.uint8).reshape(32, 32, 3)
            out = ja.add_observations(s2, ObservationIn.from_numpy(ring_poses(3)[1], image=img))
        assert out.views[0].has_image and cb.list_views(s2).views[-1].has_image

        # the owner's refusals come back as they are
        with pytest.raises(ValidationError) as bad:
            ca.select(s2, shortlist_size=0)
        assert bad.value.field == "body.shortlist_size"
        with pytest.raises(ConflictError) as missing:
            ca.commit(s2, 999)  # no such candidate in the owner's pool
        assert "999" in missing.value.message
        with pytest.raises(ConflictError):
            _new(ca, s2)               # the id is taken on b
        with pytest.raises(NotFoundError) as nobody:
            _new(zc, instance="nobody")
        assert nobody.value.code == "instance_unavailable"

        # a selection forwarded by a is decided, and published once, by its owner b
        got: list[SelectResponse] = []
        zc.subscribe_decisions(s2, got.append)
        time.sleep(0.3)
        d = ca.select(s2, method="random", seed=3)
        _until(lambda: got, "the decision")
        time.sleep(0.3)
        assert [g.chosen.id for g in got] == [d.chosen.id]

        # robot topics reach the owner through the instance the client knows
        zc.publish_pool(s2, ring_poses(5), ids=[70, 71, 72, 73, 74])
        _until(lambda: cb.get_pool(s2).ids() == [70, 71, 72, 73, 74], "the published pool")

        # deleting through the other instance removes it everywhere
        assert ca.delete_session(s5).deleted
        assert not (pair.b.state_dir / "sessions" / s5).exists()
        with pytest.raises(SessionUnavailableError):
            zc.get_session(s5)
        with pytest.raises(SessionUnavailableError):
            ca.get_session(s5)


def test_the_map_and_frames_of_another_instance_s_session_leave_as_files(
        pair: Pair, tmp_path: Path) -> None:
    with Client(pair.a.url) as ca, Client(pair.b.url) as cb:
        sid = _new(ca, instance="b")
        img = np.arange(32 * 32 * 3, dtype=np.uint8).reshape(32, 32, 3)
        cb.add_observations(sid, ObservationIn.from_numpy(ring_poses(3)[1], image=img))
        cb.save_gaussians(sid, tmp_path / "owner.ply")
        ca.save_gaussians(sid, tmp_path / "through-a.ply")  # forwarded, made a file on a
        pair.zc.save_gaussians(sid, tmp_path / "zenoh.ply")
        frames = ca.get_frames(sid)
    owner = (tmp_path / "owner.ply").read_bytes()
    assert owner.startswith(b"ply\n") and owner == (tmp_path / "through-a.ply").read_bytes()
    assert owner == (tmp_path / "zenoh.ply").read_bytes()
    assert np.array_equal(frames.frames[-1].image.to_numpy(), img)


def test_the_decisions_feed_is_read_through_any_instance(pair: Pair) -> None:
    zc = pair.zc
    with Client(pair.a.url) as ca, Client(pair.b.url) as cb:
        sid = _new(zc, instance="b")
        made = [ca.select(sid, method="random", seed=i) for i in range(2)]  # forwarded to b
        # a long poll through a is forwarded to b with its wait, and wakes on the decision
        later = threading.Timer(0.5, lambda: made.append(
            cb.select(sid, method="random", seed=7)))
        later.start()
        t0 = time.monotonic()
        waited = ca.get_decisions(sid, after=2, wait=20)
        assert time.monotonic() - t0 < 15
        later.join(30)
        assert [e.seq for e in waited.decisions] == [3]
        for c in (ca, cb, zc):  # the one log of the owner, whoever asks
            out = c.get_decisions(sid)
            assert [e.seq for e in out.decisions] == [1, 2, 3] and out.epoch == waited.epoch
            assert [e.decision.chosen.id for e in out.decisions] == [d.chosen.id for d in made]


@pytest.mark.heavy
def test_a_killed_instance_fails_clearly_and_comes_back(pair: Pair) -> None:
    zc = pair.zc
    with Client(pair.a.url) as ca:
        on_a = _new(zc, instance="a")
        on_b = _new(zc, instance="b")
        zc.commit(on_b, 2)
        before = zc.get_session(on_b)

        pair.b.kill()  # SIGKILL: no shutdown code runs
        _until(lambda: _instances(zc) == {"a"}, "b gone")
        with pytest.raises(SessionUnavailableError) as via_zenoh:
            zc.get_session(on_b)
        assert f"no instance answers for session {on_b!r}" in str(via_zenoh.value)
        with pytest.raises(SessionUnavailableError) as via_http:
            ca.select(on_b)
        assert (via_http.value.status, via_http.value.code) == (404, "session_unavailable")
        assert on_b in via_http.value.message
        assert via_http.value.message.endswith("(live instances: a)")
        # a's sessions keep working, over both transports
        assert zc.select(on_a, method="agile").chosen is not None
        assert ca.select(on_a, method="random").chosen is not None
        assert on_b not in {s.id for s in ca.list_sessions().sessions}

        # an instance whose id is taken by a live one refuses to start
        twin = ServerProcess(pair.b.state_dir.parent / "twin", env={
            "AGILEGS_INSTANCE_ID": "a", "AGILEGS_ZENOH_CONNECT": pair.a.zenoh_endpoint})
        with pytest.raises(RuntimeError, match="instance id 'a' is taken"):
            twin.start()

        pair.b.start()  # same state folder, same ports
        back = _until(lambda: zc.get_session(on_b), "b's session back")
        assert (back.version, back.num_views, back.pool_size) == (
            before.version, before.num_views, before.pool_size)
        assert ca.select(on_b, method="agile", commit=True).committed is not None
        assert zc.get_session(on_b).num_views == 2
