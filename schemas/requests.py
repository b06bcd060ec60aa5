"""Request ids: what makes a write safe to send again.

A client gives every write (an operation whose HTTP method is not GET) a request id: over
HTTP the header :data:`REQUEST_ID_HEADER`, over Zenoh the selector parameter
:data:`REQUEST_ID_PARAM`. The session's owner records the id, with the answer, in the same
commit that applies the write; the same id sent again (a retry after a lost answer, or after
the session moved to another instance) is answered from that record and applies nothing. A
``create_session`` with a request id and no ``id`` creates the session
:func:`session_id_for` names, so that its retry finds the session it may have created.
"""

from __future__ import annotations

import hashlib
import re
import uuid

__all__ = ["REQUEST_ID_HEADER", "REQUEST_ID_PARAM", "REQUEST_ID_PATTERN", "check_request_id",
           "new_request_id", "session_id_for"]

REQUEST_ID_HEADER = "Idempotency-Key"
"""The HTTP header of a write's request id."""

REQUEST_ID_PARAM = "request_id"
"""The Zenoh selector parameter of a write's request id."""

REQUEST_ID_PATTERN = r"^[A-Za-z0-9._:-]{8,64}$"
"""A request id: 8 to 64 characters of letters, digits and ``. _ : -`` (a UUID's hex fits)."""

_RE = re.compile(REQUEST_ID_PATTERN)


def check_request_id(value: str) -> str:
    """``value`` if it is a valid request id; ValueError saying why otherwise."""
    if not _RE.match(value):
        raise ValueError(f"a request id is 8 to 64 characters of letters, digits and . _ : - "
                         f"(got {value[:80]!r})")
    return value


def new_request_id() -> str:
    """A fresh random request id (a UUID4's 32 hex digits)."""
    return uuid.uuid4().hex


def session_id_for(request_id: str) -> str:
    """The id of the session a ``create_session`` without ``id`` creates when it carries
    ``request_id``: ``s-`` and 12 hex digits of its SHA-256 (the form of a generated id)."""
    return "s-" + hashlib.sha256(request_id.encode()).hexdigest()[:12]
