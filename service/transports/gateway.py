"""The one request pipeline both transports use.

A transport turns what arrived into a :class:`Request` (operation, session, body bytes,
content type, accept, credentials, query parameters) and hands it to :meth:`Gateway.handle`,
which does, once for every transport:

1. authentication (bearer token, compared in constant time),
2. content negotiation (406), the body size limit and, before parsing, the count of its
   values (413),
3. decoding (JSON or msgpack by content type, 415 / 400; a raw .ply / .splat upload),
4. validation against the operation's request model (422 naming every field), and the
   decoded size of its images reserved against the memory budgets (413 / 503, see
   :mod:`agilegs.service.transports.admission`),
5. dispatch: here (:meth:`SessionRegistry.execute
   <agilegs.service.sessions.registry.SessionRegistry.execute>`), or through the
   :attr:`Gateway.router` to the instance that owns the session,
6. encoding of the answer or of the error body, in the type the request accepts (once per
   request and type: a decision's reply and its Zenoh publication share the bytes,
   :meth:`Gateway.encode`; ``get_gaussians`` also answers the ``.ply`` or ``.splat`` file
   that Accept prefers, :data:`~agilegs.schemas.codec.GAUSSIAN_FILE_TYPES`),
7. metrics, and the decision hooks after a selection made here.

A session operation whose session another instance of a cluster owns skips steps 3-5 when its
body is JSON or msgpack (or it has none): the request's bytes are forwarded as they came and
the owner's answer is passed back as it came (:meth:`Router.forward_bytes`); the owner decodes
and validates it.

Requests reach a worker through :meth:`Gateway.submit`, which admits them first (per-session
and server-wide queue limits, 429 / 503) and runs reads and compute on separate threads; the
request's :class:`~agilegs.service.transports.admission.Ticket` (its deadline, or its client gone)
is checked between the steps and inside long computations, and a cancelled request stops there
(504 ``deadline_exceeded``) having changed nothing.

It returns a :class:`Reply` (status, bytes, media type); a write refused for lack of space
is answered 507 ``insufficient_storage`` (and counted), a bug in a handler is logged and
answered 500. The HTTP routes (:mod:`agilegs.service.transports.http.routes`) and the Zenoh
queryables and subscriptions (:mod:`agilegs.service.transports.zenoh.adapter`) are glue around it.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import os
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Protocol

from pydantic import BaseModel, ValidationError

from agilegs.schemas import OPERATIONS, ErrorBody, GaussiansOut, SelectResponse, codec
from agilegs.schemas.codec import GAUSSIAN_FILE_TYPES
from agilegs.schemas.errors import ErrorCode

from ..errors import ServiceError, insufficient_storage, invalid, is_disk_full
from ..sessions import requests as applied_requests
from ..sessions.convert import gaussians_file
from ..sessions.registry import SessionRegistry
from ..settings import Settings
from .admission import (
    CLIENT_CLOSED,
    CLIENT_GONE,
    READ_OPS,
    Admission,
    Ticket,
    count_values,
    request_decoded_bytes,
)
from .metrics import Metrics
from .requests import QueryParams, parse_request

__all__ = ["RAW_TYPES", "Forwarded", "Gateway", "Reply", "Request", "Router", "file_format",
           "request_media_types"]

log = logging.getLogger(__name__)

RAW_TYPES = ("application/octet-stream", "application/x-ply", "application/x-splat")
"""Content types of a raw .ply / .splat upload to ``set_gaussians``."""


def request_media_types(op: str) -> list[str]:
    """The body media types operation ``op`` reads (JSON, msgpack; raw files for
    ``set_gaussians``)."""
    return [codec.JSON, codec.MSGPACK] + (list(RAW_TYPES) if op == "set_gaussians" else [])


def file_format(op: str, accept: str | None) -> str | None:
    """The file (``ply`` / ``splat``) that ``accept`` prefers for ``op``, where ``op`` answers
    one (``get_gaussians``); None: JSON or msgpack."""
    return codec.preferred_file(accept, GAUSSIAN_FILE_TYPES) if op == "get_gaussians" else None


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
        deadline_ms: the client's own deadline in ms from arrival (HTTP ``X-Deadline-Ms``,
            Zenoh ``deadline_ms`` parameter); the server's ``request_deadline`` caps it.
        request_id: a write's request id (HTTP ``Idempotency-Key``, Zenoh ``request_id``
            parameter, :mod:`agilegs.schemas.requests`): a write applied under it already
            is answered again, not applied.
        ticket: its deadline and cancellation (set by :meth:`Gateway.submit`, or here).
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
    deadline_ms: float | None = None
    request_id: str | None = None
    ticket: Ticket | None = None


class Reply:
    """The answer: HTTP status, encoded body and its media type; ``model`` is the response
    (None for an error), ``error`` the refusal (None for a success).

    The answer of another instance passed through as it came is decoded into ``model`` only
    when a caller reads it (``decode``)."""

    def __init__(self, status: int, body: bytes, media_type: str,
                 model: BaseModel | None = None, error: ServiceError | None = None, *,
                 decode: Callable[[], BaseModel] | None = None) -> None:
        self.status = status
        self.body = body
        self.media_type = media_type
        if error is not None:
            # the refusal's traceback holds the frames that raised it, and through them the
            # request (its body) and this reply: a cycle only a full collection would free
            error.__traceback__ = None
            error.__context__ = error.__cause__ = None
        self.error = error
        self._model = model
        self._decode = decode

    @property
    def model(self) -> BaseModel | None:
        if self._model is None and self._decode is not None:
            self._model = self._decode()
            self._decode = None
        return self._model

    @property
    def ok(self) -> bool:
        return self.error is None

    def __repr__(self) -> str:
        return (f"Reply(status={self.status}, media_type={self.media_type!r}, "
                f"{len(self.body)} bytes, error={self.error!r})")


@dataclass(frozen=True)
class Forwarded:
    """The answer of the instance that owns a session, as it came: ``ok`` (a response) or an
    error reply, its bytes and their media type (JSON or msgpack)."""

    ok: bool
    payload: bytes
    kind: str


class Router(Protocol):
    """Where an operation runs in a cluster
    (:class:`agilegs.service.transports.zenoh.cluster.ClusterNode`)."""

    def route(self, op: str, session: str | None, req: BaseModel | None, *,
              run_local: Callable[[], BaseModel], instance: str | None, local: bool,
              request_id: str | None = None) -> BaseModel: ...

    def owned_elsewhere(self, op: str, session: str | None) -> bool:
        """Whether ``op`` is a session operation on a session this instance does not hold,
        in a cluster (its request may go to the owner as it came)."""

    def forward_bytes(self, op: str, session: str, body: bytes | None, kind: str,
                      request_id: str | None = None) -> Forwarded | None:
        """Forward a request as it came (``body`` in media type ``kind``, or none: the answer
        comes in ``kind``; with its ``request_id``) to the instance that owns the session;
        None when no instance answers and this one is not in a cluster (it runs the request
        itself)."""


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
        # a session that keeps more compute queued is served at a lower OS priority
        self.background_executor = ThreadPoolExecutor(
            settings.workers, thread_name_prefix="agilegs-bg",
            initializer=_lower_priority, initargs=(settings.background_nice,))
        self.read_executor = ThreadPoolExecutor(settings.read_workers,
                                                thread_name_prefix="agilegs-read")
        self.admission = Admission(settings)
        token = settings.token_value()
        self._digest = hashlib.sha256(token.encode()).digest() if token else None
        self.router: Router | None = None
        self.decision_hooks: list[Callable[[str, SelectResponse], None]] = []
        self._encoded = threading.local()  # this thread's request: its encodings so far

    def close(self) -> None:
        self.executor.shutdown(wait=True, cancel_futures=True)
        self.background_executor.shutdown(wait=True, cancel_futures=True)
        self.read_executor.shutdown(wait=True, cancel_futures=True)

    def ticket(self, req: Request) -> Ticket:
        """``req``'s ticket: its deadline is ``request_deadline`` s after arrival, or the
        client's ``deadline_ms`` when sooner."""
        if req.ticket is None:
            limit = self.settings.request_deadline
            if req.deadline_ms is not None and req.deadline_ms >= 0:
                limit = min(limit, req.deadline_ms / 1e3)
            req.ticket = Ticket(time.monotonic() - (time.perf_counter() - req.t0) + limit)
        return req.ticket

    def submit(self, req: Request, run: Callable[[Request], Reply] | None = None
               ) -> Future[Reply]:
        """Admit ``req`` and run it (``run``, default :meth:`handle`) on a worker: reads on
        the read threads at once; compute on the compute threads, one at a time per session
        (the next one waits in the session's queue, holding no thread, until the previous
        one ends). A refusal (429, 503, the server stopping) is a finished future of the
        error reply, and ``run`` is not called."""
        run = run or self.handle
        self.ticket(req)
        kind = codec.negotiate(req.accept) or codec.JSON
        try:
            self.admission.enter(req.op, req.session)
        except ServiceError as err:
            return _done(self.error_reply(err, kind, req.transport, req.op))
        out: Future[Reply] = Future()
        read = req.op in READ_OPS
        # admitted behind another of its session's: a session keeping several queued is
        # served on the lower-priority threads, so that it cannot starve the others' CPU
        busy = (not read and req.session is not None
                and self.admission.queued(req.session) > 1)

        def job() -> None:
            try:
                with self.admission.running_compute(req.op):
                    reply = run(req)
            except BaseException as exc:  # run never raises; if it did, the caller hears
                out.set_exception(exc)
            else:
                out.set_result(reply)
            finally:
                self.admission.leave(req.op, req.session)
                if not read and req.session is not None:
                    nxt = self.admission.next_of(req.session)
                    if nxt is not None:
                        nxt()

        def start() -> None:
            try:
                pool = (self.read_executor if read else
                        self.background_executor if busy else self.executor)
                pool.submit(job)
            except RuntimeError:  # the executor is shut down: the server is stopping
                self.admission.leave(req.op, req.session)
                stopping = ServiceError(503, ErrorCode.UNAVAILABLE, "the server is stopping")
                out.set_result(self.error_reply(stopping, kind, req.transport, req.op))
                if not read and req.session is not None:
                    nxt = self.admission.next_of(req.session)
                    if nxt is not None:
                        nxt()

        if read or req.session is None or self.admission.start_or_queue(req.session, start):
            start()
        return out

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
    def negotiate(accept: str | None, op: str | None = None) -> str:
        """The media type of ``op``'s answers and errors for ``accept`` (JSON or msgpack; JSON
        when ``accept`` names only a file ``op`` answers); 406 if it names none of them."""
        kind = codec.negotiate(accept)
        if kind is None and op is not None and file_format(op, accept) is not None:
            return codec.JSON
        if kind is None:
            files = list(GAUSSIAN_FILE_TYPES.values()) if op == "get_gaussians" else []
            supported = [codec.JSON, codec.MSGPACK, *files]
            raise ServiceError(406, ErrorCode.NOT_ACCEPTABLE,
                               f"Accept names neither {codec.JSON} nor {codec.MSGPACK}"
                               + (f" nor {' nor '.join(files)}" if files else ""),
                               "header.accept", supported=supported)
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
        base = _base_type(content_type)
        if op == "set_gaussians" and params.get("format") not in (None, "ply", "splat"):
            raise invalid("query.format", "query.format: must be 'ply' or 'splat'")
        if op == "set_gaussians" and base in RAW_TYPES:
            if not body:
                raise invalid("body", f"body: the {base} body is empty (a .ply or .splat "
                                      "file is required)")
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
        self._encoded.cache = {}
        self._encoded.ticket = self.ticket(req)
        try:
            return self._handle(req)
        finally:
            self._encoded.cache = None
            self._encoded.ticket = None

    def _handle(self, req: Request) -> Reply:
        kind = codec.negotiate(req.accept) or codec.JSON
        ticket = self.ticket(req)
        try:
            ticket.check()
            spec = OPERATIONS.get(req.op)
            if spec is None or (spec.scope == "session") != (req.session is not None):
                where = "a session operation" if req.session is not None else "a service operation"
                raise ServiceError(404, ErrorCode.NOT_FOUND,
                                   f"{req.op!r} is not {where}" if spec is not None
                                   else f"unknown operation {req.op!r}", "key")
            if not req.authenticated:
                self.authenticate(req.credentials, req.credentials_field)
            kind = self.negotiate(req.accept, req.op)
            fmt = file_format(req.op, req.accept)
            if req.body is not None:
                self.check_size(len(req.body))
                if req.body and not (req.op == "set_gaussians" and _base_type(
                        req.content_type) in RAW_TYPES):
                    count_values(req.body, codec.media_type(req.content_type) or codec.JSON,
                                 self.settings.max_body_items)
            local = req.local
            as_it_came = None if fmt is not None else self._as_it_came(req, kind)
            if as_it_came is not None:
                assert self.router is not None and req.session is not None
                got = self.router.forward_bytes(req.op, req.session, req.body or None,
                                                as_it_came, request_id=req.request_id)
                if got is not None:
                    return self._forwarded_reply(req, got, kind)
                local = True  # no instance answers, and this one is alone: it answers
            payload = self.decode(req.op, req.body, req.content_type, req.params)
            model = parse_request(req.op, payload)
            del payload
            ticket.check()
            with self.admission.decoded(request_decoded_bytes(req.op, model)):
                result = self.dispatch(req.op, req.session, model, t0=req.t0,
                                       instance=req.params.get("instance"), local=local,
                                       request_id=req.request_id)
            if fmt is not None:  # the owner of the session answers the arrays, made a file here
                assert isinstance(result, GaussiansOut)
                body, kind = gaussians_file(result, fmt), GAUSSIAN_FILE_TYPES[fmt]
            else:
                body = self.encode(result, kind)
        except ServiceError as err:
            if ticket.reason == CLIENT_GONE:
                return self.gone_reply(err, kind, req.transport, req.op)
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

    def _as_it_came(self, req: Request, kind: str) -> str | None:
        """The media type ``req`` goes to the session's owner in, as it came (its body's, or
        ``kind`` without a body); None when it runs here, or cannot go as it came (a body
        neither JSON nor msgpack, fields in query parameters: the validated request goes)."""
        if (req.local or self.router is None
                or not self.router.owned_elsewhere(req.op, req.session)):
            return None
        if req.body:
            return codec.media_type(req.content_type)
        return kind if OPERATIONS[req.op].request is None else None

    def _forwarded_reply(self, req: Request, got: Forwarded, kind: str) -> Reply:
        """The owner's answer as the reply, its bytes as they came when they are in
        ``kind``."""
        if not got.ok:
            err = _owner_error(req.op, got)
            self.count(req.transport, req.op, err.status, err.code)
            body = got.payload if got.kind == kind else codec.dump(err.body(), kind)
            return Reply(err.status, body, kind, error=err)
        body = got.payload
        if got.kind != kind:  # a body in one type, the answer asked in the other
            body = codec.dump(_owner_answer(req.op, got), kind)
        self.count(req.transport, req.op, 200)
        return Reply(200, body, kind, decode=lambda: _owner_answer(req.op, got))

    def encode(self, model: BaseModel, kind: str) -> bytes:
        """``model`` as ``kind`` bytes; within a request each model is encoded once per type
        (the reply and a hook's publication of it share the bytes)."""
        cache: dict[tuple[int, str], tuple[BaseModel, bytes]] | None = getattr(
            self._encoded, "cache", None)
        if cache is None:
            return codec.dump(model, kind)
        hit = cache.get((id(model), kind))
        if hit is not None and hit[0] is model:
            return hit[1]
        data = codec.dump(model, kind)
        cache[(id(model), kind)] = (model, data)
        return data

    def dispatch(self, op: str, session: str | None, req: BaseModel | None, *,
                 t0: float | None = None, instance: str | None = None, local: bool = False,
                 request_id: str | None = None) -> BaseModel:
        """Run a validated request where it belongs: through the router in a cluster, here
        otherwise."""

        def run_local() -> BaseModel:
            return self.execute(op, session, req, t0=t0, request_id=request_id)

        if self.router is None:
            return run_local()
        return self.router.route(op, session, req, run_local=run_local, instance=instance,
                                 local=local, request_id=request_id)

    def execute(self, op: str, session: str | None, req: BaseModel | None, *,
                t0: float | None = None, request_id: str | None = None) -> BaseModel:
        """Run it here; a selection gets its ``server_ms``, is counted and goes to the hooks."""
        ticket: Ticket | None = getattr(self._encoded, "ticket", None)
        result = self.registry.execute(op, session, req,
                                       check=ticket.check if ticket is not None else None,
                                       request_id=request_id)
        if isinstance(result, SelectResponse) and not applied_requests.was_replayed():
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

    def gone_reply(self, err: ServiceError, kind: str, transport: str, op: str,
                   why: str = "the client disconnected") -> Reply:
        """The reply of a request whose client hung up (nobody reads it: its body is
        empty): logged once at INFO, counted as status 499 (not an error of the server)."""
        log.info("%s (%s): %s; the request was cancelled, nothing was changed", op, transport,
                 why)
        self.count(transport, op, CLIENT_CLOSED)
        return Reply(CLIENT_CLOSED, b"", kind, error=err)

    def count(self, transport: str, op: str, status: int, code: str | None = None) -> None:
        if self.metrics is not None:
            self.metrics.observe_request(transport, op, status, code)


