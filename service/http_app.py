"""The HTTP transport: a FastAPI app whose routes decode, call the core, encode.

Every operation of :data:`agilegs.schemas.ops.OPERATIONS` is one route (see
:mod:`agilegs.service.routes_sessions`); bodies are JSON or msgpack by Content-Type, responses
by Accept. ``/healthz`` and ``/metrics`` answer on the event loop (never behind session work,
which runs in the core's worker threads). Errors, whatever raised them, are the
:class:`~agilegs.schemas.errors.ErrorBody` of :mod:`agilegs.schemas.errors`.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import Response
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Receive, Scope, Send

from agilegs.schemas import codec
from agilegs.schemas.ops import OPERATIONS

from .core import ServiceCore, ServiceError, field_path
from .metrics import CONTENT_TYPE_LATEST, Metrics
from .settings import Settings

__all__ = ["create_app", "error_response"]

log = logging.getLogger(__name__)

_STATUS_CODES = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    406: "not_acceptable",
    409: "conflict",
    413: "payload_too_large",
    415: "unsupported_media",
    422: "invalid",
    429: "too_many",
}


def error_response(err: ServiceError, accept: str | None = None) -> Response:
    """The error body of ``err``, in the type the request accepts (JSON by default)."""
    kind = codec.negotiate(accept) or codec.JSON
    headers = {"WWW-Authenticate": "Bearer"} if err.status == 401 else None
    return Response(codec.dump(err.body(), kind), status_code=err.status, media_type=kind,
                    headers=headers)


class BearerAuth:
    """Pure ASGI middleware: every HTTP request must carry ``Authorization: Bearer <token>``
    (compared in constant time) or gets 401."""

    def __init__(self, app: ASGIApp, token: str, metrics: Metrics | None = None) -> None:
        self.app = app
        self.digest = hashlib.sha256(token.encode()).digest()
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        given = b""
        for name, value in scope["headers"]:
            if name == b"authorization":
                given = value
                break
        ok = False
        if given[:7].lower() == b"bearer ":
            ok = hmac.compare_digest(hashlib.sha256(given[7:].strip()).digest(), self.digest)
        if ok:
            await self.app(scope, receive, send)
            return
        if self.metrics is not None:
            self.metrics.observe_request("http", "auth", 401, "unauthorized")
        accept = next((v.decode("latin-1") for k, v in scope["headers"] if k == b"accept"), None)
        err = ServiceError(401, "unauthorized", "missing or wrong bearer token",
                           "header.authorization")
        await error_response(err, accept)(scope, receive, send)


def create_app(settings: Settings, core: ServiceCore | None = None) -> FastAPI:
    """The FastAPI app. Its lifespan loads the sessions and starts Zenoh (``settings.zenoh``),
    and closes both on shutdown."""
    core = core or ServiceCore(settings)
    metrics = Metrics(sessions=lambda: len(core.sessions))
    from .cluster import ClusterNode  # issue 6: placement and forwarding between instances

    cluster = ClusterNode(core, settings)
    core.metrics = metrics

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        core.load()
        adapter = None
        if settings.zenoh:
            from .zenoh_adapter import ZenohAdapter

            adapter = ZenohAdapter(core, settings, metrics, cluster=cluster)
            adapter.start()
        app.state.zenoh = adapter
        try:
            yield
        finally:
            if adapter is not None:
                adapter.close()
            core.close()

    app = FastAPI(
        title="agilegs",
        summary="AGILE-GS next-best-view service for active 3D Gaussian Splatting",
        description=_DESCRIPTION,
        version=core.health().version,
        lifespan=lifespan,
        docs_url="/docs",
        openapi_url="/openapi.json",
    )
    app.state.core = core
    app.state.cluster = cluster
    app.state.metrics = metrics
    app.state.settings = settings

    async def on_service_error(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, ServiceError)
        return error_response(exc, request.headers.get("accept"))

    async def on_validation(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, RequestValidationError)
        items = []
        for e in exc.errors():
            items.append((field_path("", e.get("loc", ())), str(e.get("msg", "invalid"))))
        from agilegs.schemas.errors import ErrorItem

        first = items[0] if items else ("request", "invalid")
        err = ServiceError(422, "invalid", f"{first[0]}: {first[1]}", first[0],
                           [ErrorItem(field=f, message=msg) for f, msg in items])
        metrics.observe_request("http", _op_name(request), 422, "invalid")
        return error_response(err, request.headers.get("accept"))

    async def on_http(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, StarletteHTTPException)
        code = _STATUS_CODES.get(exc.status_code, "error")
        err = ServiceError(exc.status_code, code, str(exc.detail), None)
        metrics.observe_request("http", _op_name(request), exc.status_code, code)
        return error_response(err, request.headers.get("accept"))

    async def on_crash(request: Request, exc: Exception) -> Response:
        log.exception("internal error on %s %s", request.method, request.url.path)
        metrics.observe_request("http", _op_name(request), 500, "internal")
        err = ServiceError(500, "internal", f"internal error ({type(exc).__name__})", None)
        return error_response(err, request.headers.get("accept"))

    app.add_exception_handler(ServiceError, on_service_error)
    app.add_exception_handler(RequestValidationError, on_validation)
    app.add_exception_handler(StarletteHTTPException, on_http)
    app.add_exception_handler(Exception, on_crash)

    from .routes_sessions import build_router

    app.include_router(build_router(core, settings, metrics, dispatch=cluster.call))

    @app.get("/metrics", tags=["service"], summary="Prometheus metrics",
             response_class=Response,
             responses={200: {"content": {CONTENT_TYPE_LATEST: {"schema": {"type": "string"}}}}})
    async def get_metrics() -> Response:
        return Response(metrics.render(), media_type=CONTENT_TYPE_LATEST)

    app.openapi = lambda: _openapi(app)  # type: ignore[method-assign]
    token = settings.token_value()
    if token:
        app.add_middleware(BearerAuth, token=token, metrics=metrics)
    return app


def _op_name(request: Request) -> str:
    route = request.scope.get("route")
    return getattr(route, "name", None) or "unknown"


def _openapi(app: FastAPI) -> dict[str, Any]:
    """FastAPI's schema plus the request models (bodies are decoded by hand: JSON or msgpack)."""
    if app.openapi_schema:
        return app.openapi_schema
    schema = get_openapi(title=app.title, version=app.version, summary=app.summary,
                         description=app.description, routes=app.routes)
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    for op in OPERATIONS.values():
        if op.request is None:
            continue
        js = op.request.model_json_schema(ref_template="#/components/schemas/{model}",
                                          mode="validation")
        for name, sub in js.pop("$defs", {}).items():
            components.setdefault(name, sub)
        components[op.request.__name__] = js
    security = app.state.settings.token_value()
    if security:
        components_root = schema["components"]
        components_root["securitySchemes"] = {"bearer": {"type": "http", "scheme": "bearer"}}
        schema["security"] = [{"bearer": []}]
    app.openapi_schema = schema
    return schema


