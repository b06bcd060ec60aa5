"""What a request may cost, checked before the work: memory, queueing, and deadlines.

Every request goes through :class:`Admission` on its way to a worker thread
(:meth:`agilegs.service.transports.gateway.Gateway.submit`):

- **Reads and compute apart.** Reads (:data:`READ_OPS`: a session's state, pool, views,
  information, Gaussians and decisions, the session list) run on their own threads; they take
  a session's current record without its lock, so they never wait behind compute, of their
  session or another.
- **Fair queueing.** A session's compute requests run one at a time: the next waits in the
  session's queue without holding a worker thread, so one session never occupies more than
  one. A request admitted while another of its session's is queued or running runs on the
  background threads, whose OS priority is lower (``background_nice``): a session that
  keeps compute queued cannot starve the others of CPU. A session has at most
  ``max_session_queue`` compute requests running or waiting; one more is refused at once
  with 429 and ``Retry-After``. All sessions together
  have at most ``max_queued``; beyond, 503 with ``Retry-After`` (and ``/readyz`` says the
  server is saturated).
- **Deadlines.** Each request carries a :class:`Ticket`: its deadline (``request_deadline``,
  shortened by the request's own) and whether its client has gone. The pipeline checks it at
  each stage boundary (picked up by a worker, decoded, waiting for the session's lock, between
  the candidates of a selection: :mod:`agilegs.service.nbv.cancel`); a cancelled request stops
  there with 504 ``deadline_exceeded`` and frees its worker, having changed nothing.
- **Memory.** A JSON or msgpack body is refused (413) before it is parsed when it holds more
  than ``max_body_items`` values (:func:`count_values`); the images and depth maps of a request
  are priced from their headers before decoding (:func:`decoded_bytes`) against
  ``max_request_decoded_bytes`` (413) and, with every request in flight, against
  ``max_inflight_decoded_bytes`` (503 with ``Retry-After``). The bodies themselves are
  priced before they are read (:meth:`Admission.reserve_body`): the bytes of every body being
  read or held by a request in flight count against ``max_inflight_body_bytes`` (503 with
  ``Retry-After`` beyond), from the Content-Length, or chunk by chunk without one; a body
  refused for its size or for the budget is not read.
"""

from __future__ import annotations

import io
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from pydantic import BaseModel

from agilegs import schemas as m
from agilegs.schemas import codec
from agilegs.schemas.errors import ErrorCode

from ..errors import ServiceError
from ..settings import Settings

__all__ = ["CLIENT_CLOSED", "CLIENT_GONE", "READ_OPS", "Admission", "Ticket", "count_values",
           "decoded_bytes", "parse_deadline_ms", "request_decoded_bytes"]

log = logging.getLogger(__name__)

READ_OPS = frozenset({"health", "list_sessions", "get_session", "get_gaussians",
                      "list_views", "get_frames", "get_pool", "get_information", "get_decisions"})
"""Operations that only read: they run on the read threads and never queue behind compute."""

CLIENT_GONE = "the client disconnected"
"""A :class:`Ticket`'s reason when its client hung up."""

CLIENT_CLOSED = 499
"""The status a request whose client hung up is counted with (nginx's "client closed
request"); it is never sent."""

LARGE_BODY = 4 << 20
"""A body this large or larger makes the allocator trim once the bodies in flight are done."""

RETRY_AFTER = 1.0
"""Seconds a refusal for load tells the client to wait (``Retry-After``)."""


class Ticket:
    """A request's deadline and whether it was cancelled (its client went away).

    Args:
        deadline: ``time.monotonic()`` after which the request is cancelled (None: never).
    """

    def __init__(self, deadline: float | None = None) -> None:
        self.deadline = deadline
        self.reason: str | None = None

    def cancel(self, reason: str) -> None:
        """Cancel the request at its next stage boundary (``reason`` says why)."""
        if self.reason is None:
            self.reason = reason

    @property
    def cancelled(self) -> bool:
        return self.reason is not None or (
            self.deadline is not None and time.monotonic() > self.deadline)

    def check(self) -> None:
        """Raise 504 ``deadline_exceeded`` if the request is cancelled or past its deadline."""
        if self.reason is None and self.deadline is not None and time.monotonic() > self.deadline:
            self.reason = "its deadline passed"
        if self.reason is not None:
            raise ServiceError(504, ErrorCode.DEADLINE_EXCEEDED,
                               f"the request was cancelled: {self.reason}; nothing was changed",
                               "header.x-deadline-ms", limit="request_deadline")


