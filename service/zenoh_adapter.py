"""The Zenoh transport: queryables, subscriptions and the decision publication.

Key expressions come from :mod:`agilegs.schemas.keys`. A query's payload is decoded (msgpack,
or JSON when the query's encoding says so), handed to :meth:`ServiceCore.call` in a worker
thread, and answered with the operation's response or an error reply carrying the same
:class:`~agilegs.schemas.errors.ErrorBody` as over HTTP. Frames and pools published by a
robot are applied in arrival order by one thread; a refused one is published on
``agilegs/<session>/errors``. Every decision (over HTTP or Zenoh) is published on
``agilegs/<session>/decisions``.

Which keys this instance declares (the ``@service`` and ``@instances/<id>`` queryables, and
each owned session's queryable and subscribers) and where an operation runs (here, or
forwarded to the instance that owns the session) is :mod:`agilegs.service.cluster`'s business.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import queue
import threading
import time
from typing import Any

from agilegs.client._zenoh import peer_config
from agilegs.schemas import codec, keys
from agilegs.schemas.models import SelectResponse

from .cluster import ClusterNode
from .core import ServiceCore, ServiceError
from .metrics import Metrics
from .settings import Settings

__all__ = ["ZenohAdapter"]

log = logging.getLogger(__name__)

_STOP = object()


class ZenohAdapter:
    """Serves the core over Zenoh (peer mode) until :meth:`close`."""

    def __init__(self, core: ServiceCore, settings: Settings, metrics: Metrics | None = None,
                 cluster: ClusterNode | None = None) -> None:
        self.core = core
        # issue 6: which keys this instance declares, and where an operation runs
        self.cluster = cluster if cluster is not None else ClusterNode(core, settings)
        self.settings = settings
        self.metrics = metrics
        token = settings.token_value()
        self._digest = hashlib.sha256(token.encode()).digest() if token else None
        self.session: Any = None
        self._entities: list[Any] = []
        self._inbox: queue.Queue[Any] = queue.Queue()
        self._worker: threading.Thread | None = None
        self._closing = False

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        import zenoh

        mode = self.settings.zenoh_mode
        listen = [] if mode == "client" else self.settings.zenoh_listen
        conf = peer_config(listen, self.settings.zenoh_connect, mode)
        self.session = zenoh.open(conf)
        # issue 6: the @service, @instances/<id> and per-session queryables and the
        # per-session subscribers are declared by the cluster node (service/cluster.py)
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
        self.core.decision_listeners.append(self.publish_decision)
        self.core.zenoh_enabled = True
        log.info("zenoh: %s %r, listening on %s, connecting to %s", mode,
                 self.cluster.instance_id, listen, self.settings.zenoh_connect)

    def close(self) -> None:
        """Undeclare everything and close the session (a declared callback left behind
        would keep the process from exiting)."""
        self._closing = True
        if self.publish_decision in self.core.decision_listeners:
            self.core.decision_listeners.remove(self.publish_decision)
        self.core.zenoh_enabled = False
        self.cluster.detach()
        for entity in reversed(self._entities):
            try:
                entity.undeclare()
            except Exception:  # already gone with the session
                log.debug("undeclare failed", exc_info=True)
        self._entities.clear()
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
        if op == "health" or (local and op == "list_sessions"):  # cheap reads: inline
            self._answer(query, op, session, t0, local, reply_key)
            return
        try:
            self.core.executor.submit(self._answer, query, op, session, t0, local, reply_key)
        except RuntimeError:  # the executor is shut down: the server is stopping
            self._reply_error(query, ServiceError(503, "unavailable", "the server is stopping"),
                              codec.MSGPACK, op)
            query.drop()

    def _answer(self, query: Any, op: str, session: str | None, t0: float, local: bool = False,
                reply_key: str | None = None) -> None:
        kind = codec.MSGPACK
        try:
            enc = query.encoding
            if enc is not None and str(enc).split(";", 1)[0] == codec.JSON:
                kind = codec.JSON
            if op not in keys.SESSION_OPS and op not in keys.SERVICE_OPS:
                raise ServiceError(404, "not_found", f"unknown operation {op!r}", "key")
            self._check_auth(query.attachment)
            raw = query.payload.to_bytes() if query.payload is not None else b""
            payload = None
            if len(raw) > self.settings.max_body_bytes:
                limit = self.settings.max_body_bytes
                raise ServiceError(413, "payload_too_large",
                                   f"payload exceeds max_body_bytes ({limit})", "body")
            if raw:
                try:
                    payload = codec.load(raw, kind)
                except codec.DecodeError as exc:
                    raise ServiceError(400, "bad_request", str(exc), "body") from None
            instance = query.parameters.get("instance") if op == "create_session" else None
            result = self.cluster.call(op, session, payload, t0=t0, instance=instance,
                                       local=local)
            query.reply(reply_key or query.key_expr, codec.dump(result, kind), encoding=kind)
            self._count(op, 200)
        except ServiceError as err:
            self._reply_error(query, err, kind, op)
        except Exception as exc:
            log.exception("zenoh: internal error on %s", op)
            self._reply_error(query, ServiceError(500, "internal",
                                                  f"internal error ({type(exc).__name__})"),
                              kind, op)
        finally:
            query.drop()

    def _reply_error(self, query: Any, err: ServiceError, kind: str, op: str) -> None:
        try:
            query.reply_err(codec.dump(err.body(), kind), encoding=kind)
        except Exception:
            log.debug("zenoh: could not send an error reply", exc_info=True)
        self._count(op, err.status, err.code)

    def _count(self, op: str, status: int, code: str | None = None) -> None:
        if self.metrics is not None:
            self.metrics.observe_request("zenoh", op, status, code)

    def _check_auth(self, attachment: Any) -> None:
        if self._digest is None:
            return
        given = attachment.to_bytes() if attachment is not None else b""
        ok = given[:7].lower() == b"bearer " and hmac.compare_digest(
            hashlib.sha256(given[7:].strip()).digest(), self._digest)
        if not ok:
            raise ServiceError(401, "unauthorized", "missing or wrong bearer token "
                               "(the attachment 'Bearer <token>')", "attachment")

    # ------------------------------------------------------------------ subscriptions
    def _on_sample(self, sample: Any) -> None:
        if not self._closing:
            self._inbox.put((str(sample.key_expr), sample.payload.to_bytes(),
                             str(sample.encoding) if sample.encoding is not None else None,
                             sample.attachment.to_bytes() if sample.attachment is not None
                             else None))

    def _drain(self) -> None:
        while True:
            item = self._inbox.get()
            if item is _STOP:
                return
            key, raw, encoding, attachment = item
            try:
                session, topic = keys.parse_session_key(key)
            except ValueError:
                continue
            op = "add_observations" if topic == keys.FRAMES else "set_pool"
            kind = codec.JSON if (encoding or "").split(";", 1)[0] == codec.JSON else codec.MSGPACK
            try:
                if self._digest is not None:
                    given = attachment or b""
                    if not (given[:7].lower() == b"bearer " and hmac.compare_digest(
                            hashlib.sha256(given[7:].strip()).digest(), self._digest)):
                        raise ServiceError(401, "unauthorized", "missing or wrong bearer token",
                                           "attachment")
                if len(raw) > self.settings.max_body_bytes:
                    raise ServiceError(413, "payload_too_large", "payload exceeds max_body_bytes",
                                       "body")
                try:
                    payload = codec.load(raw, kind)
                except codec.DecodeError as exc:
                    raise ServiceError(400, "bad_request", str(exc), "body") from None
                self.core.call(op, session, payload)
                self._count(op, 200)
            except ServiceError as err:
                self._count(op, err.status, err.code)
                self._publish_error(session, err)
            except Exception as exc:
                log.exception("zenoh: internal error on a %s message", topic)
                self._publish_error(session, ServiceError(500, "internal",
                                                          f"internal error ({type(exc).__name__})"))

    def _publish_error(self, session: str, err: ServiceError) -> None:
        try:
            self.session.put(keys.session_key(session, keys.ERRORS),
                             codec.dump(err.body(), codec.MSGPACK), encoding=codec.MSGPACK)
        except Exception:
            log.debug("zenoh: could not publish an error", exc_info=True)

    # ------------------------------------------------------------------ decisions
    def publish_decision(self, session: str, resp: SelectResponse) -> None:
        if self.session is None or self._closing:
            return
        self.session.put(keys.session_key(session, keys.DECISIONS),
                         codec.dump(resp, codec.MSGPACK), encoding=codec.MSGPACK)
