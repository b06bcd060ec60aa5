"""Selections on the wire: a session's selection defaults, the select request and the decision."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, model_validator

from agilegs.config.selection import FieldName, Method, ShortlistStrategy

from .config import SelectConfigPatch
from .fields import STRICT, UNIQUE, EmbodiedK, Id, Seed, ShortlistSize, unique
from .forms import RULES_KEY, WireInt
from .geometry import Pose, PoseList
from .pool import Candidate, PoolIn
from .views import View

__all__ = [
    "MAX_TARGETS",
    "ScoredCandidate",
    "SelectDefaults",
    "SelectRequest",
    "SelectResponse",
]


MAX_TARGETS = 1024
"""The most target poses a select request carries (``config.target_views`` of them are used)."""


class SelectDefaults(BaseModel):
    """A session's selection defaults; every select request may override each of them."""

    model_config = STRICT

    method: Method = Field(default="agile", description="selection method")
    shortlist_size: WireInt = Field(default=10, ge=1, le=1024, description="shortlist size N")
    shortlist: ShortlistStrategy = Field(
        default="leverage", description="shortlist strategy of agile / agile_plus"
    )
    embodied_k: EmbodiedK | None = Field(
        default=None,
        description="embodied mode: only the K candidates nearest the current view are eligible",
    )
    seed: WireInt = Field(default=0, ge=0, le=2**63 - 1, description="random seed")
    fields: list[FieldName] | None = Field(
        default=None, description="parameter blocks entering the information (None: all five)",
        json_schema_extra=UNIQUE,
    )
    config: SelectConfigPatch = Field(
        default_factory=SelectConfigPatch,
        description="further SelectConfig fields, e.g. {'anchor': {'iterations': 1}}",
    )

    @model_validator(mode="after")
    def _unique_fields(self) -> SelectDefaults:
        unique(self.fields, "fields")
        return self

class SelectRequest(BaseModel):
    """Choose the next view among the pool. Unset fields take the session's defaults.

    Embodied mode (``embodied_k``) restricts the choice to the K candidates nearest the
    current view: ``current_id`` (a candidate), ``current_pose``, or else the last acquired
    view. ``pool`` replaces the pool first (as set_pool does, persisted); a pool that is the
    session's pool as it is (the same poses in the same order, the same ids or none) leaves
    it, its ids and the version unchanged. ``commit``
    acquires the chosen candidate (as a commit does) in the same step. A selection without
    commit changes nothing persisted; the next acquisition (a commit, or an observation of a
    new view) moves the selector's warm state on as ``commit`` would have.

    ``targets`` are the views of interest of ``config.objective = "target"`` (full_eig's
    scores, agile_plus's rerank: the fall of these views' predicted render variance); without
    them that objective's targets are the pool. They are refused with the ``eig`` objective.
    """

    model_config = ConfigDict(extra="forbid", strict=True, json_schema_extra={
        "not": {"required": ["current_id", "current_pose"], "properties": {
            "current_id": {"type": "integer"}, "current_pose": {"type": "object"}}},
        RULES_KEY: ["targets-objective"]})

    method: Method | None = None
    shortlist_size: ShortlistSize | None = None
    shortlist: ShortlistStrategy | None = None
    embodied_k: EmbodiedK | None = None
    seed: Seed | None = None
    fields: list[FieldName] | None = Field(default=None, json_schema_extra=UNIQUE)
    config: SelectConfigPatch | None = Field(
        default=None, description="SelectConfig fields, merged over the session's config"
    )
    current_id: Id | None = Field(default=None, description="the current view, a candidate id")
    current_pose: Pose | None = Field(default=None, description="the current view's pose")
    pool: PoolIn | None = Field(default=None, description="replace the pool before selecting")
    targets: PoseList | None = Field(
        default=None, min_length=1, max_length=MAX_TARGETS,
        description="camera-to-world poses of the views of interest of config.objective "
        "'target' (default: the pool); only with that objective")
    commit: bool = Field(default=False, description="acquire the chosen candidate")

    @model_validator(mode="after")
    def _current(self) -> SelectRequest:
        if self.current_id is not None and self.current_pose is not None:
            raise ValueError("give current_id or current_pose, not both")
        unique(self.fields, "fields")
        return self

class ScoredCandidate(BaseModel):
    id: int
    score: float | None = Field(description="the method's score where it computed one")

class SelectResponse(BaseModel):
    """A decision: the chosen candidate, the shortlist with scores, the anchor, timings.

    ``latency_ms`` is the selection core's own breakdown (anchor, scoring, leverage,
    rerank, total); ``core_ms`` adds the session work around it (pose conversion, id
    mapping, and the commit when asked); ``server_ms`` runs from the request's arrival to
    the response being ready to encode. Transport overhead = round trip - ``latency_ms.total``.
    """

    session: str
    method: str
    chosen: Candidate
    shortlist: list[ScoredCandidate]
    anchor: Pose | None = Field(description="anchor pose (agile, agile_plus)")
    scores: list[ScoredCandidate] = Field(description="every score the method computed")
    eligible: list[int] = Field(description="candidate ids that could be chosen")
    psi_trace: list[float]
    latency_ms: dict[str, float]
    core_ms: float
    server_ms: float | None = None
    committed: View | None = Field(description="the acquired view when commit was asked")
    version: int
    time: float = Field(description="unix time (s) of the decision")