def parse_deadline_ms(text: str | None, field: str) -> float | None:
    """A client's deadline in milliseconds from ``text`` (None: none given); 400 naming
    ``field`` when it is not a number >= 0."""
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not (value >= 0 and math.isfinite(value)):
        raise ServiceError(400, ErrorCode.BAD_REQUEST,
                           f"{field}: must be a number of milliseconds >= 0", field)
    return value


class Admission:
    """The counters the limits are checked against (thread-safe; see the module docstring)."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._lock = threading.Lock()
        self._per_session: dict[str, int] = {}
        self._active: set[str] = set()  # sessions with a compute request on a worker
        self._waiting: dict[str, deque[Callable[[], None]]] = {}  # the next ones, in order
        self.compute = 0  # compute requests running or waiting
        self.running = 0  # compute requests on a worker thread
        self.inflight_bytes = 0  # decoded image bytes reserved by requests in flight
        self.body_bytes = 0  # bytes of request bodies reserved by requests in flight
        self.large_bodies = 0  # bodies of LARGE_BODY bytes or more since the last trim

    # ------------------------------------------------------------------ queueing
    def enter(self, op: str, session: str | None) -> None:
        """Count a compute request in (429 past ``max_session_queue`` for its session, 503
        past ``max_queued``); reads pass. Pair with :meth:`leave`."""
        if op in READ_OPS:
            return
        s = self.settings
        with self._lock:
            if session is not None and self._per_session.get(session, 0) >= s.max_session_queue:
                raise ServiceError(
                    429, ErrorCode.TOO_MANY,
                    f"session {session!r} has {s.max_session_queue} compute requests running "
                    f"or queued (max_session_queue); retry after the current one",
                    "path.session", limit="max_session_queue", retry_after=RETRY_AFTER)
            if self.compute >= s.max_queued:
                raise ServiceError(
                    503, ErrorCode.UNAVAILABLE,
                    f"the server is saturated: {self.compute} compute requests running or "
                    f"queued (max_queued)", None, limit="max_queued", retry_after=RETRY_AFTER)
            self.compute += 1
            if session is not None:
                self._per_session[session] = self._per_session.get(session, 0) + 1

    def queued(self, session: str) -> int:
        """Compute requests of ``session`` running or waiting (this one included once it
        was admitted)."""
        with self._lock:
            return self._per_session.get(session, 0)

    def leave(self, op: str, session: str | None) -> None:
        if op in READ_OPS:
            return
        with self._lock:
            self.compute -= 1
            if session is not None:
                left = self._per_session.get(session, 1) - 1
                if left > 0:
                    self._per_session[session] = left
                else:
                    self._per_session.pop(session, None)

    def start_or_queue(self, session: str, start: Callable[[], None]) -> bool:
        """True when no compute request of ``session`` is on a worker (the caller starts
        this one); else ``start`` waits in the session's queue (False) for :meth:`next_of`."""
        with self._lock:
            if session not in self._active:
                self._active.add(session)
                return True
            self._waiting.setdefault(session, deque()).append(start)
            return False

    def next_of(self, session: str) -> Callable[[], None] | None:
        """A compute request of ``session`` ended: the next one's ``start`` (None: none
        waits, and the session has none on a worker)."""
        with self._lock:
            queue = self._waiting.get(session)
            if queue:
                nxt = queue.popleft()
                if not queue:
                    self._waiting.pop(session, None)
                return nxt
            self._active.discard(session)
            return None

    @contextmanager
    def running_compute(self, op: str) -> Iterator[None]:
        """Count a compute request on a worker thread (``/readyz``)."""
        if op in READ_OPS:
            yield
            return
        with self._lock:
            self.running += 1
        try:
            yield
        finally:
            with self._lock:
                self.running -= 1

    # ------------------------------------------------------------------ memory
    @contextmanager
    def decoded(self, nbytes: int) -> Iterator[None]:
        """Reserve ``nbytes`` of decoded images for the block: 413 past
        ``max_request_decoded_bytes``, 503 when the requests in flight hold too much."""
        s = self.settings
        if nbytes <= 0:
            yield
            return
        if nbytes > s.max_request_decoded_bytes:
            raise ServiceError(
                413, ErrorCode.PAYLOAD_TOO_LARGE,
                f"the request's images and depth maps take {nbytes} bytes decoded, over "
                f"max_request_decoded_bytes ({s.max_request_decoded_bytes}): send fewer or "
                f"smaller frames per request", "body", limit="max_request_decoded_bytes")
        with self._lock:
            if self.inflight_bytes + nbytes > s.max_inflight_decoded_bytes:
                raise ServiceError(
                    503, ErrorCode.UNAVAILABLE,
                    f"requests in flight hold {self.inflight_bytes} decoded bytes; this one "
                    f"needs {nbytes} more, over max_inflight_decoded_bytes "
                    f"({s.max_inflight_decoded_bytes})", "body",
                    limit="max_inflight_decoded_bytes", retry_after=RETRY_AFTER)
            self.inflight_bytes += nbytes
        try:
            yield
        finally:
            with self._lock:
                self.inflight_bytes -= nbytes

    def reserve_body(self, nbytes: int) -> None:
        """Count ``nbytes`` more of request body in flight: 503 with ``Retry-After`` when
        the bodies in flight would pass ``max_inflight_body_bytes``. Pair with
        :meth:`release_body`."""
        s = self.settings
        if nbytes <= 0:
            return
        with self._lock:
            if self.body_bytes + nbytes > s.max_inflight_body_bytes:
                raise ServiceError(
                    503, ErrorCode.UNAVAILABLE,
                    f"request bodies in flight hold {self.body_bytes} bytes; this one needs "
                    f"{nbytes} more, over max_inflight_body_bytes "
                    f"({s.max_inflight_body_bytes})", "body",
                    limit="max_inflight_body_bytes", retry_after=RETRY_AFTER)
            self.body_bytes += nbytes
            if nbytes >= LARGE_BODY:
                self.large_bodies += 1

    def release_body(self, nbytes: int) -> bool:
        """Give back ``nbytes`` of :meth:`reserve_body`; True when it was the last body in
        flight and large bodies passed since the last time (time to trim the allocator)."""
        if nbytes <= 0:
            return False
        with self._lock:
            self.body_bytes -= nbytes
            if self.body_bytes == 0 and self.large_bodies:
                self.large_bodies = 0
                return True
        return False

    # ------------------------------------------------------------------ readiness
    def saturation(self) -> str | None:
        """Why the server cannot take more compute now (None: it can)."""
        s = self.settings
        with self._lock:
            if self.compute >= s.max_queued:
                return (f"{self.compute} compute requests running or queued, the most "
                        f"max_queued ({s.max_queued}) allows")
            if self.running >= s.workers and self.compute > self.running:
                waiting = self.compute - self.running
                return f"all {s.workers} compute workers are busy and {waiting} requests wait"
            if self.body_bytes >= s.max_inflight_body_bytes:
                return (f"request bodies in flight hold {self.body_bytes} bytes "
                        f"(max_inflight_body_bytes {s.max_inflight_body_bytes})")
            if self.inflight_bytes >= s.max_inflight_decoded_bytes:
                return (f"requests in flight hold {self.inflight_bytes} decoded bytes "
                        f"(max_inflight_decoded_bytes {s.max_inflight_decoded_bytes})")
        return None


