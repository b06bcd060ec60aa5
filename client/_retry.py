"""Riding through a session's handover in a fleet: an operation answered
``session_unavailable`` *with* ``retry_after`` is retried, with backoff, within the client's
``retry_window``.

A fleet's instances say ``retry_after`` when the session's owner is gone and a live instance
is taking it over (or it moved while the request ran), when the request changed nothing (no
owner received it, or a stale owner's commit was fenced), and when it is a write with a
request id (every write the SDK sends has one: :mod:`agilegs.schemas.requests`), which the
session's record makes apply once however often it is sent. Without ``retry_after`` (a
cluster whose instances keep their own state folders, a session that does not exist, a write
without a request id whose owner died while answering it) the error is raised at once. A
``delete_session`` retried after a lost answer finds the session gone: that answer is its
``Deleted``.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from typing import TypeVar

from agilegs.schemas import Deleted

from ._requests import Call
from .errors import NotFoundError, SessionUnavailableError

__all__ = ["RETRY_WINDOW", "backoff", "retry_async", "retry_sync"]

T = TypeVar("T")

RETRY_WINDOW = 10.0
"""Seconds a client keeps retrying an operation through a handover (its default)."""


def backoff(attempt: int, hint: float | None) -> float:
    """Seconds before retry ``attempt`` (0, 1, ...): 50 ms doubling up to 1 s, at least the
    server's ``retry_after``."""
    return max(hint or 0.0, min(1.0, 0.05 * 2 ** attempt))


def _next_step(exc: NotFoundError, attempt: int, deadline: float, call: Call | None
               ) -> float | Deleted:
    """After attempt ``attempt`` (0, 1, ...) of ``call`` failed with ``exc``: the seconds
    to wait before the next one, or the :class:`Deleted` a retried ``delete_session`` that
    finds its session gone has earned (the attempt before deleted it, and its answer was
    lost); ``exc`` is raised when it is final (no ``retry_after``, or past ``deadline``)."""
    if isinstance(exc, SessionUnavailableError):
        delay = backoff(attempt, exc.retry_after)
        if exc.retry_after is None or time.monotonic() + delay > deadline:
            raise exc
        return delay
    if (attempt and call is not None and call.op.name == "delete_session"
            and call.session is not None):
        return Deleted(id=call.session)
    raise exc


def retry_sync(send: Callable[[], T], window: float, call: Call | None = None) -> T:
    """``send()`` (of ``call``), retried while it raises a retryable
    :class:`SessionUnavailableError` and ``window`` seconds are not spent (then the last
    error is raised)."""
    deadline = time.monotonic() + window
    attempt = 0
    while True:
        try:
            return send()
        except NotFoundError as exc:
            step = _next_step(exc, attempt, deadline, call)
        if isinstance(step, Deleted):
            return step  # type: ignore[return-value]
        time.sleep(step)
        attempt += 1


async def retry_async(send: Callable[[], Awaitable[T]], window: float,
                      call: Call | None = None) -> T:
    """:func:`retry_sync` for a coroutine."""
    deadline = time.monotonic() + window
    attempt = 0
    while True:
        try:
            return await send()
        except NotFoundError as exc:
            step = _next_step(exc, attempt, deadline, call)
        if isinstance(step, Deleted):
            return step  # type: ignore[return-value]
        await asyncio.sleep(step)
        attempt += 1
