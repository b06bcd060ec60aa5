"""Zenoh key expressions, defined once for the server and the clients.

=====================================  ============  =======================================
key expression                         kind          payload (msgpack of a schemas model)
=====================================  ============  =======================================
``agilegs/@service/health``            queryable     -> Health
``agilegs/@service/create_session``    queryable     SessionCreate -> SessionInfo
``agilegs/@service/list_sessions``     queryable     -> SessionList
``agilegs/<session>/<op>``             queryable     each of :data:`SESSION_OPS`
``agilegs/<session>/frames``           subscription  ObservationsIn, from a robot
``agilegs/<session>/candidates``       subscription  PoolIn, from a robot (replaces the pool)
``agilegs/<session>/decisions``        publication   SelectResponse, every decision
``agilegs/<session>/errors``           publication   ErrorBody, a frames/candidates refusal
=====================================  ============  =======================================

A query's reply is the operation's response model, or an error reply carrying an
:class:`~agilegs.schemas.errors.ErrorBody` (same body and status as over HTTP). Payloads are
msgpack (JSON is accepted and answered in kind when the query's encoding says
``application/json``). With a server token, queries and publications carry the attachment
``Bearer <token>``.

``@service`` is a verbatim chunk: wildcards such as ``agilegs/*/select`` never match it.
"""

from __future__ import annotations

import re

from .models import SESSION_ID_PATTERN

__all__ = [
    "CANDIDATES",
    "DECISIONS",
    "ERRORS",
    "FRAMES",
    "PREFIX",
    "SERVICE",
    "SERVICE_OPS",
    "SESSION_OPS",
    "parse_session_key",
    "service_key",
    "session_key",
    "session_wildcard",
]

PREFIX = "agilegs"
SERVICE = "@service"

SERVICE_OPS: tuple[str, ...] = ("health", "create_session", "list_sessions")
SESSION_OPS: tuple[str, ...] = (
    "get_session",
    "delete_session",
    "set_gaussians",
    "add_observations",
    "list_views",
    "commit",
    "set_pool",
    "extend_pool",
    "get_pool",
    "select",
    "get_information",
    "get_gaussians",
)
FRAMES = "frames"
CANDIDATES = "candidates"
DECISIONS = "decisions"
ERRORS = "errors"

_SESSION_RE = re.compile(SESSION_ID_PATTERN)


def _check_session(session: str) -> str:
    if not _SESSION_RE.match(session):
        raise ValueError(f"session id {session!r} must match {SESSION_ID_PATTERN}")
    return session


def service_key(op: str) -> str:
    """``agilegs/@service/<op>``."""
    if op not in SERVICE_OPS:
        raise ValueError(f"unknown service operation {op!r}")
    return f"{PREFIX}/{SERVICE}/{op}"


def session_key(session: str, op: str) -> str:
    """``agilegs/<session>/<op>`` for an operation or a topic (frames, decisions...)."""
    if op not in SESSION_OPS and op not in (FRAMES, CANDIDATES, DECISIONS, ERRORS):
        raise ValueError(f"unknown session operation or topic {op!r}")
    return f"{PREFIX}/{_check_session(session)}/{op}"


def session_wildcard(op: str = "*") -> str:
    """``agilegs/*/<op>``: every session's ``op`` (``*``: every op)."""
    return f"{PREFIX}/*/{op}"


def parse_session_key(key: str) -> tuple[str, str]:
    """``(session, op)`` of ``agilegs/<session>/<op>``; ValueError if it is not one."""
    parts = str(key).split("/")
    if len(parts) != 3 or parts[0] != PREFIX:
        raise ValueError(f"key {key!r} is not {PREFIX}/<session>/<op>")
    return parts[1], parts[2]