def _lower_priority(nice: int) -> None:
    """Lower this worker thread's OS scheduling priority by ``nice`` (Linux: per thread;
    elsewhere, or refused, nothing)."""
    if nice <= 0 or not hasattr(os, "setpriority"):
        return
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + nice)
    except OSError:
        log.debug("could not lower the priority of a background worker", exc_info=True)


def _base_type(content_type: str | None) -> str:
    return (content_type or "").split(";", 1)[0].strip().lower()


def _done(reply: Reply) -> Future[Reply]:
    fut: Future[Reply] = Future()
    fut.set_result(reply)
    return fut


def _owner_answer(op: str, got: Forwarded) -> BaseModel:
    """The owner's answer to ``op`` decoded and validated (502 if it is malformed)."""
    spec = OPERATIONS[op]
    assert spec.response is not None
    try:
        return spec.response.model_validate(codec.load(got.payload, got.kind))
    except (codec.DecodeError, ValidationError) as exc:
        raise ServiceError(502, ErrorCode.BAD_GATEWAY, f"{op}: the owner's answer is "
                           f"malformed: {exc}") from None


def _owner_error(op: str, got: Forwarded) -> ServiceError:
    """The owner's error reply as the error it names (its status, code, message, field)."""
    try:
        info = ErrorBody.model_validate(codec.load(got.payload, got.kind)).error
    except (codec.DecodeError, ValidationError):
        return ServiceError(502, ErrorCode.BAD_GATEWAY, f"{op}: the owner's error reply is "
                            "malformed")
    return ServiceError(info.status, info.code, info.message, info.field, list(info.errors),
                        info.supported, limit=info.limit, retry_after=info.retry_after,
                        estimate=info.estimate)
