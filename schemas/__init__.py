"""agilegs.schemas: the wire contract (pydantic models and Zenoh key expressions).

Both transports encode and decode through these models: HTTP bodies in JSON or msgpack,
Zenoh payloads in msgpack. Conventions (poses camera-to-world, OpenCV axes, 4x4 row-major
or position + quaternion x, y, z, w; bytes raw in msgpack and base64 in JSON) are in
:mod:`agilegs.schemas.geometry` and :mod:`agilegs.schemas.arrays`.
"""

from .arrays import B64Bytes, DType, NDArray
from .decisions import DecisionEvent, DecisionsOut, DecisionsRequest
from .errors import ErrorBody, ErrorInfo, ErrorItem
from .fields import SESSION_ID_PATTERN
from .gaussians import GaussianArrays, GaussiansIn, GaussiansOut, GaussiansSummary
from .geometry import Bounds, Intrinsics, Pose
from .information import FieldSummary, InformationConfig, InformationOut, InformationSummary
from .mapper import MapperOptions, MapperStatus
from .ops import OPERATIONS, Operation
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
    SessionSummary,
)
from .views import (
    CommitRequest,
    Frame,
    FramesOut,
    FramesRequest,
    ImageData,
    ObservationIn,
    ObservationsIn,
    View,
    ViewsOut,
)

__all__ = [
    "OPERATIONS",
    "SESSION_ID_PATTERN",
    "B64Bytes",
    "Bounds",
    "Candidate",
    "CommitRequest",
    "DType",
    "DecisionEvent",
    "DecisionsOut",
    "DecisionsRequest",
    "Deleted",
    "ErrorBody",
    "ErrorInfo",
    "ErrorItem",
    "FieldSummary",
    "FileProblem",
    "Frame",
    "FramesOut",
    "FramesRequest",
    "GaussianArrays",
    "GaussiansIn",
    "GaussiansOut",
    "GaussiansSummary",
    "Health",
    "ImageData",
    "InformationConfig",
    "InformationOut",
    "InformationSummary",
    "Intrinsics",
    "MapperOptions",
    "MapperStatus",
    "NDArray",
    "ObservationIn",
    "ObservationsIn",
    "Operation",
    "PoolIn",
    "PoolOut",
    "Pose",
    "Repaired",
    "ScoredCandidate",
    "SelectDefaults",
    "SelectRequest",
    "SelectResponse",
    "SessionCreate",
    "SessionDamage",
    "SessionInfo",
    "SessionList",
    "SessionSummary",
    "View",
    "ViewsOut",
]
