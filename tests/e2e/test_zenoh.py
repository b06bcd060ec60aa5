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
    BadRequestError,
    Client,
    ConflictError,
    NotFoundError,
    TransportError,
    ValidationError,
    ZenohClient,
)
from agilegs.schemas import ErrorBody, ObservationIn, SelectResponse

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


@pytest.mark.parametrize("method", ["random", "spread", "agile", "agile_plus", "cover",
                                    "agile_plus@target"])
def test_zenoh_and_http_give_the_same_selection(server: ServerProcess, zc: ZenohClient,
                                                method: str) -> None:
    method, _, objective = method.partition("@")
    extra: dict = {}
    if objective:  # the target objective, with the request's own targets
        extra = {"config": {"objective": objective, "target_views": 2},
                 "targets": ring_poses(5)[[0, 2]]}
    with Client(server.url) as c:
        sid = _session(c)
        c.commit(sid, 3)
        via_http = c.select(sid, method=method, **extra)
    via_zenoh = zc.select(sid, method=method, **extra)
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
    with pytest.raises(ConflictError):
        zc.commit(sid, 999)  # no such candidate: the session's state refuses it
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


def test_no_peer_is_told_within_the_timeout_with_what_is_likely_wrong() -> None:
    from conftest import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    t0 = time.monotonic()
    with pytest.raises(TransportError) as exc:
        ZenohClient([endpoint], timeout=1.5)  # wait (10 s by default) stays within timeout
    assert time.monotonic() - t0 < 3.0
    msg = str(exc.value)
    assert f"no Zenoh peer reached at {endpoint}" in msg and "credentials" in msg


def test_zenoh_queries_need_the_token(server_factory: object) -> None:
    from agilegs.client import AuthenticationError

    token = "s3cret-token"
    srv = server_factory(env={"AGILEGS_TOKEN": token}).start()  # type: ignore[operator]
    creds = srv.zenoh_credentials  # made by the server, with a token, on its first start
    assert creds is not None and oct(creds.stat().st_mode & 0o777) == "0o600"
    with pytest.raises(TransportError):  # no Zenoh credentials: no session with the server
        ZenohClient([srv.zenoh_endpoint], token=token, wait=1.0, timeout=2.0)
    with pytest.raises(AuthenticationError):
        ZenohClient([srv.zenoh_endpoint], token="wrong", credentials=creds)
    with ZenohClient(token=token, credentials=creds) as z:  # the endpoints from the file too
        assert z.list_sessions().sessions == []


def _refusal(ans: object) -> dict:
    from agilegs.client.zenoh_rpc import Answer

    assert isinstance(ans, Answer) and not ans.ok, ans
    return ErrorBody.model_validate(ans.load()).model_dump()["error"]


def _http_refusal(r: object) -> dict:
    import httpx
    import msgpack

    assert isinstance(r, httpx.Response) and r.status_code >= 400, r
    return ErrorBody.model_validate(msgpack.unpackb(r.content)).model_dump()["error"]


