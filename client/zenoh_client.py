"""The Zenoh client: the same operations as the HTTP clients, as Zenoh queries.

Needs ``eclipse-zenoh`` (``pip install 'agilegs[zenoh]'``). Every operation is a query on
``agilegs/<session>/<op>`` (or ``agilegs/@service/<op>``) with a msgpack payload; besides, a
robot can publish frames and pools and follow every decision (see :mod:`agilegs.schemas.keys`).

With several server instances (see :mod:`agilegs.service.transports.zenoh.cluster`), a
client that reaches one of them or their router reaches every session: Zenoh routes each query
to the instance that owns the session. A query that no instance answers raises
:class:`~agilegs.client.errors.SessionUnavailableError` while some instance is alive, and
:class:`~agilegs.client.errors.TransportError` when none is.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from pydantic import BaseModel
from pydantic import ValidationError as PydanticValidationError

from agilegs import schemas as m
from agilegs.schemas import ErrorBody, codec, keys
from agilegs.schemas.requests import REQUEST_ID_PARAM

from . import _requests as rq
from ._ops import ObservationLike, PoolLike, SyncOperations
from ._requests import Call
from ._retry import RETRY_WINDOW, retry_sync
from .errors import (
    ProtocolError,
    RequestTimeout,
    SessionUnavailableError,
    TransportError,
    error_from_body,
)
from .zenoh_rpc import credentials as zenoh_credentials
from .zenoh_rpc import first_answer, open_session, read_credentials

__all__ = ["ZenohClient"]


class ZenohClient(SyncOperations):
    """Blocking Zenoh client (peer mode, scouting off).

    Args:
        connect: endpoints of the server (its ``--zenoh-listen``) or of a router (default:
            those of ``credentials``, else ``tcp/127.0.0.1:7447``).
        listen: endpoints this peer listens on (none by default).
        token: bearer token, sent as the attachment ``Bearer <token>``.
        timeout: seconds to wait for a reply (sent as the query's ``deadline_ms``: the
            server cancels work this client no longer waits for).
        wait: seconds to wait at start for the server to answer ``health`` (0: do not wait;
            at most ``timeout``).
        mode: zenoh mode, ``"peer"`` or ``"client"`` (through a router, or through one
            server instance that is a peer: it routes to the other instances).
        user, password: Zenoh credentials, for a server or router that authenticates its
            peers (``AGILEGS_ZENOH_USERS_FILE``).
        tls_root_ca: PEM CA certificate verifying a ``tls/...`` endpoint.
        tls_certificate, tls_private_key: this client's PEM certificate and key, for a
            server with mutual TLS (``AGILEGS_ZENOH_MTLS``).
        credentials: the JSON file a server started with ``AGILEGS_TOKEN`` writes in its
            state folder, ``<state-dir>/zenoh/client.json``: its endpoints, the Zenoh user
            and password it made (and its CA); ``user`` / ``password`` / ``tls_root_ca``
            given here win.
        retry_window: seconds an operation is retried, with backoff, while its session is
            handed over in a fleet (no instance answers for it, or it answers
            ``session_unavailable`` with a ``retry_after``); 0: never
            (:mod:`agilegs.client._retry`).
    """

    def __init__(
        self,
        connect: Sequence[str] | None = None,
        *,
        listen: Sequence[str] = (),
        token: str | None = None,
        timeout: float = 120.0,
        wait: float = 10.0,
        mode: str = "peer",
        user: str | None = None,
        password: str | None = None,
        tls_root_ca: str | Path | None = None,
        tls_certificate: str | Path | None = None,
        tls_private_key: str | Path | None = None,
        credentials: str | Path | None = None,
        retry_window: float = RETRY_WINDOW,
    ) -> None:
        try:
            import zenoh
        except ImportError as exc:  # pragma: no cover - depends on the install
            raise TransportError("ZenohClient needs eclipse-zenoh: "
                                 "pip install 'agilegs[zenoh]'") from exc
        if credentials is not None:
            try:
                saved = read_credentials(credentials)
            except ValueError as exc:
                raise TransportError(str(exc)) from None
            if user is None and password is None:
                user, password = saved["user"], saved["password"]
            tls_root_ca = tls_root_ca if tls_root_ca is not None else saved.get("tls_root_ca")
            if connect is None and saved["connect"]:
                connect = saved["connect"]
        if connect is None:
            connect = ("tcp/127.0.0.1:7447",)
        self.timeout = timeout
        self.retry_window = retry_window
        self._connect = list(connect)
        self._attachment = f"Bearer {token}".encode() if token else None
        self._session: Any = None
        try:
            extra = zenoh_credentials(user=user, password=password, root_ca=tls_root_ca,
                                certificate=tls_certificate, private_key=tls_private_key)
            self._session = open_session(listen, connect, mode, extra)
        except (zenoh.ZError, ValueError) as exc:
            raise TransportError(f"cannot open a Zenoh session: {exc}") from exc
        self._subscribers: list[Any] = []
        if wait > 0:
            self._wait_for_server(min(wait, timeout))

    def _wait_for_server(self, wait: float) -> None:
        """Wait up to ``wait`` s in all for ``health`` to answer (each query within what is
        left of it)."""
        deadline = time.monotonic() + wait
        timeout = self.timeout
        try:
            while True:
                self.timeout = max(0.05, deadline - time.monotonic())
                try:
                    self.health()
                    return
                except TransportError:
                    if time.monotonic() + 0.05 >= deadline:
                        self.close()
                        raise
                    time.sleep(0.05)
        finally:
            self.timeout = timeout

    @staticmethod
    def _key(call: Call) -> str:
        if call.op.scope == "service":
            return keys.service_key(call.op.name)
        assert call.session is not None
        try:
            return keys.session_key(call.session, call.op.name)
        except ValueError as exc:  # mirrors the server's answer to a bad id
            from .errors import ValidationError

            raise ValidationError(422, "invalid", str(exc), "session") from None

    def _send(self, call: Call, parameters: str | None = None) -> BaseModel | bytes:
        call = call.with_request_id()
        return retry_sync(lambda: self._send_once(call, parameters), self.retry_window, call)

    def _send_once(self, call: Call, parameters: str | None = None) -> BaseModel | bytes:
        if parameters is None:
            # the server gives up on the work once this client stops waiting for it
            params = {**(call.params or {}), "deadline_ms": f"{self.timeout * 1e3:.0f}"}
            if call.file is not None:
                params["format"] = call.file
            if call.request_id is not None:
                params[REQUEST_ID_PARAM] = call.request_id
            parameters = ";".join(f"{k}={v}" for k, v in params.items())
        key = self._key(call)
        payload = codec.dump(call.body, codec.MSGPACK) if call.body is not None else None
        try:
            ans, timed_out = first_answer(self._session, key, payload=payload,
                                          parameters=parameters, attachment=self._attachment,
                                          timeout=self.timeout)
        except Exception as exc:
            raise TransportError(f"{call.op.name}: zenoh query on {key} failed: {exc}") from exc
        if ans is not None and ans.ok and call.file is not None:
            if ans.encoding.split(";", 1)[0] != codec.GAUSSIAN_FILE_TYPES[call.file]:
                raise ProtocolError(f"{call.op.name}: asked for a .{call.file} file, the reply "
                                    f"is encoded {ans.encoding!r}")
            return ans.payload
        if ans is not None and ans.ok:
            try:
                return call.op.response.model_validate(ans.load())
            except (codec.DecodeError, PydanticValidationError) as exc:
                raise ProtocolError(f"{call.op.name}: the reply does not match "
                                    f"{call.op.response.__name__}: {exc}") from exc
        if ans is not None:
            raise error_from_body(None, ans.payload, ans.kind)
        if timed_out:
            raise RequestTimeout(f"{call.op.name}: no reply on {key} within {self.timeout} s")
        if call.op.scope == "session" and self._any_server():
            # in a fleet, a live instance takes a dead owner's sessions over: a read is worth
            # a retry, and so is a write with a request id (applied once however often sent;
            # without one it may have been applied by an owner that died answering it)
            read = call.op.http_method == "GET" or call.request_id is not None
            raise SessionUnavailableError(
                404, "session_unavailable",
                f"{call.op.name}: no instance answers for session {call.session!r}: it does not "
                "exist, or the instance that owns it is down", "path.session",
                retry_after=0.05 if read and self._in_fleet() else None)
        if not self._linked():
            raise TransportError(
                f"{call.op.name}: no Zenoh peer reached at {', '.join(self._connect)}: no server "
                "listens there, or it refused this client's link (a server with AGILEGS_TOKEN or "
                "a users file lets in only peers with its Zenoh credentials: "
                "ZenohClient(credentials='<state-dir>/zenoh/client.json') or user= and "
                "password=; with TLS, tls_root_ca=)")
        raise TransportError(f"{call.op.name}: no reply on {key} (is the server running with "
                             "Zenoh, and reachable?)")

    def _linked(self) -> bool:
        """Whether this session holds a link to some peer or router."""
        try:
            info = self._session.info
            return any(True for _ in info.peers_zid()) or any(True for _ in info.routers_zid())
        except Exception:  # an API without it: say nothing more
            return True

    def _in_fleet(self) -> bool:
        """Whether the instances answering form a fleet (they declare member tokens)."""
        try:
            return any(True for _ in self._session.liveliness().get(
                f"{keys.PREFIX}/{keys.MEMBERS}/*", timeout=min(self.timeout, 1.0)))
        except Exception:
            return False

    def _any_server(self) -> bool:
        """Whether some server instance answers ``health`` (every instance does)."""
        kwargs: dict[str, Any] = {"timeout": min(self.timeout, 2.0)}
        if self._attachment is not None:
            kwargs["attachment"] = self._attachment
        try:
            return any(True for _ in self._session.get(keys.service_key("health"), **kwargs))
        except Exception:
            return False

    # ------------------------------------------------------------------ pub / sub
    def publish_frames(self, session: str,
                       observations: ObservationLike | Sequence[ObservationLike]) -> None:
        """Publish frames on ``agilegs/<session>/frames`` (the server adds them as
        observations; a refused message is published on ``.../errors``)."""
        body = rq.add_observations(session, observations).body
        assert body is not None
        self._put(keys.session_key(session, keys.FRAMES), codec.dump(body, codec.MSGPACK))

    def publish_pool(self, session: str, poses: PoolLike, ids: Sequence[int] | None = None
                     ) -> None:
        """Publish a candidate pool on ``agilegs/<session>/candidates`` (replaces the pool)."""
        body = rq.to_pool(poses, ids)
        self._put(keys.session_key(session, keys.CANDIDATES), codec.dump(body, codec.MSGPACK))

    def _put(self, key: str, payload: bytes) -> None:
        kwargs: dict[str, Any] = {"encoding": codec.MSGPACK}
        if self._attachment is not None:
            kwargs["attachment"] = self._attachment
        self._session.put(key, payload, **kwargs)

    def subscribe_decisions(self, session: str, callback: Callable[[m.SelectResponse], None]
                            ) -> Any:
        """Call ``callback`` with every decision of ``session`` (``"*"``: every session);
        returns the subscriber (``.undeclare()`` it, or let :meth:`close` do it)."""
        key = keys.session_wildcard(keys.DECISIONS) if session == "*" else keys.session_key(
            session, keys.DECISIONS)

        def on_sample(sample: Any) -> None:
            callback(m.SelectResponse.model_validate(
                codec.load(sample.payload.to_bytes(), codec.MSGPACK)))

        sub = self._session.declare_subscriber(key, on_sample)
        self._subscribers.append(sub)
        return sub

    def subscribe_errors(self, session: str, callback: Callable[[ErrorBody], None]) -> Any:
        """Call ``callback`` with the error body of every refused frames / pool message."""

        def on_sample(sample: Any) -> None:
            callback(ErrorBody.model_validate(codec.load(sample.payload.to_bytes(),
                                                         codec.MSGPACK)))

        sub = self._session.declare_subscriber(keys.session_key(session, keys.ERRORS), on_sample)
        self._subscribers.append(sub)
        return sub

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        """Undeclare the subscribers and close the Zenoh session."""
        for sub in self._subscribers:
            try:
                sub.undeclare()
            except Exception:  # already undeclared by the caller
                pass
        self._subscribers.clear()
        if getattr(self, "_session", None) is not None:
            self._session.close()
            self._session = None

    def __enter__(self) -> ZenohClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
