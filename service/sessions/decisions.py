"""The decisions feed's log (see :mod:`agilegs.schemas.decisions`): per session, the newest
decisions with their sequence numbers, and the clients waiting for the next one.

The gateway's decision hook :meth:`DecisionLog.record` numbers every decision made on this
instance 1, 2, ... per session, in the order the hooks ran (the order the server finished
them; the same order as the Zenoh publication), and keeps the newest ``capacity`` of each
session in memory; a reader asking for older ones is told how many it ``missed``. Nothing
here is persisted: a restarted server starts a new ``epoch`` and numbers from 1 again.

A session's log is opened when the session is created (or on first use, for sessions loaded
at start) and closed when it is deleted: waiting readers are woken and told ``closed``, and
the closed log is kept (the last :data:`CLOSED_KEPT` of them) for the readers it woke, which
answer from it with ``closed`` (:meth:`DecisionLog.read_closed` for a reader woken outside
:meth:`DecisionLog.read`); a new read of a deleted session is refused (404) by the registry,
as the session is.

Waiting: :meth:`DecisionLog.read` blocks its thread (a Zenoh query, a forwarded request), at
most ``max_waiters`` at once (a read beyond that answers at once); the HTTP transport waits
on its event loop with :meth:`DecisionLog.wait_async`, holding no thread.
:meth:`DecisionLog.shutdown` wakes every waiter (the server is stopping).
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import threading
import time
import uuid
from collections import OrderedDict, deque
from collections.abc import Callable
from contextlib import suppress

from agilegs.schemas import DecisionEvent, DecisionsOut, SelectResponse

__all__ = ["CLOSED_KEPT", "DecisionLog"]

log = logging.getLogger(__name__)

CLOSED_KEPT = 64
"""Closed (deleted) sessions' logs kept for their readers to finish."""


class _SessionLog:
    """One session's log: its epoch, the newest decisions, and who listens."""

    def __init__(self, epoch: str, capacity: int) -> None:
        self.epoch = epoch
        self.entries: deque[DecisionEvent] = deque(maxlen=capacity)
        self.last_seq = 0
        self.closed = False
        self.listeners: dict[int, Callable[[], None]] = {}


