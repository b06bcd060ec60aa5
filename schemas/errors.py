"""The error body every failed request gets, over HTTP and Zenoh alike.

``{"error": {"status": 422, "code": "invalid", "message": "...", "field": "body.poses[3].matrix",
"errors": [{"field": ..., "message": ...}, ...]}}``

``supported`` lists what the server takes instead where that is the problem: the methods of
a route (405), the media types it produces (406) or reads (415). ``limit`` names the server
setting a refusal is about (``max_select_seconds``, ``max_request_decoded_bytes``...),
``retry_after`` says in how many seconds a refusal for load (429, 503) may go through (also
the HTTP ``Retry-After`` header), and ``estimate`` carries the up-front estimate a select was
refused on (``peak_bytes``, ``seconds``).

``field`` names the offending input as a path: ``body`` (the request body, over either
transport), ``path.session``, ``query.<name>``, ``header.<name>``, followed by attribute
names and ``[i]`` list indices. ``errors`` lists every problem found (``field`` and
``message`` repeat the first). Codes:

========================  ======  ====================================================
code                      status  meaning
========================  ======  ====================================================
``bad_request``           400     the body could not be decoded (not JSON / msgpack)
``unauthorized``          401     missing or wrong bearer token
``not_found``             404     unknown session, operation, or route
``session_unavailable``   404     scale-out: no live instance answers for the session
``instance_unavailable``  404     scale-out: no live instance has the requested id
``method_not_allowed``    405     the route exists but not with this method
``not_acceptable``        406     Accept names no type the server produces
``conflict``              409     the session's state forbids it (id taken, view has a frame,
                                  the body names a candidate or view the session lacks)
``session_damaged``       409     the session's files on disk do not check out (see its ``damage``)
``empty_pool``            409     a selection on an empty candidate pool
``map_empty``             409     a selection on a session without Gaussians
``payload_too_large``     413     body over the ``max_body_bytes`` setting, a body of more
                                  than ``max_body_items`` values, or images whose decoded
                                  pixels exceed ``max_request_decoded_bytes``
``limit_exceeded``        422     a value over a server limit (pool size, pixels, ...)
``unsupported_media``     415     Content-Type is neither JSON nor msgpack
``invalid``               422     a value is malformed or out of range (the field says which)
``too_many``              429     a count limit was reached (sessions, views per session,
                                  candidates when extending the pool, compute requests
                                  queued on one session: ``max_session_queue``)
``internal``              500     a server bug (bad input never yields it)
``insufficient_storage``  507     the state folder is full: the change was not made
``bad_gateway``           502     scale-out: the owning instance's answer was unusable
``unavailable``           503     the server is shutting down, a dependency is missing, or
                                  it is saturated (``retry_after`` says when to try again)
``gateway_timeout``       504     scale-out: the owning instance did not answer in time
``deadline_exceeded``     504     the request's deadline passed (or its client went away)
                                  before it finished; nothing was changed
========================  ======  ====================================================
"""

from __future__ import annotations

from enum import StrEnum

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["ERROR_STATUS", "ErrorBody", "ErrorCode", "ErrorInfo", "ErrorItem"]


class ErrorCode(StrEnum):
    """The stable machine-readable error codes (the table above)."""

    BAD_REQUEST = "bad_request"
    UNAUTHORIZED = "unauthorized"
    NOT_FOUND = "not_found"
    SESSION_UNAVAILABLE = "session_unavailable"
    INSTANCE_UNAVAILABLE = "instance_unavailable"
    METHOD_NOT_ALLOWED = "method_not_allowed"
    NOT_ACCEPTABLE = "not_acceptable"
    CONFLICT = "conflict"
    SESSION_DAMAGED = "session_damaged"
    EMPTY_POOL = "empty_pool"
    MAP_EMPTY = "map_empty"
    PAYLOAD_TOO_LARGE = "payload_too_large"
    LIMIT_EXCEEDED = "limit_exceeded"
    UNSUPPORTED_MEDIA = "unsupported_media"
    INVALID = "invalid"
    TOO_MANY = "too_many"
    INTERNAL = "internal"
    INSUFFICIENT_STORAGE = "insufficient_storage"
    BAD_GATEWAY = "bad_gateway"
    UNAVAILABLE = "unavailable"
    GATEWAY_TIMEOUT = "gateway_timeout"
    DEADLINE_EXCEEDED = "deadline_exceeded"


ERROR_STATUS: dict[ErrorCode, int] = {
    ErrorCode.BAD_REQUEST: 400,
    ErrorCode.UNAUTHORIZED: 401,
    ErrorCode.NOT_FOUND: 404,
    ErrorCode.SESSION_UNAVAILABLE: 404,
    ErrorCode.INSTANCE_UNAVAILABLE: 404,
    ErrorCode.METHOD_NOT_ALLOWED: 405,
    ErrorCode.NOT_ACCEPTABLE: 406,
    ErrorCode.CONFLICT: 409,
    ErrorCode.SESSION_DAMAGED: 409,
    ErrorCode.EMPTY_POOL: 409,
    ErrorCode.MAP_EMPTY: 409,
    ErrorCode.PAYLOAD_TOO_LARGE: 413,
    ErrorCode.LIMIT_EXCEEDED: 422,
    ErrorCode.UNSUPPORTED_MEDIA: 415,
    ErrorCode.INVALID: 422,
    ErrorCode.TOO_MANY: 429,
    ErrorCode.INTERNAL: 500,
    ErrorCode.INSUFFICIENT_STORAGE: 507,
    ErrorCode.BAD_GATEWAY: 502,
    ErrorCode.UNAVAILABLE: 503,
    ErrorCode.GATEWAY_TIMEOUT: 504,
    ErrorCode.DEADLINE_EXCEEDED: 504,
}
"""The HTTP status that goes with each code."""


class ErrorItem(BaseModel):
    """One problem: where (``field``) and why (``message``)."""

    model_config = ConfigDict(extra="ignore")

    field: str | None = Field(default=None, description="path of the offending input")
    message: str = Field(description="what is wrong with it")


class ErrorInfo(BaseModel):
    """What went wrong: HTTP status, a stable machine-readable code, and the field."""

    model_config = ConfigDict(extra="ignore")

    status: int = Field(description="HTTP status (also sent in Zenoh error replies)")
    code: str = Field(
        description="stable error code (:class:`ErrorCode`; a client keeps codes it does not "
        "know as text)",
        json_schema_extra={"enum": [c.value for c in ErrorCode]},
    )
    message: str = Field(description="human-readable reason")
    field: str | None = Field(default=None, description="path of the offending input, if any")
    errors: list[ErrorItem] = Field(default_factory=list, description="every problem found")
    supported: list[str] | None = Field(
        default=None,
        description="what the server takes instead: the methods of the route (405, also in "
        "the Allow header), the media types it produces (406) or reads (415, also in the "
        "Accept header)",
    )
    limit: str | None = Field(default=None, description="the server setting the refusal "
                              "is about (e.g. max_select_seconds)")
    retry_after: float | None = Field(default=None, description="seconds after which a "
                                      "request refused for load may go through (429, 503; "
                                      "also the Retry-After header)")
    estimate: dict[str, float] | None = Field(
        default=None, description="the up-front estimate a request was refused on "
        "(peak_bytes, seconds)")


class ErrorBody(BaseModel):
    """The body of every error response and every Zenoh error reply."""

    model_config = ConfigDict(extra="ignore")

    error: ErrorInfo
