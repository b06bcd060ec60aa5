"""The one request pipeline both transports use.

A transport turns what arrived into a :class:`Request` (operation, session, body bytes,
content type, accept, credentials, query parameters) and hands it to :meth:`Gateway.handle`,
which does, once for every transport:

1. authentication (bearer token, compared in constant time),
2. content negotiation (406) and the body size limit (413),
3. decoding (JSON or msgpack by content type, 415 / 400; a raw .ply / .splat upload),
4. validation against the operation's request model (422 naming every field),
5. dispatch: here (:meth:`SessionRegistry.execute
   <agilegs.service.sessions.registry.SessionRegistry.execute>`), or through the
   :attr:`Gateway.router` to the instance that owns the session,
6. encoding of the answer or of the error body, in the type the request accepts,
7. metrics, and the decision hooks after a selection made here.

It returns a :class:`Reply` (status, bytes, media type); a write refused for lack of space
is answered 507 ``insufficient_storage`` (and counted), a bug in a handler is logged and
answered 500. The HTTP routes (:mod:`agilegs.service.http_routes`) and the Zenoh queryables
and subscriptions (:mod:`agilegs.service.zenoh_adapter`) are glue around it.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Protocol

from pydantic import BaseModel

from agilegs.schemas import codec
from agilegs.schemas.errors import ErrorCode
from agilegs.schemas.models import SelectResponse
from agilegs.schemas.ops import OPERATIONS

from .errors import ServiceError, insufficient_storage, invalid, is_disk_full
from .metrics import Metrics
from .sessions.registry import QueryParams, SessionRegistry, parse_request
from .settings import Settings

__all__ = ["RAW_TYPES", "Gateway", "Reply", "Request", "Router", "request_media_types"]

log = logging.getLogger(__name__)

RAW_TYPES = ("application/octet-stream", "application/x-ply", "application/x-splat")
"""Content types of a raw .ply / .splat upload to ``set_gaussians``."""


def request_media_types(op: str) -> list[str]:
    """The body media types operation ``op`` reads (JSON, msgpack; raw files for
    ``set_gaussians``)."""
    return [codec.JSON, codec.MSGPACK] + (list(RAW_TYPES) if op == "set_gaussians" else [])


@dataclass
class Request:
    """One request as a transport received it.

    Attributes:
        op: the operation name (:data:`agilegs.schemas.ops.OPERATIONS`).
        session: the session id of a session operation.
        body: the body bytes (None: the operation takes none, or none came).
        content_type: the body's media type (HTTP Content-Type, Zenoh encoding).
        accept: the media types the caller accepts (HTTP Accept; Zenoh: the query's own).
        credentials: ``Bearer <token>`` as sent (HTTP Authorization, Zenoh attachment).
        credentials_field: where the credentials travel, named in a 401.
        params: query parameters (``format`` of a raw upload, ``instance`` of a create).
        transport: ``http`` or ``zenoh`` (metrics).
        t0: ``time.perf_counter()`` at arrival (a selection's ``server_ms``).
        authenticated: the transport checked the credentials already.
        local: run it here whatever the cluster holds (queries on this instance's keys).
    """

    op: str
    session: str | None = None
    body: bytes | None = None
    content_type: str | None = None
    accept: str | None = None
    credentials: bytes | None = None
    credentials_field: str = "header.authorization"
    params: Mapping[str, str] = field(default_factory=dict)
    transport: str = "http"
    t0: float = field(default_factory=time.perf_counter)
    authenticated: bool = False
    local: bool = False


@dataclass
class Reply:
    """The answer: HTTP status, encoded body and its media type; ``model`` is the response
    (None for an error), ``error`` the refusal (None for a success)."""

    status: int
    body: bytes
    media_type: str
    model: BaseModel | None = None
    error: ServiceError | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


class Router(Protocol):
    """Where an operation runs in a cluster (:class:`agilegs.service.cluster.ClusterNode`)."""

    def route(self, op: str, session: str | None, req: BaseModel | None, *,
              run_local: Callable[[], BaseModel], instance: str | None, local: bool
              ) -> BaseModel: ...


class Gateway:
    """The request pipeline (see the module docstring).

    Args:
        registry: this server's sessions.
        settings: the token, the body limit and the worker count.
        metrics: where requests and selections are counted (None: nowhere).
    """

    def __init__(self, registry: SessionRegistry, settings: Settings,
                 metrics: Metrics | None = None) -> None:
        self.registry = registry
        self.settings = settings
        self.metrics = metrics
        self.executor = ThreadPoolExecutor(settings.workers, thread_name_prefix="agilegs")
        token = settings.token_value()
        self._digest = hashlib.sha256(token.encode()).digest() if token else None
        self.router: Router | None = None
        self.decision_hooks: list[Callable[[str, SelectResponse], None]] = []

    def close(self) -> None:
        self.executor.shutdown(wait=True, cancel_futures=True)

    # ------------------------------------------------------------------ the steps
    def authenticate(self, credentials: bytes | None, field: str = "header.authorization"
                     ) -> None:
        """401 unless ``credentials`` is ``Bearer <token>`` (when the server has a token)."""
        if self._digest is None:
            return
        given = credentials or b""
        if given[:7].lower() == b"bearer " and hmac.compare_digest(
                hashlib.sha256(given[7:].strip()).digest(), self._digest):
            return
        hint = " (the attachment 'Bearer <token>')" if field == "attachment" else ""
        raise ServiceError(401, ErrorCode.UNAUTHORIZED, f"missing or wrong bearer token{hint}",
                           field)

    @staticmethod
    def negotiate(accept: str | None) -> str:
        """The response media type for ``accept``; 406 if it names neither kind."""
        kind = codec.negotiate(accept)
        if kind is None:
            raise ServiceError(406, ErrorCode.NOT_ACCEPTABLE,
                               f"Accept names neither {codec.JSON} nor {codec.MSGPACK}",
                               "header.accept", supported=[codec.JSON, codec.MSGPACK])
        return kind

    def check_size(self, size: int) -> None:
        """413 if a body of ``size`` bytes exceeds ``max_body_bytes``."""
        limit = self.settings.max_body_bytes
        if size > limit:
            raise ServiceError(413, ErrorCode.PAYLOAD_TOO_LARGE,
                               f"body exceeds max_body_bytes ({limit})", "body")

    @staticmethod
    def decode(op: str, body: bytes | None, content_type: str | None,
               params: Mapping[str, str]) -> Any:
        """Body bytes to Python data (None when the operation takes no body)."""
        spec = OPERATIONS[op]
        if spec.request is None:
            return None
        if spec.query and not body:  # HTTP: the fields are query parameters
            return QueryParams(params)
        base = (content_type or "").split(";", 1)[0].strip().lower()
        if op == "set_gaussians" and params.get("format") not in (None, "ply", "splat"):
            raise invalid("query.format", "query.format: must be 'ply' or 'splat'")
        if op == "set_gaussians" and base in RAW_TYPES and body:
            fmt = params.get("format") or ("ply" if body[:4] == b"ply\n" else "splat")
            return {"format": fmt, "data": body}
        kind = codec.media_type(content_type)
        if kind is None:
            raise ServiceError(415, ErrorCode.UNSUPPORTED_MEDIA,
                               f"Content-Type {content_type!r} is neither {codec.JSON} nor "
                               f"{codec.MSGPACK}", "header.content-type",
                               supported=request_media_types(op))
        if not body:
            raise invalid("body", "body: a request body is required")
        try:
            return codec.load(body, kind)
        except codec.DecodeError as exc:
            raise ServiceError(400, ErrorCode.BAD_REQUEST, str(exc), "body") from None

    # ------------------------------------------------------------------ the pipeline
    def handle(self, req: Request) -> Reply:
        """Run ``req`` through every step; never raises."""
        kind = codec.negotiate(req.accept) or codec.JSON
        try:
            spec = OPERATIONS.get(req.op)
            if spec is None or (spec.scope == "session") != (req.session is not None):
                where = "a session operation" if req.session is not None else "a service operation"
                raise ServiceError(404, ErrorCode.NOT_FOUND,
                                   f"{req.op!r} is not {where}" if spec is not None
                                   else f"unknown operation {req.op!r}", "key")
            if not req.authenticated:
                self.authenticate(req.credentials, req.credentials_field)
            kind = self.negotiate(req.accept)
            if req.body is not None:
                self.check_size(len(req.body))
            payload = self.decode(req.op, req.body, req.content_type, req.params)
            model = parse_request(req.op, payload)
            result = self.dispatch(req.op, req.session, model, t0=req.t0,
                                   instance=req.params.get("instance"), local=req.local)
            body = codec.dump(result, kind)
        except ServiceError as err:
            return self.error_reply(err, kind, req.transport, req.op)
        except Exception as exc:
            if is_disk_full(exc):  # nothing was changed: the store undoes a refused write
                log.warning("%s (%s) refused: the state folder is full (%s)", req.op,
                            req.transport, exc)
                if self.metrics is not None:
                    self.metrics.observe_refused_write(req.transport, req.op)
                return self.error_reply(insufficient_storage(exc), kind, req.transport, req.op)
            log.exception("internal error on %s (%s)", req.op, req.transport)
            crash = ServiceError(500, ErrorCode.INTERNAL,
                                 f"internal error ({type(exc).__name__})")
            return self.error_reply(crash, kind, req.transport, req.op)
        self.count(req.transport, req.op, 200)
        return Reply(200, body, kind, model=result)

    def dispatch(self, op: str, session: str | None, req: BaseModel | None, *,
                 t0: float | None = None, instance: str | None = None, local: bool = False
                 ) -> BaseModel:
        """Run a validated request where it belongs: through the router in a cluster, here
        otherwise."""

        def run_local() -> BaseModel:
            return self.execute(op, session, req, t0=t0)

        if self.router is None:
            return run_local()
        return self.router.route(op, session, req, run_local=run_local, instance=instance,
                                 local=local)

    def execute(self, op: str, session: str | None, req: BaseModel | None, *,
                t0: float | None = None) -> BaseModel:
        """Run it here; a selection gets its ``server_ms``, is counted and goes to the hooks."""
        result = self.registry.execute(op, session, req)
        if isinstance(result, SelectResponse):
            if t0 is not None:
                result.server_ms = (time.perf_counter() - t0) * 1e3
            if self.metrics is not None:
                self.metrics.observe_selection(result)
            for hook in self.decision_hooks:
                try:
                    hook(result.session, result)
                except Exception:  # a hook must never fail the selection
                    log.exception("decision hook failed")
        return result

    # ------------------------------------------------------------------ answers
    def error_reply(self, err: ServiceError, kind: str, transport: str, op: str) -> Reply:
        """The error body of ``err`` in ``kind``, counted."""
        self.count(transport, op, err.status, err.code)
        return Reply(err.status, codec.dump(err.body(), kind), kind, error=err)

    def count(self, transport: str, op: str, status: int, code: str | None = None) -> None:
        if self.metrics is not None:
            self.metrics.observe_request(transport, op, status, code)