# ---------------------------------------------------------------------- body values
def count_values(body: bytes, kind: str, limit: int) -> None:
    """413 naming ``max_body_items`` if the JSON / msgpack ``body`` holds more than ``limit``
    values, found without parsing it.

    A value takes at least one byte, so a body of at most ``limit`` bytes passes unscanned.
    JSON: every value but the first is preceded by a ``,`` or opens with ``[`` / ``{``
    (base64 strings hold none of the three), so their count bounds the values. msgpack: the
    values are walked (a ``bin`` / ``str`` payload is skipped by its length) until more than
    ``limit`` were seen.
    """
    if len(body) <= limit:
        return
    if kind == codec.JSON:
        n = body.count(b",") + body.count(b"[") + body.count(b"{") + 1
    else:
        n = _msgpack_values(body, limit)
    if n > limit:
        raise ServiceError(413, ErrorCode.PAYLOAD_TOO_LARGE,
                           f"the body holds more than max_body_items ({limit}) values; send "
                           "large arrays as binary NDArray fields", "body",
                           limit="max_body_items")


# payload-length bytes of the msgpack types with a length field, by first byte
_MP_LEN = {0xC4: 1, 0xC5: 2, 0xC6: 4, 0xD9: 1, 0xDA: 2, 0xDB: 4}
_MP_EXT = {0xC7: 1, 0xC8: 2, 0xC9: 4}
_MP_FIXED = {0xC0: 0, 0xC2: 0, 0xC3: 0, 0xCA: 4, 0xCB: 8, 0xCC: 1, 0xCD: 2, 0xCE: 4, 0xCF: 8,
             0xD0: 1, 0xD1: 2, 0xD2: 4, 0xD3: 8, 0xD4: 2, 0xD5: 3, 0xD6: 5, 0xD7: 9, 0xD8: 17}
