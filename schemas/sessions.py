"""Sessions on the wire: creating one, its state, the listing, damage and repair, deletion,
and the server's health."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, model_validator

from .fields import MAX_OBSERVATIONS_WIRE, SessionId
from .forms import WireInt
from .gaussians import GaussiansIn, GaussiansSummary
from .geometry import Bounds, Intrinsics
from .information import InformationConfig, InformationSummary
from .mapper import MapperOptions, MapperStatus
from .pool import PoolIn
from .selection import SelectDefaults
from .views import InitialFrame, frames_in

__all__ = [
    "Deleted",
    "FileProblem",
    "Health",
    "Repaired",
    "SessionCreate",
    "SessionDamage",
    "SessionInfo",
    "SessionList",
    "SessionState",
    "SessionSummary",
]


class SessionCreate(BaseModel):
    """Create a session: empty with scene ``bounds`` (random Gaussians inside them), from
    uploaded ``gaussians``, or from initial posed ``frames`` (RGB or RGB-D).

    With RGB-D frames and no Gaussians, the map is initialised by back-projecting the depth
    (``init_gaussians`` points, coloured from the images; the depth must hold a positive
    value); with RGB frames only, from ``bounds`` when given, else the session starts without
    Gaussians (set them with ``set_gaussians``; a selection answers ``map_empty`` until then).
    Frames become acquired views (and update Ĥ). ``pool`` sets the initial candidate pool.
    """

    model_config = ConfigDict(
        extra="forbid",
        strict=True,
        # bounds, gaussians or a frame: "not none of them" (an anyOf of the three would make
        # code generators publish no model for the body)
        json_schema_extra={"not": {"properties": {
            "bounds": {"type": "null"}, "gaussians": {"type": "null"}, "frames": {"maxItems": 0}}}},
    )

    id: SessionId | None = Field(default=None, description="session id (generated if absent)")
    intrinsics: Intrinsics = Field(description="camera of the candidates and of Ĥ")
    bounds: Bounds | None = Field(default=None, description="scene bounds")
    gaussians: GaussiansIn | None = Field(default=None, description="initial Gaussians")
    frames: Annotated[list[InitialFrame], BeforeValidator(frames_in)] = Field(
        default_factory=list, max_length=MAX_OBSERVATIONS_WIRE,
        description="initial posed frames (each with a pose; no candidate_id or view_id)",
    )
    init_gaussians: WireInt = Field(
        default=1000, ge=0, le=1_000_000,
        description="Gaussians created from bounds or depth (with depth, 0 keeps one per valid "
                    "depth pixel; more than max_gaussians is refused)"
    )
    seed: WireInt = Field(default=0, ge=0, le=2**63 - 1,
                          description="seed of the initialisation")
    pool: PoolIn | None = Field(default=None, description="initial candidate pool")
    defaults: SelectDefaults = Field(default_factory=SelectDefaults)
    information: InformationConfig = Field(default_factory=InformationConfig)
    mapper: MapperOptions = Field(default_factory=MapperOptions)

    @model_validator(mode="after")
    def _has_scene(self) -> SessionCreate:
        if self.bounds is None and self.gaussians is None and not self.frames:
            raise ValueError("give bounds, gaussians, or frames")
        return self

class FileProblem(BaseModel):
    """One state file of a session that does not check out."""

    file: str = Field(description="path under the session's folder: manifest.json, "
                                  "gaussians.<v>.pt, information.<v>.pt, pool.<v>.pt, "
                                  "views/<view>.rgb.<ext>, views/<view>.depth.npy")
    problem: str = Field(description="what is wrong: missing, truncated (n of m bytes), "
                                     "checksum mismatch, unreadable (why)")

class SessionDamage(BaseModel):
    """Why a session is damaged, and what ``repair_session`` would do about it."""

    files: list[FileProblem] = Field(description="every file that does not check out")
    version: int | None = Field(
        default=None, description="the damaged version (None: its manifest is unreadable)")
    repairable: bool = Field(
        description="whether repair_session can bring the session back; if not, delete it or "
                    "restore its folder from a backup")
    rollback_to: int | None = Field(
        default=None, description="repair_session rolls the session back to this intact "
                                  "earlier version (what later versions changed is lost)")
    drop_frames: list[int] = Field(
        default_factory=list, description="views whose damaged image / depth repair_session "
                                          "drops (the views, their poses and Ĥ stay)")
    repair: str = Field(description="what repair_session would do, in words")
    detected_at: float = Field(description="unix time (s) the damage was found")

SessionState = Literal["ok", "damaged"]

class SessionSummary(BaseModel):
    id: str
    state: SessionState = Field(
        default="ok", description="damaged: the session's files on disk do not check out "
                                  "(see damage); its operations answer 409 session_damaged, "
                                  "but for repair_session and delete_session")
    version: int | None = Field(description="incremented by every acknowledged state change "
                                            "(None: damaged and unknown)")
    num_gaussians: int | None = Field(description="None: damaged and unknown")
    pool_size: int | None = Field(description="None: damaged and unknown")
    num_views: int | None = Field(description="None: damaged and unknown")
    updated_at: float | None = Field(description="None: damaged and unknown")
    damage: SessionDamage | None = Field(default=None, description="what is damaged (state "
                                                                   "damaged only)")

class SessionInfo(BaseModel):
    """A session's state (its arrays are read through their own operations)."""

    id: str
    created_at: float = Field(description="unix time (s)")
    updated_at: float = Field(description="unix time (s) of the last state change")
    version: int = Field(description="incremented by every acknowledged state change")
    intrinsics: Intrinsics
    bounds: Bounds | None
    defaults: SelectDefaults
    information_config: InformationConfig
    gaussians: GaussiansSummary
    information: InformationSummary
    pool_size: int
    next_candidate_id: int
    num_views: int
    last_view_id: int | None
    mapper: MapperStatus | None = Field(default=None, description="the mapper's progress")

class SessionList(BaseModel):
    sessions: list[SessionSummary]

class Deleted(BaseModel):
    id: str
    deleted: bool = True

class Repaired(BaseModel):
    """What ``repair_session`` did."""

    id: str
    repaired: bool = Field(description="False: the session was not damaged; nothing changed")
    rolled_back_to: int | None = Field(
        default=None, description="the intact earlier version restored (what later versions "
                                  "changed is lost)")
    dropped_frames: list[int] = Field(
        default_factory=list, description="views whose damaged image / depth was dropped")
    version: int = Field(description="the session's version now (a repair is a state change)")
    message: str = Field(description="what was done, in words")

class Health(BaseModel):
    status: Literal["ok"] = "ok"
    version: str
    sessions: int = Field(description="sessions held (damaged ones included)")
    damaged: int = Field(default=0, description="sessions held whose files do not check out")
    zenoh: bool
    uptime_s: float