class DecisionLog:
    """The decisions of every session of one server (see the module docstring).

    Args:
        capacity: decisions kept per session (older ones are dropped, and counted as
            ``missed`` by a reader that asks for them).
        max_waiters: blocking reads allowed to wait at once (each holds a thread).
    """

    def __init__(self, capacity: int = 100, max_waiters: int = 8) -> None:
        if capacity < 1 or max_waiters < 0:
            raise ValueError("capacity must be >= 1 and max_waiters >= 0")
        self.capacity = capacity
        self.max_waiters = max_waiters
        self._run = uuid.uuid4().hex[:10]
        self._incarnations = itertools.count(1)
        self._tokens = itertools.count(1)
        self._cond = threading.Condition()
        self._open: dict[str, _SessionLog] = {}
        self._closed: OrderedDict[str, _SessionLog] = OrderedDict()
        self._waiting = 0
        self.stopping = False

    # ------------------------------------------------------------------ sessions
    def _new(self) -> _SessionLog:
        return _SessionLog(f"{self._run}-{next(self._incarnations)}", self.capacity)

    def _get(self, session: str) -> _SessionLog:
        """The session's open log, else its closed one, else a new open one (lock held)."""
        slog = self._open.get(session) or self._closed.get(session)
        if slog is None:
            slog = self._open[session] = self._new()
        return slog

    def open(self, session: str) -> None:
        """A session was created: a new log (new epoch) replaces any earlier one."""
        with self._cond:
            old = self._open.pop(session, None)
            self._closed.pop(session, None)
            self._open[session] = self._new()
            if old is not None:
                old.closed = True
            wake = self._wake(old)
        _call(wake)

    def close(self, session: str) -> None:
        """A session was deleted: its readers are told ``closed``."""
        with self._cond:
            slog = self._open.pop(session, None)
            if slog is None:
                return
            slog.closed = True
            self._closed[session] = slog
            while len(self._closed) > CLOSED_KEPT:
                self._closed.popitem(last=False)
            wake = self._wake(slog)
        _call(wake)

    def shutdown(self) -> None:
        """The server is stopping: every waiter answers now (and no new one waits)."""
        with self._cond:
            self.stopping = True
            wake = [cb for s in list(self._open.values()) + list(self._closed.values())
                    for cb in s.listeners.values()]
            self._cond.notify_all()
        _call(wake)

    def _wake(self, slog: _SessionLog | None) -> list[Callable[[], None]]:
        self._cond.notify_all()
        return list(slog.listeners.values()) if slog is not None else []

    # ------------------------------------------------------------------ writing
    def record(self, session: str, decision: SelectResponse) -> None:
        """Append ``decision`` to the session's log, numbered (the gateway's decision
        hook)."""
        with self._cond:
            slog = self._get(session)
            seq = slog.last_seq + 1
            slog.entries.append(DecisionEvent.model_construct(seq=seq, decision=decision))
            slog.last_seq = seq
            wake = self._wake(slog)
        _call(wake)

    # ------------------------------------------------------------------ reading
    def read(self, session: str, after: int = 0, limit: int = 100, wait: float = 0.0
             ) -> DecisionsOut:
        """The decisions after ``after`` (at most ``limit``); with none newer, block up to
        ``wait`` seconds for one (unless ``max_waiters`` reads wait already)."""
        deadline = time.monotonic() + max(0.0, wait)
        with self._cond:
            slog = self._get(session)
            if wait > 0 and not self._answerable(slog, after) and (
                    self._waiting < self.max_waiters):
                self._waiting += 1
                try:
                    while not self._answerable(slog, after):
                        remaining = deadline - time.monotonic()
                        if remaining <= 0:
                            break
                        self._cond.wait(remaining)
                finally:
                    self._waiting -= 1
            return self._out(session, slog, after, limit)

    def read_closed(self, session: str, after: int = 0, limit: int = 100
                    ) -> DecisionsOut | None:
        """A deleted session's closed log after ``after`` (``closed`` once read to its
        end), or None when no closed log of it is kept."""
        with self._cond:
            slog = self._closed.get(session)
            if slog is None or session in self._open:
                return None
            return self._out(session, slog, after, limit)

    def has_news(self, session: str, after: int) -> bool:
        """Whether a read after ``after`` would answer without waiting."""
        with self._cond:
            return self._answerable(self._get(session), after)

    def _answerable(self, slog: _SessionLog, after: int) -> bool:
        # after > last_seq: a decision this log never made (another epoch): answer at once
        return slog.last_seq != after or slog.closed or self.stopping

    def _out(self, session: str, slog: _SessionLog, after: int, limit: int) -> DecisionsOut:
        held = [e for e in slog.entries if e.seq > after][:limit]
        first = slog.entries[0].seq if slog.entries else slog.last_seq + 1
        missed = max(0, min(first, slog.last_seq + 1) - after - 1)
        next_after = held[-1].seq if held else min(after, slog.last_seq)
        return DecisionsOut.model_construct(
            session=session, epoch=slog.epoch, decisions=held, last_seq=slog.last_seq,
            next_after=next_after, missed=missed,
            closed=slog.closed and next_after >= slog.last_seq)

    # ------------------------------------------------------------------ waiting on a loop
    def listen(self, session: str, callback: Callable[[], None]) -> int:
        """Call ``callback`` (from any thread, quickly) when the session's log changes, it
        closes or the server stops; a token for :meth:`unlisten`."""
        with self._cond:
            token = next(self._tokens)
            self._get(session).listeners[token] = callback
            return token

    def unlisten(self, session: str, token: int) -> None:
        with self._cond:
            for slog in (self._open.get(session), self._closed.get(session)):
                if slog is not None:
                    slog.listeners.pop(token, None)

    async def wait_async(self, session: str, after: int, timeout: float) -> None:
        """Wait on the running event loop, up to ``timeout`` s, until a read after ``after``
        would answer (a newer decision, the session closed, the server stopping)."""
        loop = asyncio.get_running_loop()
        event = asyncio.Event()

        def wake() -> None:
            with suppress(RuntimeError):  # the loop is closed: nobody waits any more
                loop.call_soon_threadsafe(event.set)

        token = self.listen(session, wake)
        try:
            if self.has_news(session, after):
                return
            with suppress(TimeoutError):
                await asyncio.wait_for(event.wait(), max(0.0, timeout))
        finally:
            self.unlisten(session, token)


def _call(callbacks: list[Callable[[], None]]) -> None:
    for cb in callbacks:
        try:
            cb()
        except Exception:  # a listener must not break the writer
            log.exception("decision listener failed")
