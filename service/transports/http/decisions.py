"""HTTP glue of the decisions feed (:mod:`agilegs.schemas.decisions`): the long poll waits on
the event loop, and ``Accept: text/event-stream`` gets server-sent events.

Long poll (``GET /v1/sessions/{session}/decisions?after=N&wait=S``)
    For a session held here, the wait happens on the event loop
    (:meth:`DecisionLog.wait_async <agilegs.service.sessions.decisions.DecisionLog.wait_async>`),
    then the gateway's pipeline answers once, without waiting: a waiting poll holds no worker
    thread. A session held by another instance of a cluster goes through the pipeline as
    is (forwarded with its wait).

Event stream (``Accept: text/event-stream``)
    Events: ``feed`` first (``{"session", "epoch", "last_seq"}``), then one ``decision`` per
    decision (its ``id`` is ``<epoch>:<seq>``, its data the :class:`DecisionEvent` as JSON),
    ``missed`` (``{"missed", "after"}``) when the log no longer holds some, ``closed`` when
    the session is deleted (the stream ends), ``error`` (an ErrorBody) if reading fails, and
    a ``: keep-alive`` comment every :data:`HEARTBEAT_S` s of silence. The stream stays open
    ``wait`` seconds (default and at most ``AGILEGS_MAX_POLL_WAIT``), then ends; a browser's
    ``EventSource`` reconnects by itself with ``Last-Event-ID`` and goes on where it stopped
    (from the new epoch's start when the server restarted meanwhile). Refusals before the
    stream starts (404, 422, ...) are the usual JSON error bodies.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

from fastapi import Request
from fastapi.responses import Response, StreamingResponse
from pydantic import BaseModel, ValidationError

from agilegs.schemas import DecisionsOut, DecisionsRequest, Operation, codec
from agilegs.schemas.errors import ErrorCode

from ..gateway import Gateway, Reply
from ..gateway import Request as GatewayRequest

__all__ = ["EVENT_STREAM", "HEARTBEAT_S", "decisions_endpoint", "wants_events"]

EVENT_STREAM = "text/event-stream"
HEARTBEAT_S = 15.0
"""Seconds of silence after which the stream sends a keep-alive comment."""
REMOTE_POLL_S = 0.5
"""Seconds between two reads of a stream on a session held by another instance."""

Handle = Callable[[Operation, Request, "str | None"], Awaitable[Response]]
Run = Callable[[Gateway, GatewayRequest], Awaitable[Reply]]
Respond = Callable[[Reply], Response]
Endpoint = Callable[[Request, str], Awaitable[Response]]


def wants_events(accept: str | None) -> bool:
    """Whether an Accept header names ``text/event-stream`` (with a quality above 0)."""
    return any(kind == EVENT_STREAM and q > 0 for kind, q in codec.media_ranges(accept))


def _parse(params: dict[str, str]) -> DecisionsRequest | None:
    try:
        return DecisionsRequest.model_validate_strings(params)
    except ValidationError:
        return None


def _last_event_id(value: str | None) -> tuple[str, int] | None:
    """``(epoch, seq)`` of a ``Last-Event-ID`` header written by this stream, else None."""
    epoch, _, seq = (value or "").strip().rpartition(":")
    if not epoch or not seq.isdigit():
        return None
    return epoch, int(seq)


def _event(name: str, data: BaseModel | dict[str, Any], event_id: str | None = None) -> bytes:
    text = (codec.dump(data, codec.JSON).decode() if isinstance(data, BaseModel)
            else json.dumps(data, allow_nan=False))
    head = f"id: {event_id}\n" if event_id is not None else ""
    return f"{head}event: {name}\ndata: {text}\n\n".encode()


def decisions_endpoint(gateway: Gateway, op: Operation, *, handle: Handle, run: Run,
                       respond: Respond) -> Endpoint:
    """The endpoint of ``get_decisions`` (see the module docstring).

    Args:
        handle: the route's plain handler (the pipeline run as is).
        run: runs the pipeline on a gateway request in a worker thread.
        respond: a gateway reply as an HTTP response.
    """
    feed = gateway.registry.decisions
    max_wait = gateway.settings.max_poll_wait

    def local(session: str) -> bool:
        s = gateway.registry.sessions.get(session)
        return s is not None and not s.closed

    def request(session: str, params: dict[str, str], accept: str | None) -> GatewayRequest:
        return GatewayRequest(op=op.name, session=session, accept=accept, params=params,
                              transport="http", authenticated=True)

    async def long_poll(req: Request, session: str) -> Response:
        params = dict(req.query_params)
        want = _parse(params)
        accept = req.headers.get("accept")
        if (want is None or want.wait <= 0 or not local(session)
                or codec.negotiate(accept) is None):
            return await handle(op, req, session)
        await feed.wait_async(session, want.after, min(want.wait, max_wait))
        reply = await run(gateway, request(session, {**params, "wait": "0"}, accept))
        if not reply.ok and reply.error is not None and reply.error.code == ErrorCode.NOT_FOUND:
            # deleted while this poll waited: it answers what the closed log holds
            rest = feed.read_closed(session, want.after, want.limit)
            if rest is not None:
                kind = reply.media_type
                return respond(Reply(200, codec.dump(rest, kind), kind, model=rest))
        return respond(reply)

    async def stream(req: Request, session: str) -> Response:
        params = dict(req.query_params)
        want = _parse(params)
        if want is None:  # the pipeline names the bad field (422), in JSON
            return respond(await run(gateway, request(session, params, codec.JSON)))
        last = _last_event_id(req.headers.get("last-event-id"))
        after = want.after if "after" in params or last is None else last[1]
        reply = await run(gateway, request(
            session, {**params, "after": str(after), "wait": "0"}, codec.JSON))
        if reply.ok and last is not None and "after" not in params:
            assert isinstance(reply.model, DecisionsOut)
            if reply.model.epoch != last[0]:  # the server restarted since: from the start
                after = 0
                reply = await run(gateway, request(
                    session, {**params, "after": "0", "wait": "0"}, codec.JSON))
        if not reply.ok:
            return respond(reply)
        duration = min(want.wait if "wait" in params else max_wait, max_wait)
        return StreamingResponse(
            events(session, reply, after, want.limit, duration), media_type=EVENT_STREAM,
            headers={"cache-control": "no-cache", "x-accel-buffering": "no"})

    async def events(session: str, reply: Reply, after: int, limit: int, duration: float
                     ) -> AsyncIterator[bytes]:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + duration
        out = reply.model
        assert isinstance(out, DecisionsOut)
        epoch = out.epoch
        yield _event("feed", {"session": session, "epoch": epoch, "last_seq": out.last_seq})
        quiet_since = loop.time()
        while True:
            if out.epoch != epoch:  # the session was created again: its new log from 1
                epoch, after = out.epoch, 0
                yield _event("feed", {"session": session, "epoch": epoch,
                                      "last_seq": out.last_seq})
            else:
                if out.missed:
                    yield _event("missed", {"missed": out.missed, "after": after})
                for ev in out.decisions:
                    yield _event("decision", ev, f"{epoch}:{ev.seq}")
                    quiet_since = loop.time()
                after = out.next_after
                if out.closed:
                    yield _event("closed", {"session": session})
                    return
                if len(out.decisions) < limit:  # caught up: wait for the next one
                    remaining = deadline - loop.time()
                    if remaining <= 0 or feed.stopping:
                        return
                    pause = min(remaining, max(0.0, quiet_since + HEARTBEAT_S - loop.time()))
                    if local(session):
                        await feed.wait_async(session, after, pause)
                    else:
                        await asyncio.sleep(min(pause, REMOTE_POLL_S))
                    if feed.stopping:
                        return
                    if loop.time() - quiet_since >= HEARTBEAT_S:
                        yield b": keep-alive\n\n"
                        quiet_since = loop.time()
            reply = await run(gateway, request(
                session, {"after": str(after), "limit": str(limit), "wait": "0"}, codec.JSON))
            if not reply.ok:
                assert reply.error is not None
                if reply.error.code == ErrorCode.NOT_FOUND:  # deleted meanwhile
                    yield _event("closed", {"session": session})
                else:
                    yield _event("error", reply.error.body())
                return
            out = reply.model
            assert isinstance(out, DecisionsOut)

    async def endpoint(req: Request, session: str) -> Response:
        if wants_events(req.headers.get("accept")):
            return await stream(req, session)
        return await long_poll(req, session)

    return endpoint
