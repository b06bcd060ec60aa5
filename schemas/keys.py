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
``agilegs/@instances/<id>/<op>``       queryable     one instance's :data:`INSTANCE_OPS`
                                                     (scale-out: the same payloads as
                                                     ``@service``)
=====================================  ============  =======================================

A query's reply is the operation's response model, or an error reply carrying an
:class:`~agilegs.schemas.errors.ErrorBody` (same body and status as over HTTP). ``get_gaussians``
with the selector parameter ``format=ply`` (or ``splat``) replies with the file's bytes instead,
encoded ``application/x-ply`` (``application/x-splat``; see
:data:`~agilegs.schemas.codec.GAUSSIAN_FILE_TYPES`). Payloads are
msgpack (JSON is accepted and answered in kind when the query's encoding says
``application/json``). With a server token, queries and publications carry the attachment
``Bearer <token>``.

``@service`` and ``@instances`` are verbatim chunks: wildcards such as ``agilegs/*/select``
never match them. An instance id is one key chunk matching :data:`INSTANCE_ID_PATTERN`.
"""

from __future__ import annotations

import re

from .fields import SESSION_ID_PATTERN

__all__ = [
    "CANDIDATES",
    "DECISIONS",
    "ERRORS",
    "FRAMES",
    "INSTANCES",
    "INSTANCE_ID_PATTERN",
    "INSTANCE_OPS",
    "LEASES",
    "MEMBERS",
    "PREFIX",
    "SERVICE",
    "SERVICE_OPS",
    "SESSION_OPS",
    "check_instance_id",
    "instance_key",
    "instances_wildcard",
    "lease_key",
    "member_key",
    "parse_instance_key",
    "parse_lease_key",
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
    "repair_session",
    "set_gaussians",
    "add_observations",
    "list_views",
    "get_frames",
    "commit",
    "set_pool",
    "extend_pool",
    "get_pool",
    "select",
    "get_information",
    "get_gaussians",
    "get_decisions",
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


# ----------------------------------------------------------------------------- instances
INSTANCES = "@instances"
"""Verbatim key chunk under which instances answer (``agilegs/@instances/<id>/<op>``)."""

INSTANCE_ID_PATTERN = r"^[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}$"
"""An instance id: one Zenoh key chunk of letters, digits, ``_``, ``-`` and ``.``."""

INSTANCE_OPS: tuple[str, ...] = ("health", "create_session", "list_sessions")

_INSTANCE_RE = re.compile(INSTANCE_ID_PATTERN)


def check_instance_id(instance: str, field: str = "instance") -> str:
    """``instance`` if it is a valid instance id, else ValueError naming ``field``."""
    if not isinstance(instance, str) or not _INSTANCE_RE.match(instance):
        raise ValueError(f"{field} {instance!r} must match {INSTANCE_ID_PATTERN}")
    return instance


def instance_key(instance: str, op: str) -> str:
    """``agilegs/@instances/<instance>/<op>`` for ``op`` in :data:`INSTANCE_OPS`."""
    if op not in INSTANCE_OPS:
        raise ValueError(f"op {op!r} is not one of {INSTANCE_OPS}")
    return f"{PREFIX}/{INSTANCES}/{check_instance_id(instance)}/{op}"


def instances_wildcard(op: str = "health") -> str:
    """``agilegs/@instances/*/<op>``: every instance's ``op``."""
    if op not in INSTANCE_OPS:
        raise ValueError(f"op {op!r} is not one of {INSTANCE_OPS}")
    return f"{PREFIX}/{INSTANCES}/*/{op}"


def parse_instance_key(key: str) -> tuple[str, str]:
    """``(instance, op)`` of ``agilegs/@instances/<instance>/<op>``; ValueError otherwise."""
    parts = str(key).split("/")
    if len(parts) != 4 or parts[0] != PREFIX or parts[1] != INSTANCES:
        raise ValueError(f"key {key!r} is not {PREFIX}/{INSTANCES}/<instance>/<op>")
    return check_instance_id(parts[2], "key"), parts[3]


# ---------------------------------------------------------------------------- a fleet's leases
LEASES = "@leases"
"""Liveliness tokens of a fleet (instances sharing an object store): ``agilegs/@leases/<session>
/<instance>`` while an instance owns a session, ``agilegs/@members/<instance>`` while an
instance is up (a chunk beginning with ``@`` is matched by no wildcard: two prefixes)."""
MEMBERS = "@members"


def lease_key(session: str, instance: str) -> str:
    """``agilegs/@leases/<session>/<instance>``: ``instance`` owns ``session``."""
    return f"{PREFIX}/{LEASES}/{_check_session(session)}/{check_instance_id(instance)}"


def member_key(instance: str) -> str:
    """``agilegs/@members/<instance>``: ``instance`` is up."""
    return f"{PREFIX}/{MEMBERS}/{check_instance_id(instance)}"


def parse_lease_key(key: str) -> tuple[str, str]:
    """``(session, instance)`` of a lease key, ``(MEMBERS, instance)`` of a member key;
    ValueError otherwise."""
    parts = str(key).split("/")
    if len(parts) == 3 and parts[0] == PREFIX and parts[1] == MEMBERS:
        return MEMBERS, check_instance_id(parts[2], "key")
    if len(parts) != 4 or parts[0] != PREFIX or parts[1] != LEASES:
        raise ValueError(f"key {key!r} is not {PREFIX}/{LEASES}/<session>/<instance>")
    return _check_session(parts[2]), check_instance_id(parts[3], "key")
