"""HTTP routes: one per operation of :data:`agilegs.schemas.ops.OPERATIONS`.

Each route reads the body (bounded by ``max_body_bytes``), hands the bytes to a worker
thread that decodes them (JSON or msgpack) and calls :meth:`ServiceCore.call`, then encodes
the response as the request's Accept asks. ``/healthz`` answers on the event loop.
"""

from __future__ import annotations

import asyncio
import functools
import time
from collections.abc import Awaitable, Callable
from typing import Annotated, Any

from fastapi import APIRouter, Path, Request
from fastapi.responses import Response

from agilegs.schemas import codec
from agilegs.schemas.errors import ErrorBody
from agilegs.schemas.keys import INSTANCE_ID_PATTERN
from agilegs.schemas.models import SESSION_ID_PATTERN
from agilegs.schemas.ops import OPERATIONS, Operation

from .core import ServiceCore, ServiceError
from .metrics import Metrics
from .settings import Settings

__all__ = ["build_router"]

SessionPath = Annotated[
    str,
    Path(pattern=SESSION_ID_PATTERN, description="session id ([A-Za-z0-9_-], 1 to 64)"),
]

_RAW_TYPES = ("application/octet-stream", "application/x-ply", "application/x-splat")


def _error_responses(op: Operation) -> dict[int | str, dict[str, Any]]:
    codes = [400, 401, 406, 422, 500]
    if op.request is not None:
        codes += [413, 415]
    if op.scope == "session":
        codes += [404, 409, 429]
    elif op.name == "create_session":
        codes += [404, 409, 429]  # 404: no instance answers as ?instance=
    return {
        c: {
            "model": ErrorBody,
            "description": "error (see the error codes)",
            "content": {codec.MSGPACK: {"schema": {"$ref": "#/components/schemas/ErrorBody"}}},
        }
        for c in sorted(set(codes))
    }


def _request_body(op: Operation) -> dict[str, Any] | None:
    if op.request is None:
        return None
    ref = {"$ref": f"#/components/schemas/{op.request.__name__}"}
    content: dict[str, Any] = {codec.JSON: {"schema": ref}, codec.MSGPACK: {"schema": ref}}
    extra: dict[str, Any] = {"requestBody": {"required": True, "content": content}}
    if op.name == "set_gaussians":
        # a raw .ply / .splat upload: the file as the body, its format in the query
        content["application/octet-stream"] = {"schema": {"type": "string", "format": "binary"}}
        extra["parameters"] = [{
            "name": "format", "in": "query", "required": False,
            "description": "format of an application/octet-stream body (default: sniffed)",
            "schema": {"type": "string", "enum": ["ply", "splat"]},
        }]
    if op.name == "create_session":  # issue 6: explicit placement
        extra["parameters"] = [{
            "name": "instance", "in": "query", "required": False,
            "description": "create it on this instance (default: the instance with the fewest "
                           "sessions, ties by smallest id; see agilegs.service.cluster)",
            "schema": {"type": "string", "pattern": INSTANCE_ID_PATTERN},
        }]
    return extra


async def read_body(request: Request, limit: int) -> bytes:
    """The request body, refusing more than ``limit`` bytes (413) before reading it all."""
    length = request.headers.get("content-length")
    if length is not None:
        try:
            too_big = int(length) > limit
        except ValueError:
            raise ServiceError(400, "bad_request", "Content-Length is not a number",
                               "header.content-length") from None
        if too_big:
            raise ServiceError(413, "payload_too_large",
                               f"body of {length} bytes exceeds max_body_bytes ({limit})", "body")
    chunks = []
    total = 0
    async for chunk in request.stream():
        total += len(chunk)
        if total > limit:
            raise ServiceError(413, "payload_too_large",
                               f"body exceeds max_body_bytes ({limit})", "body")
        chunks.append(chunk)
    return b"".join(chunks)


def _decode(op: Operation, body: bytes, content_type: str | None, params: dict[str, str]) -> Any:
    """Body bytes to Python data (runs in a worker thread)."""
    base = (content_type or "").split(";", 1)[0].strip().lower()
    if op.name == "set_gaussians" and base in _RAW_TYPES:
        fmt = params.get("format") or ("ply" if body[:4] == b"ply\n" else "splat")
        return {"format": fmt, "data": body}
    kind = codec.media_type(content_type)
    if kind is None:
        raise ServiceError(415, "unsupported_media",
                           f"Content-Type {content_type!r} is neither {codec.JSON} nor "
                           f"{codec.MSGPACK}", "header.content-type")
    if not body:
        raise ServiceError(422, "invalid", "body: a request body is required", "body")
    try:
        return codec.load(body, kind)
    except codec.DecodeError as exc:
        raise ServiceError(400, "bad_request", str(exc), "body") from None


def build_router(core: ServiceCore, settings: Settings, metrics: Metrics,
                 dispatch: Callable[..., Any] | None = None) -> APIRouter:
    """The routes; ``dispatch`` (a :meth:`ClusterNode.call <agilegs.service.cluster.
    ClusterNode.call>`) runs operations where their session lives, else ``core.call``."""
    router = APIRouter()

    def work(op: Operation, session: str | None, body: bytes | None, content_type: str | None,
             params: dict[str, str], t0: float) -> Any:
        payload = None if body is None else _decode(op, body, content_type, params)
        if dispatch is None:
            return core.call(op.name, session, payload, t0=t0)
        return dispatch(op.name, session, payload, t0=t0, instance=params.get("instance"))

    async def handle(op: Operation, request: Request, session: str | None) -> Response:
        t0 = time.perf_counter()
        try:
            kind = codec.negotiate(request.headers.get("accept"))
            if kind is None:
                raise ServiceError(406, "not_acceptable",
                                   f"Accept names neither {codec.JSON} nor {codec.MSGPACK}",
                                   "header.accept")
            body = None
            if op.request is not None:
                body = await read_body(request, settings.max_body_bytes)
            result = await asyncio.get_running_loop().run_in_executor(
                core.executor,
                functools.partial(work, op, session, body, request.headers.get("content-type"),
                                  dict(request.query_params), t0),
            )
            content = codec.dump(result, kind)
        except ServiceError as err:
            metrics.observe_request("http", op.name, err.status, err.code)
            raise
        metrics.observe_request("http", op.name, 200)
        return Response(content, media_type=kind)

    def endpoint_for(op: Operation) -> Callable[..., Awaitable[Response]]:
        if op.name == "health":

            async def health() -> Response:
                # on the event loop: answers while every worker thread is busy
                return Response(codec.dump(core.health(), codec.JSON), media_type=codec.JSON)

            return health
        if op.scope == "service":

            async def service_endpoint(request: Request) -> Response:
                return await handle(op, request, None)

            return service_endpoint

        async def session_endpoint(request: Request, session: SessionPath) -> Response:
            return await handle(op, request, session)

        return session_endpoint

    for op in OPERATIONS.values():
        extra = _request_body(op)
        router.add_api_route(
            op.http_path,
            endpoint_for(op),
            methods=[op.http_method],
            name=op.name,
            operation_id=op.name,
            summary=op.summary,
            description=(op.request.__doc__ or "") if op.request is not None else "",
            response_model=op.response,
            responses={
                200: {"content": {codec.MSGPACK: {
                    "schema": {"$ref": f"#/components/schemas/{op.response.__name__}"}}}},
                **_error_responses(op),
            },
            tags=["service" if op.scope == "service" else "sessions"],
            openapi_extra=extra,
        )
    return router
