"""The gateway does each piece of work once: a request for a session another instance owns
goes to it as it came and its answer comes back as it came; a decision's reply and its
publication share one encoding."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from conftest import SMALL_INTRINSICS, call, ring_poses

from agilegs import schemas as m
from agilegs.schemas import ErrorBody, ErrorInfo, codec
from agilegs.service.sessions.registry import SessionRegistry
from agilegs.service.settings import Settings
from agilegs.service.transports.gateway import Forwarded, Gateway, Request

VIEW = m.View(id=4, pose=m.Pose.from_matrix(ring_poses(1)[0]), candidate_id=2, intrinsics=None,
              has_image=False, has_depth=False, created_at=1.0)


class Router:
    """A cluster in which session ``remote`` lives on another instance."""

    def __init__(self, answer: Forwarded | None) -> None:
        self.answer = answer
        self.sent: list[tuple[str, str, bytes | None, str]] = []
        self.routed: list[tuple[str, bool]] = []
        self.request_ids: list[str | None] = []

    def owned_elsewhere(self, op: str, session: str | None) -> bool:
        return session == "remote"

    def forward_bytes(self, op: str, session: str, body: bytes | None, kind: str,
                      request_id: str | None = None) -> Forwarded | None:
        self.sent.append((op, session, body, kind))
        self.request_ids.append(request_id)
        return self.answer

    def route(self, op: str, session: str | None, req: Any, *, run_local: Any,
              instance: str | None, local: bool, request_id: str | None = None) -> Any:
        self.routed.append((op, local))
        return run_local()


@pytest.fixture
def gateway(tmp_path: Path) -> Any:
    reg = SessionRegistry(Settings(state_dir=tmp_path / "state", zenoh=False, workers=2,
                                   mapper=False))
    reg.load()
    gw = Gateway(reg, reg.settings)
    yield gw
    gw.close()
    reg.close()


def test_a_request_for_another_instance_s_session_goes_and_comes_back_as_it_came(
        gateway: Gateway) -> None:
    answer = codec.dump(VIEW, codec.MSGPACK)
    gateway.router = router = Router(Forwarded(True, answer, codec.MSGPACK))
    body = b"\xc1 not even msgpack"  # the owner decodes it, not this instance
    reply = gateway.handle(Request(op="commit", session="remote", body=body,
                                   content_type=codec.MSGPACK, accept=codec.MSGPACK,
                                   request_id="r-0123456789"))
    assert reply.status == 200 and reply.body is answer and reply.media_type == codec.MSGPACK
    assert router.sent == [("commit", "remote", body, codec.MSGPACK)] and router.routed == []
    assert router.request_ids == ["r-0123456789"]  # the owner applies it once
    assert reply.model == VIEW  # decoded only for a caller that reads it
    # no body: the answer is asked in the type the caller accepts
    reply = gateway.handle(Request(op="get_session", session="remote", accept=codec.JSON))
    assert router.sent[-1] == ("get_session", "remote", None, codec.JSON)


def test_the_owner_s_error_comes_back_with_its_status(gateway: Gateway) -> None:
    err = ErrorBody(error=ErrorInfo(status=409, code="conflict", message="candidate 9 is not "
                                    "in the pool", field="body.candidate_id"))
    payload = codec.dump(err, codec.JSON)
    gateway.router = Router(Forwarded(False, payload, codec.JSON))
    reply = gateway.handle(Request(op="commit", session="remote", body=b'{"candidate_id": 9}',
                                   content_type=codec.JSON, accept=codec.JSON))
    assert (reply.status, reply.body) == (409, payload)
    assert reply.error is not None and reply.error.field == "body.candidate_id"
    # asked in the other type: the same error, re-encoded
    reply = gateway.handle(Request(op="commit", session="remote", body=b'{"candidate_id": 9}',
                                   content_type=codec.JSON, accept=codec.MSGPACK))
    got = ErrorBody.model_validate(codec.load(reply.body, codec.MSGPACK))
    assert reply.status == 409 and got == err


def test_an_answer_in_the_other_type_is_converted(gateway: Gateway) -> None:
    gateway.router = Router(Forwarded(True, codec.dump(VIEW, codec.JSON), codec.JSON))
    reply = gateway.handle(Request(op="commit", session="remote", body=b'{"candidate_id": 2}',
                                   content_type=codec.JSON, accept=codec.MSGPACK))
    assert reply.status == 200
    assert m.View.model_validate(codec.load(reply.body, codec.MSGPACK)) == VIEW


def test_what_cannot_go_as_it_came_is_validated_here(gateway: Gateway) -> None:
    router = Router(None)
    gateway.router = router
    # fields in query parameters: validated here, routed as a model
    reply = gateway.handle(Request(op="get_decisions", session="remote",
                                   params={"after": "x"}, accept=codec.JSON))
    assert reply.status == 422 and router.sent == []
    # nobody answers on a lone server: it answers itself (once asked, run here)
    reply = gateway.handle(Request(op="get_session", session="remote", accept=codec.JSON))
    assert reply.status == 404 and len(router.sent) == 1
    assert router.routed == [("get_session", True)]  # the 422 came before any routing
    # a session held here is not forwarded
    reply = gateway.handle(Request(op="get_session", session="local", accept=codec.JSON))
    assert reply.status == 404 and len(router.sent) == 1
    assert router.routed[-1] == ("get_session", False)


def test_a_decision_and_its_publication_share_one_encoding(gateway: Gateway) -> None:
    call(gateway.registry, "create_session", None, {
        "id": "s", "intrinsics": SMALL_INTRINSICS, "init_gaussians": 50,
        "bounds": {"min": [-0.5] * 3, "max": [0.5] * 3},
        "pool": {"poses": [{"matrix": p.tolist()} for p in ring_poses(6)]}})
    published: list[bytes] = []
    gateway.decision_hooks.append(
        lambda sid, resp: published.append(gateway.encode(resp, codec.MSGPACK)))
    reply = gateway.handle(Request(op="select", session="s", body=b'{"method": "random"}',
                                   content_type=codec.JSON, accept=codec.MSGPACK))
    assert reply.status == 200 and published and reply.body is published[0]
    reply = gateway.handle(Request(op="select", session="s", body=b'{"method": "random"}',
                                   content_type=codec.JSON, accept=codec.JSON))
    assert reply.status == 200 and len(published) == 2 and reply.body is not published[1]
    assert m.SelectResponse.model_validate_json(reply.body).chosen == m.SelectResponse(
        **codec.load(published[1], codec.MSGPACK)).chosen