def test_zenoh_refusals_match_http_and_change_nothing(server_factory: object) -> None:
    """Every queryable answers a malformed, oversized, unauthenticated, wrongly encoded or
    unknown-operation query with the error body HTTP gives, and nothing refused changes a
    session."""
    import httpx

    from agilegs.client.zenoh_rpc import credentials, first_answer, open_session, read_credentials
    from agilegs.schemas import OPERATIONS, keys

    token = "audit-token"
    srv = server_factory(env={"AGILEGS_TOKEN": token, "AGILEGS_MAX_BODY_BYTES": "4096"}
                         ).start()  # type: ignore[operator]
    auth = f"Bearer {token}".encode()
    c = Client(srv.url, token=token)
    sid = _session(c, 4)
    c.commit(sid, 1)

    def state() -> tuple:
        info = c.get_session(sid)
        return (info.version, info.information.digest, c.get_pool(sid).ids(),
                [v.id for v in c.list_views(sid).views], len(c.list_sessions().sessions))

    before = state()
    http = httpx.Client(base_url=srv.url, headers={"accept": "application/msgpack"})
    saved = read_credentials(srv.zenoh_credentials)
    z = open_session(connect=[srv.zenoh_endpoint], extra=credentials(
        user=saved["user"], password=saved["password"]))
    try:
        def ask(key: str, payload: bytes | None = None, attachment: bytes | None = auth,
                encoding: str = "application/msgpack") -> dict:
            ans, _ = first_answer(z, key, timeout=20, payload=payload, attachment=attachment,
                                  encoding=encoding)
            return _refusal(ans)

        def http_call(op: object, content: bytes | None = None, token_ok: bool = True,
                      content_type: str = "application/msgpack") -> dict:
            path = op.http_path.replace("{session}", sid)  # type: ignore[attr-defined]
            headers = {"content-type": content_type}
            if token_ok:
                headers["authorization"] = f"Bearer {token}"
            return _http_refusal(http.request(op.http_method, path,  # type: ignore[attr-defined]
                                              content=content, headers=headers))

        checked = 0
        for op in OPERATIONS.values():
            key = (keys.session_key(sid, op.name) if op.scope == "session"
                   else keys.service_key(op.name))
            # no token: 401 on every queryable, the same body as HTTP but for where it travels
            z401, h401 = ask(key, attachment=None), http_call(op, token_ok=False)
            assert (z401["status"], z401["code"]) == (h401["status"], h401["code"]) == (
                401, "unauthorized")
            assert z401["field"] == "attachment" and h401["field"] == "header.authorization"
            if op.request is None:
                continue
            # malformed, oversized and wrongly encoded bodies: the very same body as HTTP
            for payload, encoding, status in ((b"\xc1\x00", "application/msgpack", 400),
                                              (b"\x90" * 5000, "application/msgpack", 413),
                                              (b"{}", "text/plain", 415)):
                zr = ask(key, payload, encoding=encoding)
                assert zr["status"] == status, (op.name, zr)
                if not op.query:  # over HTTP a query operation's request is its query string
                    hr = http_call(op, payload, content_type=encoding)
                    assert zr == hr, (op.name, zr, hr)
                checked += 1
            # valid msgpack, schema-invalid body: the same 422 naming the field
            zr = ask(key, b"\x81\xa5bogus\x01")
            assert zr["status"] == 422, (op.name, zr)
            if not op.query:
                hr = http_call(op, b"\x81\xa5bogus\x01")
                assert zr == hr, (op.name, zr, hr)
        assert checked == 3 * sum(op.request is not None for op in OPERATIONS.values())
        # an unknown operation, or a service operation under a session's key: 404
        for name in ("no_such_op", "create_session", "health", keys.FRAMES):
            zr = ask(f"{keys.PREFIX}/{sid}/{name}", b"\x80")
            assert (zr["status"], zr["code"], zr["field"]) == (404, "not_found", "key"), zr
        assert state() == before  # nothing refused changed anything
    finally:
        z.close()
        http.close()
        c.close()


def test_zenoh_saves_the_map_as_http_does(server: ServerProcess, zc: ZenohClient,
                                          tmp_path) -> None:
    from agilegs.client.zenoh_rpc import first_answer
    from agilegs.schemas import keys

    with Client(server.url) as c:
        sid = _session(c)
        for suffix in ("ply", "splat"):
            c.save_gaussians(sid, tmp_path / f"http.{suffix}")
            zc.save_gaussians(sid, tmp_path / f"zenoh.{suffix}")
            assert (tmp_path / f"zenoh.{suffix}").read_bytes() == (
                tmp_path / f"http.{suffix}").read_bytes()
    assert (tmp_path / "zenoh.ply").read_bytes().startswith(b"ply\n")
    ans, _ = first_answer(zc._session, keys.session_key(sid, "get_gaussians"),
                          parameters="format=obj", timeout=30)
    assert ans is not None and not ans.ok
    assert ErrorBody.model_validate(ans.load()).error.field == "query.format"


def test_a_write_sent_again_over_zenoh_with_its_request_id_is_applied_once(
        server: ServerProcess, zc: ZenohClient) -> None:
    from dataclasses import replace

    from agilegs.client import _requests as rq

    with Client(server.url) as c:
        sid = _session(c, 6)
        deadline = time.monotonic() + 20
        while True:  # the session's queryable reaches this client
            try:
                zc.get_session(sid)
                break
            except NotFoundError:
                assert time.monotonic() < deadline
                time.sleep(0.05)
        once = replace(rq.commit(sid, 2), request_id="zenoh-commit-01")
        first = zc._send(once)
        assert zc._send(once) == first
        assert c.get_session(sid).num_views == 1
        with pytest.raises(BadRequestError) as bad:
            zc._send(replace(rq.commit(sid, 3), request_id="bad id"))
        assert bad.value.field == "query.request_id" and bad.value.status == 400
