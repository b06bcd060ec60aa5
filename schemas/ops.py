"""The operation table: each operation's name (the client method and the Zenoh key's last
chunk), its HTTP route, and its request and response models."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from pydantic import BaseModel

from . import decisions as d
from .gaussians import GaussiansIn, GaussiansOut
from .information import InformationOut
from .pool import PoolIn, PoolOut
from .selection import SelectRequest, SelectResponse
from .sessions import Deleted, Health, Repaired, SessionCreate, SessionInfo, SessionList
from .views import CommitRequest, FramesOut, FramesRequest, ObservationsIn, View, ViewsOut

__all__ = ["OPERATIONS", "Operation"]


@dataclass(frozen=True)
class Operation:
    """One operation of the service."""

    name: str
    scope: Literal["service", "session"]
    http_method: str
    http_path: str
    request: type[BaseModel] | None
    response: type[BaseModel]
    summary: str
    query: bool = False
    """Over HTTP the request's fields are query parameters (a GET), not a body."""
    event_stream: bool = False
    """Over HTTP it also answers ``Accept: text/event-stream`` with server-sent events."""


def _op(
    name: str,
    scope: Literal["service", "session"],
    method: str,
    path: str,
    request: type[BaseModel] | None,
    response: type[BaseModel],
    summary: str,
    **more: bool,
) -> Operation:
    return Operation(name, scope, method, path, request, response, summary, **more)


_S = "/v1/sessions/{session}"

OPERATIONS: dict[str, Operation] = {
    op.name: op
    for op in (
        _op("health", "service", "GET", "/healthz", None, Health, "liveness and counts"),
        _op("create_session", "service", "POST", "/v1/sessions", SessionCreate,
            SessionInfo, "create a session"),
        _op("list_sessions", "service", "GET", "/v1/sessions", None, SessionList,
            "list sessions"),
        _op("get_session", "session", "GET", _S, None, SessionInfo, "read a session's state"),
        _op("delete_session", "session", "DELETE", _S, None, Deleted, "delete a session"),
        _op("repair_session", "session", "POST", _S + "/repair", None, Repaired,
            "bring a damaged session back (its last intact version, damaged frames dropped)"),
        _op("set_gaussians", "session", "PUT", _S + "/gaussians", GaussiansIn, SessionInfo,
            "replace the Gaussians"),
        _op("add_observations", "session", "POST", _S + "/observations", ObservationsIn,
            ViewsOut, "add posed frames (acquired views; update Ĥ)"),
        _op("list_views", "session", "GET", _S + "/views", None, ViewsOut,
            "list acquired views"),
        _op("get_frames", "session", "GET", _S + "/frames", FramesRequest, FramesOut,
            "read acquired views with their images and depth (one view, or all)", query=True),
        _op("commit", "session", "POST", _S + "/views", CommitRequest, View,
            "acquire a view (update Ĥ)"),
        _op("set_pool", "session", "PUT", _S + "/pool", PoolIn, PoolOut,
            "replace the candidate pool"),
        _op("extend_pool", "session", "POST", _S + "/pool", PoolIn, PoolOut,
            "add candidates to the pool"),
        _op("get_pool", "session", "GET", _S + "/pool", None, PoolOut, "read the pool"),
        _op("select", "session", "POST", _S + "/select", SelectRequest, SelectResponse,
            "choose the next view"),
        _op("get_information", "session", "GET", _S + "/information", None, InformationOut,
            "read Ĥ"),
        _op("get_gaussians", "session", "GET", _S + "/gaussians", None, GaussiansOut,
            "read the current Gaussians (the mapper's published map)"),
        _op("get_decisions", "session", "GET", _S + "/decisions", d.DecisionsRequest,
            d.DecisionsOut, "the decisions after a sequence number (long poll; server-sent "
            "events)", query=True, event_stream=True),
    )
}
