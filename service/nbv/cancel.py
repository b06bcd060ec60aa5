"""Cooperative cancellation points for long computations.

A caller that may give up on a computation runs it inside :func:`scope` with a ``check``
function; the loops of the selection methods (one candidate, one acquired view, one pixel
batch at a time) call :func:`checkpoint`, which calls ``check``: it returns to go on, or
raises to stop the computation there (the exception propagates to the caller unchanged).
Outside a scope :func:`checkpoint` does nothing. The scope is per thread.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

__all__ = ["checkpoint", "scope"]

_local = threading.local()


@contextmanager
def scope(check: Callable[[], None]) -> Iterator[None]:
    """Run the block with ``check`` as this thread's cancellation check (scopes nest: the
    inner one applies until it ends)."""
    prev = getattr(_local, "check", None)
    _local.check = check
    try:
        yield
    finally:
        _local.check = prev


def checkpoint() -> None:
    """Call this thread's cancellation check, if any (it raises to cancel)."""
    check = getattr(_local, "check", None)
    if check is not None:
        check()
