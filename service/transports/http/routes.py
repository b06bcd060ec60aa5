"""HTTP routes: one per operation of :data:`agilegs.schemas.ops.OPERATIONS`, as glue over
the gateway.

Each route checks that the response type is acceptable (406) and reads the body, refusing
more than ``max_body_bytes`` (413) before it has all arrived, and its bytes beyond the
server's budget of bodies in flight (503, :meth:`Admission.reserve_body
<agilegs.service.transports.admission.Admission.reserve_body>`) before reading them; a client that
hangs up mid-body is logged at INFO and counted as 499; then the gateway admits it and
a worker thread runs its pipeline (:meth:`Gateway.submit
<agilegs.service.transports.gateway.Gateway.submit>`). The ``X-Deadline-Ms`` header shortens the
request's deadline; a client that disconnects before the answer cancels its request at the
next stage boundary. ``/healthz`` answers on the event loop, never behind session work. The
decisions feed's long poll and event stream are :mod:`agilegs.service.transports.http.decisions`.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Awaitable, Callable
from typing import Annotated

from fastapi import APIRouter, Path, Request
from fastapi.responses import Response
from starlette.requests import ClientDisconnect

from agilegs.schemas import OPERATIONS, SESSION_ID_PATTERN, Operation, codec
from agilegs.schemas.errors import ErrorCode
from agilegs.schemas.requests import REQUEST_ID_HEADER

from ...errors import ServiceError
from ..admission import CLIENT_CLOSED, CLIENT_GONE, Ticket, parse_deadline_ms
from ..gateway import Gateway, Reply
from ..gateway import Request as GatewayRequest
from ..requests import parse_request_id
from .decisions import decisions_endpoint
from .edge import TIMED_OUT, release_memory
from .openapi import route_openapi

__all__ = ["build_router", "read_body", "response", "run_pipeline"]

SessionPath = Annotated[
    str,
    Path(pattern=SESSION_ID_PATTERN, description="session id ([A-Za-z0-9_-], 1 to 64)"),
]


def response(reply: Reply) -> Response:
    """The HTTP response of a gateway reply, with the headers its status calls for
    (RFC 9110): ``WWW-Authenticate`` on 401, ``Allow`` on 405, ``Accept`` on 415,
    ``Retry-After`` on a refusal for load."""
    headers = {}
    if reply.status == 401:
        headers["WWW-Authenticate"] = "Bearer"
    if reply.error is not None and reply.error.retry_after is not None:
        headers["Retry-After"] = str(max(1, math.ceil(reply.error.retry_after)))
    supported = reply.error.supported if reply.error is not None else None
    if supported is not None and reply.status == 405:
        headers["Allow"] = ", ".join(supported)
    elif supported is not None and reply.status == 415:
        headers["Accept"] = ", ".join(supported)
    return Response(reply.body, status_code=reply.status, media_type=reply.media_type,
                    headers=headers or None)


BODY_COPIES = 2
"""A body read costs up to twice its size (its chunks, then the joined bytes): it is priced
at that against ``max_inflight_body_bytes``."""


class ClientGone(Exception):
    """The client hung up before its request's body was in."""


async def read_body(request: Request, gateway: Gateway, reserved: list[int]) -> bytes:
    """The request body, refusing more than ``max_body_bytes`` (413) before reading it all,
    :data:`BODY_COPIES` times its bytes priced against ``max_inflight_body_bytes`` before
    they are read (503; added to
    ``reserved[0]``, which the caller gives back); :class:`ClientGone` when the client hangs
    up."""
    length = request.headers.get("content-length")
    size = None
    if length is not None:
        try:
            size = int(length)
        except ValueError:
            raise ServiceError(400, ErrorCode.BAD_REQUEST, "Content-Length is not a number",
                               "header.content-length") from None
        gateway.check_size(size)
        gateway.admission.reserve_body(BODY_COPIES * size)
        reserved[0] += BODY_COPIES * size
    chunks = []
    total = 0
    try:
        async for chunk in request.stream():
            total += len(chunk)
            gateway.check_size(total)
            if size is None or total > size:  # no (or a wrong) Content-Length: as it comes
                more = BODY_COPIES * total - reserved[0]
                gateway.admission.reserve_body(more)
                reserved[0] += more
            chunks.append(chunk)
    except ClientDisconnect:
        raise ClientGone from None
    return b"".join(chunks)