_MP_CONTAINER = {0xDC: (2, 1), 0xDD: (4, 1), 0xDE: (2, 2), 0xDF: (4, 2)}


def _msgpack_values(body: bytes, limit: int) -> int:
    """The values of a msgpack ``body`` (at most ``limit + 1``: it stops there)."""
    i, n, end = 0, 0, len(body)
    while i < end and n <= limit:
        b = body[i]
        n += 1
        i += 1
        if b <= 0x7F or b >= 0xE0 or 0x80 <= b <= 0x9F:
            continue  # fixint; a fixmap / fixarray's items come next
        if b <= 0xBF:  # fixstr
            i += b & 0x1F
        elif b in _MP_FIXED:
            i += _MP_FIXED[b]
        elif b in _MP_LEN:
            w = _MP_LEN[b]
            i += w + int.from_bytes(body[i:i + w], "big")
        elif b in _MP_EXT:
            w = _MP_EXT[b]
            i += w + 1 + int.from_bytes(body[i:i + w], "big")
        elif b in _MP_CONTAINER:
            i += _MP_CONTAINER[b][0]
        # 0xC1 (never used): malformed; msgpack's own decoder says so
    return n


# ---------------------------------------------------------------------- decoded images
def image_size(img: m.ImageData) -> tuple[int, int, int]:
    """(width, height, bytes per pixel decoded) of an image, from its header (PNG / JPEG:
    Pillow reads the header only; raw: its shape); (0, 0, 0) when unreadable (the decoding
    step refuses it later)."""
    if img.encoding == "raw":
        if img.shape is None or img.dtype is None or len(img.shape) != 3:
            return 0, 0, 0
        return int(img.shape[1]), int(img.shape[0]), 3 * (1 if img.dtype == "uint8" else 4)
    from PIL import Image

    try:
        with Image.open(io.BytesIO(img.data)) as im:
            w, h = im.size
            bands = len(im.getbands())
            depth = 2 if im.mode in ("I;16", "I;16B", "I", "F") else 1
            return int(w), int(h), bands * depth
    except Exception:
        return 0, 0, 0


def decoded_bytes(o: m.ObservationIn) -> int:
    """Bytes one observation's image and depth take decoded: a PNG / JPEG's decoding buffer
    plus its RGB uint8 array, a raw image's stored copy, a depth map's float32 array and its
    scaled copy."""
    total = 0
    if o.image is not None:
        w, h, px = image_size(o.image)
        if o.image.encoding == "raw":
            total += w * h * px
        else:
            total += w * h * (px + 3 + (3 if px != 3 else 0))
    if o.depth is not None:
        total += math.prod(o.depth.shape) * 8
    return total


def request_decoded_bytes(op: str, req: BaseModel | None) -> int:
    """The decoded bytes of the frames a validated request carries (0: none)."""
    frames: Any = None
    if op == "add_observations" and isinstance(req, m.ObservationsIn):
        frames = req.observations
    elif op == "create_session" and isinstance(req, m.SessionCreate):
        frames = req.frames
    return sum(decoded_bytes(o) for o in frames) if frames else 0
