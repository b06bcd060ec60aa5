"""The client SDK without a server: encoding, error mapping, torch-free import."""

from __future__ import annotations

import asyncio
import json

import httpx
import msgpack
import numpy as np
import pytest

from agilegs.client import (
    APIError,
    AsyncClient,
    AuthenticationError,
    BadRequestError,
    Client,
    ConflictError,
    NotFoundError,
    PayloadTooLargeError,
    ProtocolError,
    ServerError,
    TooManyError,
    TransportError,
    ValidationError,
)
from agilegs.schemas import codec

INTR = {"fx": 10.0, "fy": 10.0, "cx": 4.0, "cy": 4.0, "width": 8, "height": 8}


def _error(status: int, code: str, field: str | None = "body.x") -> dict:
    return {"error": {"status": status, "code": code, "message": f"{code} happened",
                      "field": field, "errors": [{"field": field, "message": "why"}]}}


@pytest.mark.parametrize(
    "status, cls",
    [(400, BadRequestError), (401, AuthenticationError), (404, NotFoundError),
     (406, BadRequestError), (409, ConflictError), (413, PayloadTooLargeError),
     (415, BadRequestError), (422, ValidationError), (429, TooManyError), (500, ServerError),
     (503, ServerError)],
)
@pytest.mark.parametrize("kind", [codec.JSON, codec.MSGPACK])
def test_error_bodies_map_to_the_exception_tree(status: int, cls: type, kind: str) -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(status, content=codec.dump(_error(status, "c"), kind),
                              headers={"content-type": kind})

    c = Client("http://x", transport=httpx.MockTransport(handler))
    with pytest.raises(cls) as exc:
        c.get_session("s1")
    assert isinstance(exc.value, APIError)
    assert exc.value.status == status and exc.value.field == "body.x"
    assert exc.value.errors[0].message == "why"


def test_unparseable_error_body_still_maps_by_status() -> None:
    c = Client("http://x", transport=httpx.MockTransport(
        lambda r: httpx.Response(502, content=b"<html>bad gateway</html>")))
    with pytest.raises(ServerError, match="bad gateway"):
        c.health()


@pytest.mark.parametrize("encoding", ["msgpack", "json"])
def test_requests_are_encoded_as_asked(encoding: str) -> None:
    seen: list[httpx.Request] = []
    kind = codec.MSGPACK if encoding == "msgpack" else codec.JSON

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        body = {"candidates": [{"id": 7, "pose": {"matrix": np.eye(4).tolist()}}], "version": 3}
        return httpx.Response(200, content=codec.dump(body, kind), headers={"content-type": kind})

    c = Client("http://x", token="sesame", encoding=encoding,  # type: ignore[arg-type]
               transport=httpx.MockTransport(handler))
    poses = np.stack([np.eye(4)] * 2)
    out = c.set_pool("s1", poses, ids=[7, 8])
    req = seen[0]
    assert req.method == "PUT" and req.url.path == "/v1/sessions/s1/pool"
    assert req.headers["authorization"] == "Bearer sesame"
    assert req.headers["content-type"] == kind and req.headers["accept"] == kind
    body = msgpack.unpackb(req.content) if encoding == "msgpack" else json.loads(req.content)
    assert body["ids"] == [7, 8] and np.allclose(body["poses"][1]["matrix"], np.eye(4))
    assert out.ids() == [7] and out.matrices().shape == (1, 4, 4)


def test_select_request_and_numpy_out() -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        body = json.loads(request.content)
        assert request.url.path == "/v1/sessions/s1/select"
        assert body["method"] == "agile" and body["commit"] is True and body["embodied_k"] == 3
        assert np.allclose(body["current_pose"]["matrix"], np.eye(4))
        resp = {
            "session": "s1", "method": "agile",
            "chosen": {"id": 4, "pose": {"matrix": np.eye(4).tolist()}},
            "shortlist": [{"id": 4, "score": 0.5}, {"id": 1, "score": None}],
            "anchor": None, "scores": [], "eligible": [1, 4], "psi_trace": [],
            "latency_ms": {"total": 1.0}, "core_ms": 1.2, "server_ms": 1.5,
            "committed": None, "version": 2, "time": 0.0,
        }
        return httpx.Response(200, json=resp)

    c = Client("http://x", encoding="json", transport=httpx.MockTransport(handler))
    r = c.select("s1", method="agile", embodied_k=3, current_pose=np.eye(4), commit=True)
    assert r.chosen.id == 4 and r.shortlist[1].score is None
    np.testing.assert_array_equal(r.chosen.pose.to_matrix(), np.eye(4))


def test_transport_failures_and_contract_breaches() -> None:
    def refuse(request: httpx.Request) -> httpx.Response:
        raise httpx.ConnectError("refused", request=request)

    with pytest.raises(TransportError) as exc:
        Client("http://x", transport=httpx.MockTransport(refuse)).health()
    assert isinstance(exc.value.__cause__, httpx.ConnectError)
    bad = Client("http://x", transport=httpx.MockTransport(
        lambda r: httpx.Response(200, json={"unexpected": True})))
    with pytest.raises(ProtocolError):
        bad.health()


def test_async_client_shares_the_operations() -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path == "/v1/sessions/nope":
            return httpx.Response(404, json=_error(404, "not_found", "session"))
        return httpx.Response(200, json={"status": "ok", "version": "1", "sessions": 0,
                                         "zenoh": False, "uptime_s": 1.0})

    async def main() -> None:
        async with AsyncClient("http://x", transport=httpx.MockTransport(handler)) as c:
            assert (await c.health()).status == "ok"
            with pytest.raises(NotFoundError) as exc:
                await c.get_session("nope")
            assert exc.value.field == "session"

    asyncio.run(main())


def test_sync_async_and_zenoh_clients_offer_the_same_methods() -> None:
    import inspect

    from agilegs.client import ZenohClient
    from agilegs.schemas import OPERATIONS

    def signature(cls: type, name: str) -> list[tuple[str, object, object]]:
        params = inspect.signature(getattr(cls, name)).parameters.values()
        return [(p.name, p.kind, p.default) for p in params]

    for cls in (Client, AsyncClient, ZenohClient):
        for name in OPERATIONS:
            assert callable(getattr(cls, name, None)), (cls.__name__, name)
    for name in OPERATIONS:
        # the same parameters, in the same order, with the same defaults
        assert signature(AsyncClient, name) == signature(Client, name), name
        assert signature(ZenohClient, name) == signature(Client, name), name
    assert inspect.iscoroutinefunction(AsyncClient.select)
    assert not inspect.iscoroutinefunction(Client.select)


def test_create_session_inputs_are_validated_client_side() -> None:
    def never(request: httpx.Request) -> httpx.Response:
        raise AssertionError("nothing must be sent")

    c = Client("http://x", transport=httpx.MockTransport(never))
    with pytest.raises(ValidationError) as exc:
        c.create_session({**INTR, "width": 0}, bounds={"min": [0] * 3, "max": [1] * 3})
    assert exc.value.status == 422
    with pytest.raises(ValidationError, match="shape"):
        c.set_pool("s1", np.zeros((3, 4)))
    bad = np.eye(4)
    bad[3, 3] = 2
    with pytest.raises(ValidationError, match="last row") as exc:
        c.commit("s1", pose=bad)
    assert exc.value.field is not None and exc.value.field.endswith("matrix")
