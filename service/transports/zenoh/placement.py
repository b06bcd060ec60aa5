"""Where a session lives in a cluster: the keys an owner declares, an instance's default
id, the placement policy of a new session, and the errors of a session or instance that no
one answers for (:mod:`agilegs.service.transports.zenoh.cluster`)."""

from __future__ import annotations

import re
import socket
from collections.abc import Mapping

from agilegs import schemas as m
from agilegs.schemas import keys

from ...errors import ServiceError

__all__ = ["HANDOVER_RETRY", "default_instance_id", "instance_unavailable", "placement_order",
           "session_queryable_key", "session_unavailable"]

HANDOVER_RETRY = 0.2  # the retry_after of a fleet's session_unavailable (s)

_SESSION_RE = re.compile(m.SESSION_ID_PATTERN)


def session_queryable_key(session: str) -> str:
    """``agilegs/<session>/*``: every operation of one session."""
    if not _SESSION_RE.match(session):
        raise ValueError(f"session id {session!r} must match {m.SESSION_ID_PATTERN}")
    return f"{keys.PREFIX}/{session}/*"


def default_instance_id(hostname: str | None = None, port: int = 8000) -> str:
    """``<hostname>-<port>`` with the characters an instance id may not hold replaced by
    ``-`` (the hostname's domain part dropped); a valid id in every case."""
    host = (hostname if hostname is not None else socket.gethostname()).split(".", 1)[0]
    host = re.sub(r"[^A-Za-z0-9_-]", "-", host)[:50] or "agilegs"
    return f"{host}-{int(port)}"


def placement_order(loads: Mapping[str, int]) -> list[str]:
    """The instances to try for a new session, best first: fewest sessions, then smallest id.

    Args:
        loads: instance id -> number of sessions it holds.
    """
    return sorted(loads, key=lambda iid: (int(loads[iid]), iid))


def session_unavailable(session: str, instances: list[str], *, fleet: bool = False
                        ) -> ServiceError:
    """404 ``session_unavailable``; in a fleet with ``retry_after`` (a live instance takes a
    dead owner's sessions over: the client retries)."""
    live = ", ".join(sorted(instances))
    return ServiceError(
        404, "session_unavailable",
        f"no instance answers for session {session!r}: it does not exist, or the instance that "
        f"owns it is down (live instances: {live})", "path.session",
        retry_after=HANDOVER_RETRY if fleet else None)


def instance_unavailable(instance: str) -> ServiceError:
    return ServiceError(404, "instance_unavailable", f"no instance {instance!r} answers",
                        "query.instance")
