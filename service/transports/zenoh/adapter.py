"""The Zenoh transport: queryables, subscriptions and the decision publication, as glue over
the gateway.

Key expressions come from :mod:`agilegs.schemas.keys`. A query becomes a gateway
:class:`~agilegs.service.transports.gateway.Request` (its payload msgpack, or JSON when the query's
encoding says so, refused with 415 like over HTTP when it names another type; its attachment
the credentials; its ``deadline_ms`` parameter its deadline, which the SDK sets to its query
timeout; ``get_gaussians``' ``format`` parameter, ``ply`` or ``splat``, asks for the file
as HTTP's Accept does, answered with the encoding ``application/x-ply`` /
``application/x-splat``) admitted and run in a worker thread (:meth:`Gateway.submit
<agilegs.service.transports.gateway.Gateway.submit>`), and is answered with
the reply or an error reply carrying the same :class:`~agilegs.schemas.errors.ErrorBody` as
over HTTP. Frames and pools published by a robot are applied in arrival order by one thread; a
refused one is published on ``agilegs/<session>/errors``. Every decision made on this
instance (over HTTP or Zenoh) is published on ``agilegs/<session>/decisions``.

Who may connect and which keys they may use is Zenoh's own business, set up from the
server's settings by :mod:`agilegs.service.transports.zenoh.security` (TLS, usrpwd, access control).

Which keys this instance declares (the ``@service`` and ``@instances/<id>`` queryables, and
each owned session's queryable and subscribers) is :mod:`agilegs.service.transports.zenoh.cluster`'s
business.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Any

from agilegs.client.zenoh_rpc import open_session
from agilegs.schemas import SelectResponse, codec, keys
from agilegs.schemas.codec import GAUSSIAN_FILE_TYPES
from agilegs.schemas.errors import ErrorCode
from agilegs.schemas.requests import REQUEST_ID_PARAM

from ...errors import ServiceError
from ...settings import Settings
from ..admission import parse_deadline_ms
from ..gateway import Gateway, Reply, Request
from ..requests import parse_request_id
from .cluster import ClusterNode
from .security import zenoh_settings

__all__ = ["ZenohAdapter", "content_type", "reply_kind"]

log = logging.getLogger(__name__)

_STOP = object()


_DEFAULT_ENCODINGS = ("", "zenoh/bytes")


def content_type(encoding: Any) -> str:
    """The media type of a query's or sample's payload: its Zenoh encoding, msgpack when it
    names none (the gateway answers 415 to one it does not read, as over HTTP)."""
    text = str(encoding) if encoding is not None else ""
    return codec.MSGPACK if text.split(";", 1)[0].strip() in _DEFAULT_ENCODINGS else text


def reply_kind(encoding: Any) -> str:
    """The media type of the answer: JSON for a JSON payload, msgpack otherwise."""
    return codec.JSON if codec.media_type(content_type(encoding)) == codec.JSON else codec.MSGPACK


class ZenohAdapter:
    """Serves the gateway over Zenoh until :meth:`close`.

    Args:
        gateway: the request pipeline.
        cluster: which keys this instance declares (it joins the cluster on :meth:`start`).
        settings: the Zenoh mode and endpoints.
    """

    def __init__(self, gateway: Gateway, cluster: ClusterNode, settings: Settings) -> None:
        self.gateway = gateway
        self.cluster = cluster
        self.settings = settings
        self.session: Any = None
        self._inbox: queue.Queue[Any] = queue.Queue()
        self._worker: threading.Thread | None = None
        self._closing = False

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        mode = self.settings.zenoh_mode
        listen = [] if mode == "client" else self.settings.zenoh_listen
        self.session = open_session(listen, self.settings.zenoh_connect, mode,
                                    zenoh_settings(self.settings))
        try:
            self.cluster.attach(self.session, on_query=self._on_query,
                                on_session_query=self._on_session_query,
                                on_sample=self._on_sample)
        except Exception:
            self.session.close()
            self.session = None
            raise
        self._worker = threading.Thread(target=self._drain, name="agilegs-zenoh-inbox",
                                        daemon=True)
        self._worker.start()
        self.gateway.decision_hooks.append(self.publish_decision)
        self.gateway.registry.zenoh_enabled = True
        log.info("zenoh: %s %r, listening on %s, connecting to %s", mode,
                 self.cluster.instance_id, listen, self.settings.zenoh_connect)

    def close(self) -> None:
        """Undeclare everything and close the session (a declared callback left behind
        would keep the process from exiting)."""
        self._closing = True
        if self.publish_decision in self.gateway.decision_hooks:
            self.gateway.decision_hooks.remove(self.publish_decision)
        self.gateway.registry.zenoh_enabled = False
        self.cluster.detach()
        self._inbox.put(_STOP)
        if self._worker is not None:
            self._worker.join(timeout=10)
        if self.session is not None:
            self.session.close()
            self.session = None

    # ------------------------------------------------------------------ queries
    def _on_session_query(self, query: Any) -> None:
        key = str(query.key_expr)
        if "*" in key or "$" in key:  # a wildcard query is not addressed to one session
            query.drop()
            return
        try:
            session, op = keys.parse_session_key(key)
        except ValueError:
            query.drop()
            return
        self._on_query(query, op, session)

    def _on_query(self, query: Any, op: str, session: str | None, local: bool = False,
                  reply_key: str | None = None) -> None:
        t0 = time.perf_counter()
        try:
            req = self._request(query, op, session, t0, local)
        except ServiceError as err:
            reply = self.gateway.error_reply(err, reply_kind(query.encoding), "zenoh", op)
            self._reply(query, reply.body, reply.media_type, None, ok=False)
            query.drop()
            return
        if op == "health" or (local and op == "list_sessions"):  # cheap reads: inline
            self._answer(query, req, reply_key)
            return
        ran: list[bool] = []

        def run(r: Request) -> Reply:
            ran.append(True)
            return self._answer(query, r, reply_key)

        fut = self.gateway.submit(req, run)
        if fut.done() and not ran:  # refused (429, 503): never ran, answered here
            reply = fut.result()
            self._reply(query, reply.body, reply.media_type, None, ok=False)
            query.drop()

    @staticmethod
    def _request(query: Any, op: str, session: str | None, t0: float, local: bool
                 ) -> Request:
        """The gateway request of a query; its ``deadline_ms`` parameter (the client's query
        timeout) bounds the work."""
        kind = reply_kind(query.encoding)
        params = {}
        if op == "create_session" and query.parameters.get("instance") is not None:
            params["instance"] = query.parameters.get("instance")
        deadline_ms = parse_deadline_ms(query.parameters.get("deadline_ms"), "query.deadline_ms")
        request_id = parse_request_id(query.parameters.get(REQUEST_ID_PARAM),
                                      f"query.{REQUEST_ID_PARAM}")
        accept = kind
        fmt = query.parameters.get("format") if op == "get_gaussians" else None
        if fmt is not None:  # the file, as Accept asks for it over HTTP; errors in ``kind``
            if fmt not in GAUSSIAN_FILE_TYPES:
                raise ServiceError(422, ErrorCode.INVALID, "query.format: must be one of "
                                   f"{', '.join(GAUSSIAN_FILE_TYPES)}", "query.format")
            accept = f"{GAUSSIAN_FILE_TYPES[fmt]}, {kind};q=0.5"
        return Request(
            op=op, session=session,
            body=query.payload.to_bytes() if query.payload is not None else b"",
            content_type=content_type(query.encoding), accept=accept,
            credentials=query.attachment.to_bytes() if query.attachment is not None
            else None,
            credentials_field="attachment", params=params, transport="zenoh", t0=t0,
            local=local, deadline_ms=deadline_ms, request_id=request_id,
        )

    def _answer(self, query: Any, req: Request, reply_key: str | None = None) -> Reply:
        try:
            reply = self.gateway.handle(req)
            self._reply(query, reply.body, reply.media_type, reply_key, ok=reply.ok)
            return reply
        finally:
            query.drop()

    @staticmethod
    def _reply(query: Any, body: bytes, kind: str, reply_key: str | None, *, ok: bool) -> None:
        try:
            if ok:
                query.reply(reply_key or query.key_expr, body, encoding=kind)
            else:
                query.reply_err(body, encoding=kind)
        except Exception:
            log.debug("zenoh: could not send a reply", exc_info=True)

    # ------------------------------------------------------------------ subscriptions
    def _on_sample(self, sample: Any) -> None:
        if not self._closing:
            self._inbox.put((str(sample.key_expr), sample.payload.to_bytes(),
                             content_type(sample.encoding),
                             sample.attachment.to_bytes() if sample.attachment is not None
                             else None))

    def _drain(self) -> None:
        while True:
            item = self._inbox.get()
            if item is _STOP:
                return
            key, raw, kind, attachment = item
            try:
                session, topic = keys.parse_session_key(key)
            except ValueError:
                continue
            op = "add_observations" if topic == keys.FRAMES else "set_pool"
            reply = self.gateway.handle(Request(
                op=op, session=session, body=raw, content_type=kind, accept=codec.MSGPACK,
                credentials=attachment, credentials_field="attachment", transport="zenoh",
                local=True,
            ))
            if not reply.ok:
                self._publish(keys.session_key(session, keys.ERRORS), reply.body)

    def _publish(self, key: str, body: bytes) -> None:
        try:
            self.session.put(key, body, encoding=codec.MSGPACK)
        except Exception:
            log.debug("zenoh: could not publish on %s", key, exc_info=True)

    # ------------------------------------------------------------------ decisions
    def publish_decision(self, session: str, resp: SelectResponse) -> None:
        if self.session is None or self._closing:
            return
        self.session.put(keys.session_key(session, keys.DECISIONS),
                         self.gateway.encode(resp, codec.MSGPACK), encoding=codec.MSGPACK)
