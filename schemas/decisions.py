"""The decisions feed: a session's decisions in order, for clients that follow a session.

Every decision the server makes on a session (a ``select``, over HTTP or Zenoh) gets a
sequence number, 1, 2, ... per session, in the order the server finished them, and is held
in a bounded in-memory log (the newest ``AGILEGS_DECISION_LOG`` per session). A client
follows the session with ``get_decisions(after=<the last seq it has>)``: it gets every
decision after that one, in order, each exactly once, and ``missed`` counts those the log
no longer holds. The log lives in the server's memory: ``epoch`` changes when it starts again
(a server restart, or the session deleted and created again), and numbering then starts
again at 1, so a client that sees another ``epoch`` starts over from ``after=0``.

HTTP serves it as a long poll (``GET .../decisions?after=&wait=``) and, when the request
accepts ``text/event-stream``, as server-sent events (one ``decision`` event per decision,
its ``id`` the sequence number). Zenoh serves it as the query ``agilegs/<session>/get_decisions``
besides the publication ``agilegs/<session>/decisions``.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from .selection import SelectResponse

__all__ = ["MAX_WAIT_WIRE", "DecisionEvent", "DecisionsOut", "DecisionsRequest"]

MAX_WAIT_WIRE = 60.0
"""The schema's own cap on ``wait`` (s); the server caps it lower (``AGILEGS_MAX_POLL_WAIT``)."""


class DecisionsRequest(BaseModel):
    """Read the session's decisions after ``after``, waiting up to ``wait`` seconds for one
    when none is newer (a long poll). Over HTTP the fields are query parameters."""

    model_config = ConfigDict(extra="forbid")

    after: int = Field(default=0, ge=0, le=2**53,
                       description="return the decisions with a sequence number above this "
                                   "(0: every decision the log holds)")
    wait: float = Field(default=0.0, ge=0.0, le=MAX_WAIT_WIRE,
                        description="seconds to wait for a decision when none is newer than "
                                    "after (0: answer at once; the server caps it at its "
                                    "AGILEGS_MAX_POLL_WAIT). Over HTTP with Accept: "
                                    "text/event-stream: how long the stream stays open "
                                    "(default: that cap)")
    limit: int = Field(default=100, ge=1, le=1000, description="most decisions per answer")


class DecisionEvent(BaseModel):
    """One decision and its sequence number in the session's log."""

    seq: int = Field(description="1, 2, ... per session and epoch, in the order of the decisions")
    decision: SelectResponse


class DecisionsOut(BaseModel):
    """The decisions after ``after``, oldest first."""

    session: str
    epoch: str = Field(description="the log's id: another epoch means the numbering started "
                                   "again at 1 (server restart, session created again)")
    decisions: list[DecisionEvent]
    last_seq: int = Field(description="sequence number of the newest decision (0: none yet)")
    next_after: int = Field(description="the after of the next poll: the last decision "
                                        "returned, or after (at most last_seq) when none was")
    missed: int = Field(description="decisions after `after` that the log no longer holds "
                                    "(it keeps the newest AGILEGS_DECISION_LOG per session)")
    closed: bool = Field(description="the session was deleted: no decision will follow")
