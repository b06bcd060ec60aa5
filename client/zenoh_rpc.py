"""Zenoh sessions and request / reply for agilegs (no torch): the client SDK's
:class:`~agilegs.client.ZenohClient` and the server's cluster both use it.

Needs ``eclipse-zenoh`` (``pip install 'agilegs[zenoh]'``).
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from agilegs.schemas import codec

__all__ = ["Answer", "credentials", "first_answer", "open_session", "query", "read_credentials",
           "session_config"]


def session_config(
    listen: Sequence[str] = (), connect: Sequence[str] = (), mode: str = "peer",
    extra: Mapping[str, Any] | None = None,
) -> Any:
    """A ``zenoh.Config``: ``mode`` (peer by default), explicit listen / connect endpoints,
    multicast and gossip scouting off (peers meet only through the endpoints given), and the
    ``extra`` settings (a Zenoh config path such as ``transport/auth/usrpwd/user`` -> its
    value, e.g. :func:`credentials`)."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    for path, value in (extra or {}).items():
        conf.insert_json5(path, json.dumps(value))
    return conf


def credentials(*, user: str | None = None, password: str | None = None,
                root_ca: str | Path | None = None, certificate: str | Path | None = None,
                private_key: str | Path | None = None) -> dict[str, Any]:
    """The Zenoh settings a peer connects with: a username and password (Zenoh's usrpwd
    authentication), the CA certificate that verifies a ``tls/`` endpoint, and its own
    certificate and key for mutual TLS (PEM files)."""
    out: dict[str, Any] = {}
    if (user is None) != (password is None):
        raise ValueError("a Zenoh user needs its password, and a password its user")
    if (certificate is None) != (private_key is None):
        raise ValueError("a TLS certificate needs its private key, and a key its certificate")
    if user is not None:
        out["transport/auth/usrpwd/user"] = user
        out["transport/auth/usrpwd/password"] = password
    if root_ca is not None:
        out["transport/link/tls/root_ca_certificate"] = str(root_ca)
    if certificate is not None:
        out["transport/link/tls/connect_certificate"] = str(certificate)
        out["transport/link/tls/connect_private_key"] = str(private_key)
        out["transport/link/tls/enable_mtls"] = True  # present it
    return out


def read_credentials(path: str | Path) -> dict[str, Any]:
    """What a client needs to reach a server, from the JSON file the server writes in its
    state folder (``zenoh/client.json``): ``connect`` (the server's endpoints), ``user`` and
    ``password`` (its Zenoh credentials) and, with TLS, ``tls_root_ca`` (a path; relative
    paths are relative to the file). ValueError naming the file when it is malformed."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read the Zenoh credentials: {exc}") from None
    if not isinstance(data, dict) or not isinstance(data.get("user"), str) \
            or not isinstance(data.get("password"), str):
        raise ValueError(f"{path}: expected a JSON object with user and password")
    out: dict[str, Any] = {"user": data["user"], "password": data["password"],
                           "connect": [str(e) for e in data.get("connect") or []]}
    if data.get("tls_root_ca"):
        out["tls_root_ca"] = path.parent / str(data["tls_root_ca"])
    return out


def open_session(listen: Sequence[str] = (), connect: Sequence[str] = (), mode: str = "peer",
                 extra: Mapping[str, Any] | None = None) -> Any:
    """An open ``zenoh.Session`` with :func:`session_config` (close it when done)."""
    import zenoh

    return zenoh.open(session_config(listen, connect, mode, extra))


@dataclass(frozen=True)
class Answer:
    """One reply to a query: ``ok`` (a response) or not (an error reply), the key it came
    on, its payload and the payload's media type (JSON or msgpack), and its Zenoh encoding
    as sent (a file's media type: ``application/x-ply``)."""

    ok: bool
    key: str
    payload: bytes
    kind: str
    encoding: str = ""

    def load(self) -> Any:
        """The payload as Python data (``codec.DecodeError`` if malformed)."""
        return codec.load(self.payload, self.kind)


def _answer(reply: Any) -> Answer:
    if reply.ok is not None:
        sample = reply.ok
        kind = codec.media_type(str(sample.encoding)) or codec.MSGPACK
        return Answer(True, str(sample.key_expr), sample.payload.to_bytes(), kind,
                      str(sample.encoding))
    err = reply.err
    kind = (codec.media_type(str(err.encoding)) if err.encoding is not None else None
            ) or codec.MSGPACK
    return Answer(False, "", err.payload.to_bytes(), kind)


def query(
    session: Any,
    key: str,
    *,
    payload: bytes | None = None,
    parameters: str | None = None,
    attachment: bytes | None = None,
    timeout: float = 10.0,
    remote_only: bool = False,
    every_reply: bool = False,
    encoding: str = codec.MSGPACK,
) -> Iterator[Answer]:
    """The answers to a get on ``key`` (msgpack payload), as they come.

    Args:
        encoding: the payload's media type (msgpack; JSON is answered in JSON).
        parameters: the selector's parameters (``instance=gpu-1``).
        attachment: ``Bearer <token>``.
        remote_only: ask other Zenoh sessions only (not this one's own queryables).
        every_reply: keep every replier's answer (no consolidation).
    """
    import zenoh

    selector = key if not parameters else f"{key}?{parameters}"
    kwargs: dict[str, Any] = {"timeout": timeout, "encoding": encoding}
    if payload is not None:
        kwargs["payload"] = payload
    if attachment is not None:
        kwargs["attachment"] = attachment
    if every_reply:
        kwargs["consolidation"] = zenoh.ConsolidationMode.NONE
    if remote_only:
        kwargs["allowed_destination"] = zenoh.Locality.REMOTE
    for reply in session.get(selector, **kwargs):
        yield _answer(reply)


def first_answer(session: Any, key: str, *, timeout: float, **kwargs: Any
                 ) -> tuple[Answer | None, bool]:
    """The first answer to a get on ``key`` (the arguments of :func:`query`), and whether
    the wait for it ran out the timeout (no answer and ``timed_out``: nobody answered in
    time; no answer otherwise: nobody declares the key)."""
    t0 = time.monotonic()
    for ans in query(session, key, timeout=timeout, **kwargs):
        return ans, False
    return None, time.monotonic() - t0 >= timeout * 0.99