async def run_pipeline(gateway: Gateway, req: GatewayRequest,
                       request: Request | None = None) -> Reply:
    """The gateway's pipeline on ``req`` in a worker thread, once admitted (429 / 503 when
    not; 503 once the server stops). With ``request`` (its body read), the client
    disconnecting cancels ``req``."""
    ticket = gateway.ticket(req)
    fut = gateway.submit(req)
    watch = None
    if request is not None and not fut.done():
        watch = asyncio.create_task(_on_disconnect(request, ticket))
    try:
        return await asyncio.wrap_future(fut)
    finally:
        if watch is not None:
            watch.cancel()


async def _on_disconnect(request: Request, ticket: Ticket) -> None:
    """Cancel ``ticket`` when the client of ``request`` (its body read) disconnects."""
    while True:
        message = await request.receive()
        if message["type"] == "http.disconnect":
            ticket.cancel(CLIENT_GONE)
            return


def deadline_header(request: Request) -> float | None:
    """The ``X-Deadline-Ms`` header as milliseconds (400 when it is not a number >= 0)."""
    return parse_deadline_ms(request.headers.get("x-deadline-ms"), "header.x-deadline-ms")


def build_router(gateway: Gateway) -> APIRouter:
    """The routes of every operation."""
    router = APIRouter()

    async def handle(op: Operation, request: Request, session: str | None) -> Response:
        t0 = time.perf_counter()
        accept = request.headers.get("accept")
        body = None
        reserved = [0]
        try:
            try:
                gateway.negotiate(accept, op.name)
                if op.name == "get_gaussians" and "format" in request.query_params:
                    raise ServiceError(400, ErrorCode.BAD_REQUEST, "query.format: "
                                       "get_gaussians takes no format parameter; ask for a file "
                                       "with Accept: application/x-ply or application/x-splat",
                                       "query.format")
                deadline_ms = deadline_header(request)
                request_id = parse_request_id(request.headers.get(REQUEST_ID_HEADER),
                                              f"header.{REQUEST_ID_HEADER.lower()}")
                if op.request is not None and not op.query:
                    body = await read_body(request, gateway, reserved)
            except ServiceError as err:
                kind = codec.negotiate(accept) or codec.JSON
                return response(gateway.error_reply(err, kind, "http", op.name))
            except ClientGone:
                late = request.scope.get(TIMED_OUT)
                why = (f"its body did not arrive within {late:g} s (body_timeout): the "
                       "connection was closed" if late else
                       "the client disconnected before its body was in")
                gone = ServiceError(CLIENT_CLOSED, ErrorCode.BAD_REQUEST, why, "body")
                return response(gateway.gone_reply(gone, codec.JSON, "http", op.name, why))
            req = GatewayRequest(
                op=op.name, session=session, body=body,
                content_type=request.headers.get("content-type"), accept=accept,
                params=dict(request.query_params), transport="http", t0=t0,
                authenticated=True, deadline_ms=deadline_ms, request_id=request_id,
            )
            del body
            return response(await run_pipeline(gateway, req, request))
        finally:
            if gateway.admission.release_body(reserved[0]):
                asyncio.get_running_loop().run_in_executor(None, release_memory)

    def endpoint_for(op: Operation) -> Callable[..., Awaitable[Response]]:
        if op.name == "health":

            async def health() -> Response:
                # on the event loop: answers while every worker thread is busy
                return Response(codec.dump(gateway.registry.health(), codec.JSON),
                                media_type=codec.JSON)

            return health
        if op.event_stream:
            feed = decisions_endpoint(gateway, op, handle=handle, run=run_pipeline,
                                      respond=response)

            async def feed_endpoint(request: Request, session: SessionPath) -> Response:
                return await feed(request, session)

            return feed_endpoint
        if op.scope == "service":

            async def service_endpoint(request: Request) -> Response:
                return await handle(op, request, None)

            return service_endpoint

        async def session_endpoint(request: Request, session: SessionPath) -> Response:
            return await handle(op, request, session)

        return session_endpoint

    for op in OPERATIONS.values():
        router.add_api_route(
            op.http_path,
            endpoint_for(op),
            methods=[op.http_method],
            name=op.name,
            operation_id=op.name,
            summary=op.summary,
            description=(op.request.__doc__ or "") if op.request is not None else "",
            response_model=op.response,
            tags=["service" if op.scope == "service" else "sessions"],
            **route_openapi(op),
        )
    return router
