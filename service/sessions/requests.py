"""Writes applied once: the request id of the write being served, and the session's record
of the writes applied under one (:class:`~agilegs.service.store.records.AppliedRequest`,
:mod:`agilegs.schemas.requests`).

The transport reads a write's request id and the registry serves the write inside
:func:`serving`; a session's write looks its id up in the record first (:func:`applied`) and
answers from it when found, and otherwise records the id and its answer in the record it
commits (:func:`remember`), so that the commit and its memory of the request are one.
The record keeps the last :data:`KEEP` ids and the answers of the last :data:`KEEP_ANSWERS` of
them, each of at most :data:`MAX_ANSWER_BYTES` as JSON and all together at most
:data:`ANSWERS_BUDGET` (the newest first), so that a session whose writes carry ids commits a
manifest of bounded size.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import replace
from typing import Any

from pydantic import BaseModel

from ..errors import ServiceError
from ..store.records import AppliedRequest, SessionRecord

__all__ = ["ANSWERS_BUDGET", "KEEP", "KEEP_ANSWERS", "MAX_ANSWER_BYTES", "applied", "current",
           "remember", "replay", "serving", "was_replayed"]

KEEP = 256
KEEP_ANSWERS = 16
MAX_ANSWER_BYTES = 256 * 1024
ANSWERS_BUDGET = 512 * 1024

_current: ContextVar[tuple[str, str] | None] = ContextVar("agilegs_request", default=None)
_replayed: ContextVar[bool] = ContextVar("agilegs_request_replayed", default=False)


@contextmanager
def serving(op: str, request_id: str | None) -> Iterator[None]:
    """Serve operation ``op`` with ``request_id`` (None: a request without one); after it,
    :func:`was_replayed` says whether it was answered from the record."""
    _replayed.set(False)
    token = _current.set((request_id, op) if request_id is not None else None)
    try:
        yield
    finally:
        _current.reset(token)


def current() -> str | None:
    """The request id of the request being served here (None: none)."""
    got = _current.get()
    return got[0] if got is not None else None


def was_replayed() -> bool:
    """Whether the last request served in this context was a write applied already (its
    answer came from the record: nothing was applied, nothing is to be published)."""
    return _replayed.get()


def applied(rec: SessionRecord) -> AppliedRequest | None:
    """The write of the current request id that ``rec`` records as applied; None when there
    is no request id or it was not applied. 409 when the id was applied to another
    operation."""
    got = _current.get()
    if got is None:
        return None
    rid, op = got
    for r in reversed(rec.requests):
        if r.id == rid:
            if r.op != op:
                raise ServiceError(409, "conflict", f"request id {rid!r} was used for {r.op}, "
                                   f"not {op}: a request id names one write", "request_id")
            _replayed.set(True)
            return r
    return None


def remember(rec: SessionRecord, answer: BaseModel | None) -> SessionRecord:
    """``rec`` (the record a write commits) with the current request id recorded, ``answer``
    kept as JSON when it is small enough; ``rec`` itself without a request id."""
    got = _current.get()
    if got is None:
        return rec
    rid, op = got
    data: dict[str, Any] | None = None
    if answer is not None:
        data = answer.model_dump(mode="json")
        if _size(data) > MAX_ANSWER_BYTES:
            data = None
    new = _within_budget((*rec.requests, AppliedRequest(rid, op, rec.version, data)))
    return replace(rec, requests=new[-KEEP:])


def _size(answer: dict[str, Any]) -> int:
    """An answer's size as the JSON the manifest stores (bytes)."""
    return len(json.dumps(answer))


def _within_budget(requests: tuple[AppliedRequest, ...]) -> tuple[AppliedRequest, ...]:
    """``requests`` (oldest first) with the answers kept only for the newest
    :data:`KEEP_ANSWERS` that fit :data:`ANSWERS_BUDGET` together; the others keep their ids.
    The sizes read are at most the budget's and one answer's, whatever the record holds."""
    out = list(requests)
    count, total = 0, 0
    for i in range(len(out) - 1, -1, -1):
        r = out[i]
        if r.answer is None:
            continue
        if count < KEEP_ANSWERS:
            total += _size(r.answer)
            if total <= ANSWERS_BUDGET:
                count += 1
                continue
            count = KEEP_ANSWERS  # full: every older answer is dropped unread
        out[i] = replace(r, answer=None)
    return tuple(out)


def replay(found: AppliedRequest, response: type[BaseModel]) -> BaseModel | None:
    """The answer ``found`` kept, as ``response``; None when it was not kept."""
    if found.answer is None:
        return None
    return response.model_validate(found.answer)
