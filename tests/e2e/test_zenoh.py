"""Zenoh against the shared server: same answers as HTTP, pub/sub, error replies.

Peers meet on a loopback TCP endpoint with multicast and gossip scouting off.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Iterator

import numpy as np
import pytest
from conftest import SMALL_INTRINSICS, ServerProcess, ring_poses

from agilegs.client import (
    Client,
    NotFoundError,
    ObservationIn,
    TransportError,
    ValidationError,
    ZenohClient,
)
from agilegs.schemas import ErrorBody, SelectResponse

BOUNDS = {"min": [-0.5] * 3, "max": [0.5] * 3}


@pytest.fixture(scope="module")
def zc(server: ServerProcess) -> Iterator[ZenohClient]:
    with ZenohClient([server.zenoh_endpoint], timeout=60) as z:
        yield z


def _session(c: Client, n: int = 16) -> str:
    sid = f"z-{uuid.uuid4().hex[:8]}"
    c.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=200,
                     pool=ring_poses(n), defaults={"shortlist_size": 5})
    return sid


def _comparable(r: SelectResponse) -> dict:
    d = r.model_dump(exclude={"latency_ms", "core_ms", "server_ms", "time"})
    return d


@pytest.mark.parametrize("method", ["random", "agile", "agile_plus", "cover"])
def test_zenoh_and_http_give_the_same_selection(server: ServerProcess, zc: ZenohClient,
                                                method: str) -> None:
    with Client(server.url) as c:
        sid = _session(c)
        c.commit(sid, 3)
        via_http = c.select(sid, method=method)
    via_zenoh = zc.select(sid, method=method)
    assert _comparable(via_zenoh) == _comparable(via_http)
    assert set(via_zenoh.latency_ms) == set(via_http.latency_ms)


def test_full_loop_over_zenoh(zc: ZenohClient) -> None:
    sid = f"z-{uuid.uuid4().hex[:8]}"
    info = zc.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=100)
    assert info.id == sid and zc.health().zenoh
    zc.set_pool(sid, ring_poses(10))
    assert zc.extend_pool(sid, ring_poses(2), ids=[50, 51]).ids()[-2:] == [50, 51]
    d = zc.select(sid, method="agile", commit=True)
    assert d.committed is not None
    zc.add_observations(sid, ObservationIn.from_numpy(
        view_id=d.committed.id, image=np.zeros((32, 32, 3), np.uint8)))
    views = zc.list_views(sid).views
    assert len(views) == 1 and views[0].has_image
    assert zc.get_pool(sid).ids().count(d.chosen.id) == 0
    assert zc.get_information(sid).arrays()["quats"].shape == (100, 4)
    assert zc.get_session(sid).num_views == 1
    assert sid in [s.id for s in zc.list_sessions().sessions]
    assert zc.delete_session(sid).deleted


def test_error_replies_map_like_http(server: ServerProcess, zc: ZenohClient) -> None:
    with Client(server.url) as c:
        sid = _session(c, 4)
        with pytest.raises(ValidationError) as via_http:
            c.select(sid, shortlist_size=0)
    with pytest.raises(ValidationError) as via_zenoh:
        zc.select(sid, shortlist_size=0)
    assert via_zenoh.value.field == via_http.value.field == "body.shortlist_size"
    assert via_zenoh.value.message == via_http.value.message
    with pytest.raises(NotFoundError):
        zc.commit(sid, 999)
    with pytest.raises(NotFoundError):
        zc.get_session("no-such-session")
    with pytest.raises(ValidationError):
        zc.get_session("bad/id")


def test_decisions_are_published_and_robot_topics_are_applied(
        server: ServerProcess, zc: ZenohClient) -> None:
    with Client(server.url) as c:
        sid = _session(c, 6)
    got: list[SelectResponse] = []
    errors: list[ErrorBody] = []
    arrived = threading.Event()

    def on_decision(r: SelectResponse) -> None:
        got.append(r)
        arrived.set()

    zc.subscribe_decisions(sid, on_decision)
    zc.subscribe_errors(sid, errors.append)
    time.sleep(0.3)  # let the subscriptions reach the server
    with Client(server.url) as c:
        r = c.select(sid, method="random")  # over HTTP: published on Zenoh too
        assert arrived.wait(10)
        assert got[0].chosen.id == r.chosen.id and got[0].session == sid

        zc.publish_pool(sid, ring_poses(9), ids=list(range(100, 109)))
        zc.publish_frames(sid, ObservationIn.from_numpy(ring_poses(3)[1]))
        bad = ring_poses(1)
        bad[0, 0, 0] = 3.0
        zc.publish_pool(sid, bad)  # refused: reported on the errors topic
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            if (c.get_pool(sid).ids() == list(range(100, 109))
                    and c.get_session(sid).num_views == 1 and errors):
                break
            time.sleep(0.05)
        assert c.get_pool(sid).ids() == list(range(100, 109))
        assert c.get_session(sid).num_views == 1
        assert errors and errors[0].error.status == 422
        assert errors[0].error.field == "body.poses[0].matrix"


def test_no_server_is_a_transport_error() -> None:
    from conftest import free_port

    with pytest.raises(TransportError):
        ZenohClient([f"tcp/127.0.0.1:{free_port()}"], wait=0.5)


def test_zenoh_queries_need_the_token(server_factory: object) -> None:
    from agilegs.client import AuthenticationError

    token = "s3cret-token"
    srv = server_factory(env={"AGILEGS_TOKEN": token}).start()  # type: ignore[operator]
    with pytest.raises(AuthenticationError):
        ZenohClient([srv.zenoh_endpoint], token="wrong")
    with ZenohClient([srv.zenoh_endpoint], token=token) as z:
        assert z.list_sessions().sessions == []