_DESCRIPTION = """
Next-best-view selection for active 3D Gaussian Splatting (AGILE-GS), per map session.

* Bodies are JSON (`application/json`) or msgpack (`application/msgpack`), chosen by
  `Content-Type`; responses follow `Accept`. Bytes travel raw in msgpack and base64 in JSON.
* Poses are camera-to-world with OpenCV axes (x right, y down, z forward): a 4x4 row-major
  `matrix`, or `position` + `orientation_xyzw` (unit quaternion, ROS order x, y, z, w). The
  rotation must be orthonormal (max |RᵀR − I| ≤ 1e-3, det > 0).
* Every error is `{"error": {"status", "code", "message", "field", "errors"}}` with a 4xx
  status naming the offending field; a refused request changes nothing.
* With `AGILEGS_TOKEN` set, every request needs `Authorization: Bearer <token>`.
* The same operations are served over Zenoh under `agilegs/<session>/<op>`.
* With several instances joined over Zenoh, any instance serves every session: an operation
  on a session another instance owns is forwarded to it (its answer is returned as is; 404
  `session_unavailable` when no instance answers for the session); `POST /v1/sessions` places
  a new session on the instance with the fewest sessions (or `?instance=<id>`), and
  `GET /v1/sessions` lists every instance's sessions.
"""
