"""Riding through a session's handover in a fleet: an operation answered
``session_unavailable`` *with* ``retry_after`` is retried, with backoff, within the client's
``retry_window``.

A fleet's instances say ``retry_after`` when the session's owner is gone and a live instance
is taking it over (or it moved while the request ran), and only when the request changed
nothing (no owner received it, or a stale owner's commit was fenced), so retrying it applies
it once. Without ``retry_after`` (a cluster whose instances keep their own state folders, a
session that does not exist, a write whose owner died while answering it) the error is raised
at once.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from typing import TypeVar

from .errors import SessionUnavailableError

__all__ = ["RETRY_WINDOW", "backoff", "retry_async", "retry_sync"]

T = TypeVar("T")

RETRY_WINDOW = 10.0
"""Seconds a client keeps retrying an operation through a handover (its default)."""


def backoff(attempt: int, hint: float | None) -> float:
    """Seconds before retry ``attempt`` (0, 1, ...): 50 ms doubling up to 1 s, at least the
    server's ``retry_after``."""
    return max(hint or 0.0, min(1.0, 0.05 * 2 ** attempt))


def _retryable(exc: SessionUnavailableError) -> bool:
    return exc.retry_after is not None


def retry_sync(send: Callable[[], T], window: float) -> T:
    """``send()``, retried while it raises a retryable :class:`SessionUnavailableError` and
    ``window`` seconds are not spent (then the last error is raised)."""
    deadline = time.monotonic() + window
    attempt = 0
    while True:
        try:
            return send()
        except SessionUnavailableError as exc:
            delay = backoff(attempt, exc.retry_after)
            if not _retryable(exc) or time.monotonic() + delay > deadline:
                raise
        time.sleep(delay)
        attempt += 1


async def retry_async(send: Callable[[], Awaitable[T]], window: float) -> T:
    """:func:`retry_sync` for a coroutine."""
    deadline = time.monotonic() + window
    attempt = 0
    while True:
        try:
            return await send()
        except SessionUnavailableError as exc:
            delay = backoff(attempt, exc.retry_after)
            if not _retryable(exc) or time.monotonic() + delay > deadline:
                raise
        await asyncio.sleep(delay)
        attempt += 1
