"""The HTTP transport: a FastAPI app whose routes hand every request to the gateway.

Every operation of :data:`agilegs.schemas.ops.OPERATIONS` is one route (see
:mod:`agilegs.service.transports.http.routes`); bodies are JSON or msgpack by Content-Type,
responses by Accept. ``/healthz`` (liveness), ``/readyz`` (readiness: 503 with the reason while the
server compiles its kernels at start, or is saturated, :meth:`Admission.saturation
<agilegs.service.transports.admission.Admission.saturation>`) and ``/metrics`` answer on the event
loop. Errors, whatever raised them, are the :class:`~agilegs.schemas.errors.ErrorBody` of
:mod:`agilegs.schemas.errors`. The app's lifespan starts (unless told otherwise) and stops the
:class:`~agilegs.service.server.Server` it serves.

``/`` redirects to ``/docs``. The OpenAPI pages (``/docs``: Swagger UI, ``/redoc``) load their
scripts and styles from the server itself (fastapi-offline's copies), never from a CDN, so
they work on a network without the internet.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Protocol

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import RedirectResponse, Response
from fastapi_offline import FastAPIOffline
from prometheus_client import CONTENT_TYPE_LATEST
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match
from starlette.types import ASGIApp, Receive, Scope, Send

from agilegs.schemas import ErrorItem, codec
from agilegs.schemas.errors import ErrorCode

from ...errors import ServiceError, field_path
from ...sessions.registry import SessionRegistry
from ...settings import Settings
from ..gateway import Gateway
from ..metrics import Metrics
from .openapi import DESCRIPTION, build_openapi
from .routes import build_router, response

__all__ = ["create_app", "route_methods"]

log = logging.getLogger(__name__)

_STATUS_CODES = {
    400: ErrorCode.BAD_REQUEST,
    401: ErrorCode.UNAUTHORIZED,
    404: ErrorCode.NOT_FOUND,
    405: ErrorCode.METHOD_NOT_ALLOWED,
    406: ErrorCode.NOT_ACCEPTABLE,
    409: ErrorCode.CONFLICT,
    413: ErrorCode.PAYLOAD_TOO_LARGE,
    415: ErrorCode.UNSUPPORTED_MEDIA,
    422: ErrorCode.INVALID,
    429: ErrorCode.TOO_MANY,
}


class BearerAuth:
    """Pure ASGI middleware: every HTTP request must carry ``Authorization: Bearer <token>``
    (the gateway checks it) or gets 401."""

    def __init__(self, app: ASGIApp, gateway: Gateway) -> None:
        self.app = app
        self.gateway = gateway

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope["headers"])
        try:
            self.gateway.authenticate(headers.get(b"authorization"))
        except ServiceError as err:
            accept = headers.get(b"accept", b"").decode("latin-1") or None
            kind = codec.negotiate(accept) or codec.JSON
            reply = self.gateway.error_reply(err, kind, "http", "auth")
            await response(reply)(scope, receive, send)
            return
        await self.app(scope, receive, send)


class Served(Protocol):
    """What the app serves: one server instance (:class:`agilegs.service.server.Server`)."""

    settings: Settings
    gateway: Gateway
    registry: SessionRegistry
    metrics: Metrics

    def start(self) -> None: ...

    def close(self) -> None: ...

    def warming(self) -> str | None: ...


def create_app(server: Served, *, start: bool = True) -> FastAPI:
    """The FastAPI app of ``server``; its lifespan starts the server (sessions loaded, Zenoh
    joined; with ``start=False`` the caller has started it) and stops it on shutdown."""
    settings = server.settings
    gateway = server.gateway

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if start:
            server.start()
        try:
            yield
        finally:
            server.close()

    app = FastAPIOffline(
        title="agilegs",
        summary="AGILE-GS next-best-view service for active 3D Gaussian Splatting",
        description=DESCRIPTION,
        version=server.registry.health().version,
        lifespan=lifespan,
        docs_url="/docs",
        openapi_url="/openapi.json",
        swagger_ui_parameters={"validatorUrl": None},  # no request to a public validator
    )
    app.state.server = server

    @app.get("/", include_in_schema=False)
    async def root(request: Request) -> RedirectResponse:
        return RedirectResponse(f"{request.scope.get('root_path', '')}/docs")

    def error(request: Request, err: ServiceError) -> Response:
        kind = codec.negotiate(request.headers.get("accept")) or codec.JSON
        return response(gateway.error_reply(err, kind, "http", _op_name(request)))

    async def on_validation(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, RequestValidationError)
        items = [(field_path("", e.get("loc", ())), str(e.get("msg", "invalid")))
                 for e in exc.errors()]
        first = items[0] if items else ("request", "invalid")
        return error(request, ServiceError(
            422, ErrorCode.INVALID, f"{first[0]}: {first[1]}", first[0],
            [ErrorItem(field=f, message=msg) for f, msg in items]))

    async def on_http(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, StarletteHTTPException)
        code = _STATUS_CODES.get(exc.status_code, ErrorCode.INTERNAL)
        if exc.status_code == 405:
            allowed = route_methods(app, request.url.path)
            return error(request, ServiceError(
                405, code, f"{request.method} is not allowed on {request.url.path}; it "
                f"takes {', '.join(allowed)}", "method", supported=allowed))
        return error(request, ServiceError(exc.status_code, code, str(exc.detail), None))

    async def on_crash(request: Request, exc: Exception) -> Response:
        log.exception("internal error on %s %s", request.method, request.url.path)
        return error(request, ServiceError(500, ErrorCode.INTERNAL,
                                           f"internal error ({type(exc).__name__})", None))

    app.add_exception_handler(RequestValidationError, on_validation)
    app.add_exception_handler(StarletteHTTPException, on_http)
    app.add_exception_handler(Exception, on_crash)
    app.include_router(build_router(gateway))

    @app.get("/metrics", tags=["service"], summary="Prometheus metrics",
             response_class=Response,
             responses={200: {"content": {CONTENT_TYPE_LATEST: {"schema": {"type": "string"}}}}})
    async def get_metrics() -> Response:
        return Response(server.metrics.render(), media_type=CONTENT_TYPE_LATEST)

    @app.get("/readyz", tags=["service"], summary="Readiness: 503 with the reason while the "
             "server compiles its kernels at start (warm-up) or is saturated",
             response_class=Response)
    async def readyz() -> Response:
        # on the event loop, like /healthz (liveness): answers while every worker is busy
        reason = server.warming() or gateway.admission.saturation()
        if reason is None:
            return Response(codec.dump({"ready": True}, codec.JSON), media_type=codec.JSON)
        return Response(codec.dump({"ready": False, "reason": reason}, codec.JSON),
                        status_code=503, media_type=codec.JSON, headers={"Retry-After": "1"})

    app.openapi = lambda: build_openapi(app, settings)  # type: ignore[method-assign]
    if settings.token_value() is not None:
        app.add_middleware(BearerAuth, gateway=gateway)
    return app


_METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")


def route_methods(app: FastAPI, path: str) -> list[str]:
    """The HTTP methods that some route of ``app`` serves on ``path`` (sorted)."""
    allowed = []
    for method in _METHODS:
        scope = {"type": "http", "path": path, "root_path": "", "method": method}
        if any(route.matches(scope)[0] == Match.FULL for route in app.routes):
            allowed.append(method)
    return sorted(allowed)


def _op_name(request: Request) -> str:
    route = request.scope.get("route")
    return getattr(route, "name", None) or "unknown"
