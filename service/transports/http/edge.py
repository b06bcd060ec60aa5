"""The HTTP server's edge: how long a connection may take to send a request, how many may be
open, and memory handed back to the operating system.

- :class:`EdgeProtocol` is uvicorn's h11 protocol with two read deadlines. A connection must
  send a request's complete headers within ``header_timeout`` seconds of opening (or of its
  previous response); bytes trickling in do not extend it. Once the headers are in, the whole
  body must arrive within ``body_timeout`` seconds. A connection past either deadline is
  closed: one still waiting for headers silently (logged at DEBUG), one in the middle of a
  body as a client that hung up (logged once at INFO with the reason, the request's work
  cancelled, status 499 in the metrics).
- :func:`uvicorn_config` gives uvicorn the protocol, the keep-alive limit
  (``keep_alive_timeout``: an idle connection between two requests is closed after it), the
  connection cap (``max_connections``: beyond it a request gets 503) and the largest request
  head (``max_header_bytes``; beyond, 400).
- :func:`tune_allocator` and :func:`release_memory`: glibc's allocator keeps freed memory in
  its arenas and raises its mmap threshold after large frees, so a burst of large bodies
  leaves the process at its peak. Buffers of 1 MiB and more are mmapped (returned at once
  when freed), at most 4 arenas are used, and :func:`release_memory` (``malloc_trim``) is
  called when the last large body in flight is done. Elsewhere than glibc both do nothing.
"""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import logging
import resource
import threading
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from ...settings import Settings

__all__ = ["TIMED_OUT", "EdgeProtocol", "raise_file_limit", "release_memory", "tune_allocator",
           "uvicorn_config"]

log = logging.getLogger(__name__)


TIMED_OUT = "agilegs.body_timeout"
"""The scope key the protocol sets (to ``body_timeout``) on a request whose connection it
closed because the body was late."""


class EdgeProtocol(H11Protocol):
    """uvicorn's h11 protocol with a header and a body read deadline (class attributes,
    set by :func:`protocol_class`)."""

    header_timeout: float = 10.0
    body_timeout: float = 60.0
    timed_out: dict[str, int] = {"headers": 0, "body": 0}

    _deadline: asyncio.TimerHandle | None = None
    _phase: str | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm("headers", self.header_timeout)

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        self._follow()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():
            self._phase = None
            self._follow()

    def _follow(self) -> None:
        """Arm the deadline of what the connection is waiting for: the next request's
        headers, the current request's body, or nothing (the request is in)."""
        state = self.conn.their_state
        if state is h11.IDLE:
            if self._phase != "headers" and self.conn.our_state in (h11.IDLE, h11.DONE):
                self._arm("headers", self.header_timeout)
        elif state is h11.SEND_BODY:
            if self._phase != "body":
                self._arm("body", self.body_timeout)
        else:
            self._disarm()

    def _arm(self, phase: str, seconds: float) -> None:
        self._disarm()
        self._phase = phase
        self._deadline = self.loop.call_later(seconds, self._expired, phase)

    def _disarm(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None
        self._phase = None

    def _expired(self, phase: str) -> None:
        self._deadline = None
        if self.transport.is_closing():
            return
        type(self).timed_out[phase] = type(self).timed_out.get(phase, 0) + 1
        who = f"{self.client[0]}:{self.client[1]}" if self.client else "a client"
        if phase == "headers":
            log.debug("closing the connection of %s: no complete request headers within "
                      "%.0f s (header_timeout)", who, self.header_timeout)
        else:  # the request reading the body logs it, once (agilegs.service.transports.http.routes)
            self.scope[TIMED_OUT] = self.body_timeout  # type: ignore[literal-required]
            log.debug("closing the connection of %s: the body of %s %s did not arrive within "
                      "%.0f s (body_timeout)", who, self.scope.get("method"),
                      self.scope.get("path"), self.body_timeout)
        self.transport.close()


def protocol_class(settings: Settings) -> type[EdgeProtocol]:
    """:class:`EdgeProtocol` with the deadlines of ``settings``."""
    return type("EdgeProtocol", (EdgeProtocol,), {
        "header_timeout": settings.header_timeout, "body_timeout": settings.body_timeout,
        "timed_out": {"headers": 0, "body": 0}})


def uvicorn_config(settings: Settings) -> dict[str, Any]:
    """The ``uvicorn.Config`` arguments of the edge settings."""
    return {"http": protocol_class(settings),
            "timeout_keep_alive": settings.keep_alive_timeout,
            "limit_concurrency": settings.max_connections,
            "h11_max_incomplete_event_size": settings.max_header_bytes,
            "backlog": min(2048, settings.max_connections)}


def raise_file_limit(connections: int) -> None:
    """Raise the soft limit of open files to what ``connections`` need (up to the hard
    limit); a warning when the hard limit is lower."""
    want = connections + 1024  # the state folder, Zenoh, the log
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or soft >= want:
        return
    new = want if hard == resource.RLIM_INFINITY else min(want, hard)
    try:
        resource.setrlimit(resource.RLIMIT_NOFILE, (new, hard))
    except (ValueError, OSError):
        new = soft
    if new < want:
        log.warning("max_connections is %d but the process may open only %d files "
                    "(ulimit -n): connections beyond are refused by the OS", connections, new)


_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8

_libc: Any = None
_lock = threading.Lock()
_trimming = False


def _glibc() -> Any:
    global _libc
    if _libc is None:
        try:
            lib = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            lib.malloc_trim, lib.mallopt  # noqa: B018 - glibc only
            _libc = lib
        except (OSError, AttributeError):
            _libc = False
    return _libc or None


def tune_allocator(mmap_threshold: int = 1 << 20, trim_threshold: int = 8 << 20,
                   arenas: int = 4) -> bool:
    """glibc: buffers of ``mmap_threshold`` bytes and more are mmapped (freed at once), the
    heap's top is trimmed past ``trim_threshold``, at most ``arenas`` arenas. False
    elsewhere."""
    libc = _glibc()
    if libc is None:
        return False
    ok = (libc.mallopt(_M_MMAP_THRESHOLD, mmap_threshold) == 1
          and libc.mallopt(_M_TRIM_THRESHOLD, trim_threshold) == 1
          and libc.mallopt(_M_ARENA_MAX, arenas) == 1)
    return bool(ok)


def release_memory() -> bool:
    """Hand the allocator's free memory back to the OS (glibc ``malloc_trim``); True when
    it ran (False elsewhere, or while another call runs)."""
    global _trimming
    libc = _glibc()
    if libc is None:
        return False
    with _lock:
        if _trimming:
            return False
        _trimming = True
    try:
        libc.malloc_trim(0)
    finally:
        with _lock:
            _trimming = False
    return True
