"""The client's exceptions: one tree for HTTP and Zenoh alike.

::

    AgileGSError                       every error this package raises
    ├── TransportError                 the server could not be reached or did not answer
    │   └── RequestTimeout             no answer within the timeout
    ├── ProtocolError                  an answer that breaks the wire contract
    └── APIError                       the server refused the request (an error body)
        ├── BadRequestError            400  undecodable body; 406 / 415 media types
        ├── AuthenticationError        401  missing or wrong bearer token
        ├── NotFoundError              404  unknown session or route
        │   └── SessionUnavailableError     no instance answers for the session
        ├── ConflictError              409  state forbids it (id taken, empty pool, no such
        │   │                               candidate or view in the session, ...)
        │   └── SessionDamagedError         the session's files on disk do not check out
        ├── PayloadTooLargeError       413  a body over the server's max_body_bytes
        ├── ValidationError            422  a malformed or out-of-range value
        │   └── LimitExceededError          a value over a server limit (pool, pixels, ...)
        ├── TooManyError               429  a count limit (sessions, views, a pool extended,
        │                                   compute requests queued on one session)
        └── ServerError                5xx  a server fault
            └── InsufficientStorageError  507  the server's disk is full (nothing changed)

An :class:`APIError` carries the error body's ``status``, ``code``, ``message``, ``field``
(the path of the offending input, e.g. ``body.poses[3].matrix``), ``errors`` (every
problem found), and where the server sets them ``limit`` (the setting a refusal is about),
``retry_after`` (seconds, on 429 / 503) and ``estimate`` (a select refused on its cost).
HTTP error responses and Zenoh error replies carry the same body, so the
same exception comes out of :class:`Client`, :class:`AsyncClient` and :class:`ZenohClient`.
Backend exceptions (httpx, zenoh) are chained as ``__cause__``.
"""

from __future__ import annotations

from typing import Any

from agilegs.schemas import ErrorBody, ErrorItem, codec

__all__ = [
    "APIError",
    "AgileGSError",
    "AuthenticationError",
    "BadRequestError",
    "ConflictError",
    "InsufficientStorageError",
    "LimitExceededError",
    "NotFoundError",
    "PayloadTooLargeError",
    "ProtocolError",
    "RequestTimeout",
    "ServerError",
    "SessionDamagedError",
    "SessionUnavailableError",
    "TooManyError",
    "TransportError",
    "ValidationError",
    "error_from_body",
]


class AgileGSError(Exception):
    """Base of every error raised by :mod:`agilegs.client`."""


class TransportError(AgileGSError):
    """The server could not be reached, or the connection failed mid-request."""


class RequestTimeout(TransportError):
    """No answer within the client's timeout."""


class ProtocolError(AgileGSError):
    """The server's answer does not follow the wire contract (undecodable, wrong shape)."""


class APIError(AgileGSError):
    """The server refused the request; see the module docstring for the fields."""

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        field: str | None = None,
        errors: list[ErrorItem] | None = None,
        *,
        limit: str | None = None,
        retry_after: float | None = None,
        estimate: dict[str, float] | None = None,
    ) -> None:
        where = f" [{field}]" if field and not message.startswith(field) else ""
        super().__init__(f"{status} {code}: {message}{where}")
        self.status = status
        self.code = code
        self.message = message
        self.field = field
        self.errors = errors or []
        self.limit = limit  # the server setting a refusal is about
        self.retry_after = retry_after  # seconds before a refusal for load may go through
        self.estimate = estimate  # the up-front estimate a select was refused on


class BadRequestError(APIError):
    """400 (undecodable body), 406 (no acceptable response type), 415 (body type)."""


class AuthenticationError(APIError):
    """401: missing or wrong bearer token."""


class NotFoundError(APIError):
    """404: unknown session, operation or route."""


class SessionUnavailableError(NotFoundError):
    """404 ``session_unavailable``: no live instance answers for the session; it does not
    exist, or the instance that owns it is down (it comes back when that instance restarts)."""


class ConflictError(APIError):
    """409: the session's state forbids it (id taken, empty pool, map empty, a candidate or
    view the request names is not in the session...)."""


class SessionDamagedError(ConflictError):
    """409 ``session_damaged``: the session's files on the server's disk do not check out;
    ``list_sessions`` shows what is damaged, ``repair_session`` brings it back to its last
    intact version, ``delete_session`` removes it."""


class PayloadTooLargeError(APIError):
    """413: the body exceeds the server's ``max_body_bytes``."""


class ValidationError(APIError):
    """422: a value is malformed or out of range; ``field`` says which."""


class LimitExceededError(ValidationError):
    """422 ``limit_exceeded``: a value over a limit of the server (pool size, image pixels,
    Gaussians, render width); the server's OpenAPI schema states each limit."""


class TooManyError(APIError):
    """429: a count limit of the server (sessions, views)."""


class ServerError(APIError):
    """5xx: a fault on the server side."""


class InsufficientStorageError(ServerError):
    """507 ``insufficient_storage``: the server's state folder is full; the change was not
    made (reads keep working; retry once space is freed)."""


_BY_STATUS: dict[int, type[APIError]] = {
    400: BadRequestError,
    401: AuthenticationError,
    404: NotFoundError,
    405: NotFoundError,
    406: BadRequestError,
    409: ConflictError,
    413: PayloadTooLargeError,
    415: BadRequestError,
    422: ValidationError,
    429: TooManyError,
    507: InsufficientStorageError,
}


def error_from_body(status: int | None, body: bytes, kind: str | None) -> APIError:
    """The exception for an error response / reply ``body`` (JSON or msgpack)."""
    info: Any = None
    try:
        info = ErrorBody.model_validate(codec.load(body, kind or codec.JSON)).error
    except Exception:
        try:  # the other encoding, in case the content type was missing or wrong
            other = codec.MSGPACK if (kind or codec.JSON) == codec.JSON else codec.JSON
            info = ErrorBody.model_validate(codec.load(body, other)).error
        except Exception:
            info = None
    if info is None:
        st = status or 500
        text = body[:200].decode("utf-8", "replace")
        cls = _BY_STATUS.get(st, ServerError if st >= 500 else APIError)
        return cls(st, "unknown", f"unexpected error body: {text!r}")
    st = status or info.status
    cls = _BY_STATUS.get(st, ServerError if st >= 500 else APIError)
    if info.code == "session_unavailable":
        cls = SessionUnavailableError
    elif info.code == "session_damaged":
        cls = SessionDamagedError
    elif info.code == "limit_exceeded" and st == 422:
        cls = LimitExceededError
    return cls(st, info.code, info.message, info.field, list(info.errors), limit=info.limit,
               retry_after=info.retry_after, estimate=info.estimate)
