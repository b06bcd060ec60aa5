"""Request and response models of every operation (HTTP and Zenoh share them), gathered from
the modules that define them by concept: :mod:`.sessions`, :mod:`.gaussians`, :mod:`.views`
(observations and commits), :mod:`.pool`, :mod:`.selection`, :mod:`.information`,
:mod:`.mapper` (and the shared field types of :mod:`.fields`). The types they are built from
(``Pose``, ``Intrinsics``, ``Bounds``, ``NDArray``, the settings patches, ...) are importable
from here too.

Poses are camera-to-world with OpenCV axes (see :mod:`agilegs.schemas.geometry`); bytes
travel raw in msgpack and base64 in JSON (see :mod:`agilegs.schemas.arrays`). Candidate and
view ids are server-assigned (or client-chosen for candidates) integers that stay stable for
the life of a session: an id is never reused for another pose.
"""

from __future__ import annotations

from agilegs.config.selection import (
    FIELD_NAMES,
    METHODS,
    SHORTLISTS,
    FieldName,
    Method,
    ShortlistStrategy,
)

from .arrays import B64Bytes as B64Bytes
from .arrays import NDArray as NDArray
from .config import MapperConfigPatch as MapperConfigPatch
from .config import SelectConfigPatch as SelectConfigPatch
from .fields import MAX_OBSERVATIONS_WIRE as MAX_OBSERVATIONS_WIRE
from .fields import MAX_POOL_WIRE as MAX_POOL_WIRE
from .fields import SESSION_ID_PATTERN, SessionId
from .fields import EmbodiedK as EmbodiedK
from .fields import Id as Id
from .fields import Seed as Seed
from .fields import ShortlistSize as ShortlistSize
from .fields import StepsPerView as StepsPerView
from .forms import RULES_KEY as RULES_KEY
from .forms import Form as Form
from .forms import WireInt as WireInt
from .forms import integral as integral
from .forms import one_of as one_of
from .gaussians import GaussianArrays, GaussiansIn, GaussiansOut, GaussiansSummary
from .geometry import Bounds as Bounds
from .geometry import Intrinsics as Intrinsics
from .geometry import Pose as Pose
from .geometry import PoseList as PoseList
from .geometry import trusted_poses as trusted_poses
from .information import FieldSummary, InformationConfig, InformationOut, InformationSummary
from .mapper import MapperOptions, MapperState, MapperStatus
from .pool import Candidate, PoolIn, PoolOut
from .selection import ScoredCandidate, SelectDefaults, SelectRequest, SelectResponse
from .sessions import (
    Deleted,
    FileProblem,
    Health,
    Repaired,
    SessionCreate,
    SessionDamage,
    SessionInfo,
    SessionList,
    SessionState,
    SessionSummary,
)
from .views import (
    CommitRequest,
    ImageData,
    InitialFrame,
    ObservationIn,
    ObservationsIn,
    View,
    ViewsOut,
)

__all__ = [
    "FIELD_NAMES",
    "METHODS",
    "SESSION_ID_PATTERN",
    "SHORTLISTS",
    "Candidate",
    "CommitRequest",
    "Deleted",
    "FieldName",
    "FieldSummary",
    "FileProblem",
    "GaussianArrays",
    "GaussiansIn",
    "GaussiansOut",
    "GaussiansSummary",
    "Health",
    "ImageData",
    "InformationConfig",
    "InitialFrame",
    "InformationOut",
    "InformationSummary",
    "MapperOptions",
    "MapperState",
    "MapperStatus",
    "Method",
    "ObservationIn",
    "ObservationsIn",
    "PoolIn",
    "PoolOut",
    "Repaired",
    "ScoredCandidate",
    "SelectDefaults",
    "SelectRequest",
    "SelectResponse",
    "SessionCreate",
    "SessionDamage",
    "SessionId",
    "SessionInfo",
    "SessionList",
    "SessionState",
    "SessionSummary",
    "ShortlistStrategy",
    "View",
    "ViewsOut",
]
