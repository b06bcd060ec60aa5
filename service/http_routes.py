"""HTTP routes: one per operation of :data:`agilegs.schemas.ops.OPERATIONS`, as glue over
the gateway.

Each route checks that the response type is acceptable (406) and reads the body, refusing
more than ``max_body_bytes`` (413) before it has all arrived; then a worker thread runs the
gateway's pipeline on it (:meth:`Gateway.handle <agilegs.service.gateway.Gateway.handle>`).
``/healthz`` answers on the event loop, never behind session work. The decisions feed's
long poll and event stream are :mod:`agilegs.service.http_decisions`.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from typing import Annotated

from fastapi import APIRouter, Path, Request
from fastapi.responses import Response

from agilegs.schemas import codec
from agilegs.schemas.errors import ErrorCode
from agilegs.schemas.models import SESSION_ID_PATTERN
from agilegs.schemas.ops import OPERATIONS, Operation

from .errors import ServiceError
from .gateway import Gateway, Reply
from .gateway import Request as GatewayRequest
from .http_decisions import decisions_endpoint
from .http_openapi import route_openapi

__all__ = ["build_router", "read_body", "response", "run_pipeline"]

SessionPath = Annotated[
    str,
    Path(pattern=SESSION_ID_PATTERN, description="session id ([A-Za-z0-9_-], 1 to 64)"),
]


def response(reply: Reply) -> Response:
    """The HTTP response of a gateway reply, with the headers its status calls for
    (RFC 9110): ``WWW-Authenticate`` on 401, ``Allow`` on 405, ``Accept`` on 415."""
    headers = {}
    if reply.status == 401:
        headers["WWW-Authenticate"] = "Bearer"
    supported = reply.error.supported if reply.error is not None else None
    if supported is not None and reply.status == 405:
        headers["Allow"] = ", ".join(supported)
    elif supported is not None and reply.status == 415:
        headers["Accept"] = ", ".join(supported)
    return Response(reply.body, status_code=reply.status, media_type=reply.media_type,
                    headers=headers or None)


async def read_body(request: Request, gateway: Gateway) -> bytes:
    """The request body, refusing more than ``max_body_bytes`` (413) before reading it all."""
    length = request.headers.get("content-length")
    if length is not None:
        try:
            size = int(length)
        except ValueError:
            raise ServiceError(400, ErrorCode.BAD_REQUEST, "Content-Length is not a number",
                               "header.content-length") from None
        gateway.check_size(size)
    chunks = []
    total = 0
    async for chunk in request.stream():
        total += len(chunk)
        gateway.check_size(total)
        chunks.append(chunk)
    return b"".join(chunks)


async def run_pipeline(gateway: Gateway, req: GatewayRequest) -> Reply:
    """The gateway's pipeline on ``req`` in a worker thread (503 once the server stops)."""
    try:
        return await asyncio.get_running_loop().run_in_executor(
            gateway.executor, gateway.handle, req)
    except RuntimeError:  # the executor is shut down: the server is stopping
        stopping = ServiceError(503, ErrorCode.UNAVAILABLE, "the server is stopping")
        return gateway.error_reply(stopping, codec.negotiate(req.accept) or codec.JSON, "http",
                                   req.op)


def build_router(gateway: Gateway) -> APIRouter:
    """The routes of every operation."""
    router = APIRouter()

    async def handle(op: Operation, request: Request, session: str | None) -> Response:
        t0 = time.perf_counter()
        accept = request.headers.get("accept")
        body = None
        try:
            gateway.negotiate(accept)
            if op.request is not None and not op.query:
                body = await read_body(request, gateway)
        except ServiceError as err:
            kind = codec.negotiate(accept) or codec.JSON
            return response(gateway.error_reply(err, kind, "http", op.name))
        req = GatewayRequest(
            op=op.name, session=session, body=body,
            content_type=request.headers.get("content-type"), accept=accept,
            params=dict(request.query_params), transport="http", t0=t0, authenticated=True,
        )
        return response(await run_pipeline(gateway, req))

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
