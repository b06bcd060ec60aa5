"""Riding through a handover: an operation answered ``session_unavailable`` with a
``retry_after`` is retried with backoff within the client's window; without one (a session
that does not exist, a cluster without a shared store) it fails at once."""

from __future__ import annotations

import asyncio
import time

import httpx
import numpy as np
import pytest

from agilegs.client import AsyncClient, Client, NotFoundError, SessionUnavailableError
from agilegs.client._retry import backoff
from agilegs.schemas import codec

POOL = {"candidates": [{"id": 7, "pose": {"matrix": np.eye(4).tolist()}}], "version": 3}


def unavailable(retry_after: float | None) -> httpx.Response:
    body = {"error": {"status": 404, "code": "session_unavailable", "message": "moving",
                      "field": "path.session", "errors": [{"field": None, "message": "moving"}],
                      "retry_after": retry_after}}
    return httpx.Response(404, content=codec.dump(body, codec.JSON),
                          headers={"content-type": codec.JSON})


def flaky(failures: int, retry_after: float | None) -> tuple[list[float], httpx.MockTransport]:
    seen: list[float] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(time.monotonic())
        if len(seen) <= failures:
            return unavailable(retry_after)
        return httpx.Response(200, content=codec.dump(POOL, codec.JSON),
                              headers={"content-type": codec.JSON})

    return seen, httpx.MockTransport(handler)


def test_a_handover_is_ridden_through_with_backoff() -> None:
    seen, transport = flaky(3, 0.01)
    with Client("http://x", transport=transport) as c:
        assert c.get_pool("s").version == 3
    gaps = np.diff(seen)
    assert len(seen) == 4 and gaps[0] >= 0.05 and gaps[1] >= 0.1 and gaps[2] >= 0.2


def test_without_retry_after_it_fails_at_once() -> None:
    seen, transport = flaky(3, None)
    with Client("http://x", transport=transport) as c, pytest.raises(SessionUnavailableError):
        c.get_pool("s")
    assert len(seen) == 1


def test_past_the_window_the_last_error_is_raised() -> None:
    seen, transport = flaky(100, 0.2)
    t0 = time.monotonic()
    with Client("http://x", transport=transport, retry_window=1.0) as c:
        with pytest.raises(SessionUnavailableError):
            c.get_pool("s")
    assert 0.5 < time.monotonic() - t0 <= 1.05 and 3 <= len(seen) <= 6
    seen, transport = flaky(100, 0.2)
    with Client("http://x", transport=transport, retry_window=0) as c:
        with pytest.raises(SessionUnavailableError):
            c.get_pool("s")
    assert len(seen) == 1


def test_the_async_client_retries_alike() -> None:
    seen, _ = flaky(2, 0.01)

    async def handler(request: httpx.Request) -> httpx.Response:
        seen.append(time.monotonic())
        return unavailable(0.01) if len(seen) <= 2 else httpx.Response(
            200, content=codec.dump(POOL, codec.JSON), headers={"content-type": codec.JSON})

    async def run() -> int:
        async with AsyncClient("http://x", transport=httpx.MockTransport(handler)) as c:
            return (await c.get_pool("s")).version

    assert asyncio.run(run()) == 3 and len(seen) == 3


def test_backoff_doubles_up_to_a_second_and_honours_the_hint() -> None:
    assert [backoff(i, None) for i in range(7)] == [0.05, 0.1, 0.2, 0.4, 0.8, 1.0, 1.0]
    assert backoff(0, 0.3) == 0.3


def test_every_write_carries_a_request_id_and_its_retries_the_same() -> None:
    keys: list[tuple[str, str | None]] = []
    view = {"id": 0, "candidate_id": 7, "pose": {"matrix": np.eye(4).tolist()},
            "intrinsics": None, "has_image": False, "has_depth": False, "created_at": 1.0}

    def handler(request: httpx.Request) -> httpx.Response:
        keys.append((request.method, request.headers.get("idempotency-key")))
        if request.method == "POST" and len(keys) < 3:
            return unavailable(0.01)
        body = view if request.method == "POST" else POOL
        return httpx.Response(200, content=codec.dump(body, codec.JSON),
                              headers={"content-type": codec.JSON})

    with Client("http://x", transport=httpx.MockTransport(handler)) as c:
        c.get_pool("s")
        c.commit("s", candidate_id=7)
        c.commit("s", candidate_id=7)
    assert keys[0] == ("GET", None)  # reads carry none
    first, second, third = (k for _, k in keys[1:])
    assert first is not None and first == second  # a retry: the same id
    assert third is not None and third != first  # another call: another id


def test_a_delete_whose_answer_was_lost_is_done() -> None:
    plan: list[httpx.Response] = []

    def handler(request: httpx.Request) -> httpx.Response:
        return plan.pop(0)

    gone = {"error": {"status": 404, "code": "not_found", "message": "gone",
                      "field": "path.session", "errors": []}}
    not_found = httpx.Response(404, content=codec.dump(gone, codec.JSON),
                               headers={"content-type": codec.JSON})
    with Client("http://x", transport=httpx.MockTransport(handler)) as c:
        plan[:] = [unavailable(0.01), not_found]  # deleted by the attempt whose answer was lost
        assert c.delete_session("s").id == "s"
        plan[:] = [not_found]  # no such session from the start: an error
        with pytest.raises(NotFoundError):
            c.delete_session("s")
