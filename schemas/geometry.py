"""Cameras and poses on the wire.

Conventions:

* A pose is **camera-to-world** (it maps camera coordinates to world coordinates) with
  **OpenCV camera axes**: x right, y down, z forward (the optical axis). Translations are
  in scene units (metres for a metric scene).
* A pose is sent either as ``matrix``, a 4x4 **row-major** homogeneous matrix
  ``[[r00, r01, r02, tx], [r10, r11, r12, ty], [r20, r21, r22, tz], [0, 0, 0, 1]]``,
  or as ``position`` ``[x, y, z]`` plus ``orientation_xyzw``, a unit quaternion in
  **ROS order x, y, z, w**. Exactly one form per pose.
* The rotation must be a proper rotation: ``max |R^T R - I| <= 1e-3``
  (:data:`ORTHONORMAL_ATOL`), ``det R > 0``, and the last row ``[0, 0, 0, 1]`` within
  1e-6; a quaternion's norm must be within 1e-3 of 1 (:data:`QUATERNION_NORM_ATOL`; it is
  normalised before use). Anything else is rejected (HTTP 422 naming the field).
* Every number must be finite (NaN and infinities are rejected) and coordinates must lie
  within +-1e6 scene units (:data:`MAX_COORD`).
* Intrinsics are pinhole, in pixels: ``fx, fy, cx, cy, width, height``; the centre of
  pixel (0, 0) is at (0.5, 0.5).
"""

from __future__ import annotations

import itertools
import math
from typing import Annotated, Any

import numpy as np
from annotated_types import Len
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializerFunctionWrapHandler,
    ValidatorFunctionWrapHandler,
    WithJsonSchema,
    WrapSerializer,
    WrapValidator,
    field_validator,
    model_validator,
)

from agilegs.config.geometry import MAX_COORD, ORTHONORMAL_ATOL, QUATERNION_NORM_ATOL

from .forms import Form, WireInt, one_of

__all__ = [
    "MAX_COORD",
    "ORTHONORMAL_ATOL",
    "QUATERNION_NORM_ATOL",
    "Bounds",
    "FiniteFloat",
    "Intrinsics",
    "Matrix4",
    "Pose",
    "PoseArrayList",
    "PoseList",
    "Vec3",
    "Vec4",
    "check_matrices",
    "trusted_poses",
    "matrix_to_quaternion_xyzw",
    "quaternion_xyzw_to_matrix",
    "rotation_error",
]

LAST_ROW_ATOL = 1e-6

ROTATION_ENTRY_MAX = math.sqrt(1.0 + ORTHONORMAL_ATOL)
"""Largest absolute entry of an accepted rotation block (implied by :data:`ORTHONORMAL_ATOL`:
a column's squared norm is at most 1 + 1e-3)."""
QUATERNION_ENTRY_MAX = 1.0 + QUATERNION_NORM_ATOL
"""Largest absolute component of an accepted quaternion (implied by its norm)."""

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
Coord = Annotated[float, Field(allow_inf_nan=False, ge=-MAX_COORD, le=MAX_COORD)]
Vec3 = Annotated[list[Coord], Len(3, 3)]
Vec4 = Annotated[list[FiniteFloat], Len(4, 4)]


def _number(lo: float, hi: float) -> dict[str, Any]:
    return {"type": "number", "minimum": lo, "maximum": hi}


_ROW = {"type": "array", "minItems": 4, "maxItems": 4, "prefixItems": [
    _number(-ROTATION_ENTRY_MAX, ROTATION_ENTRY_MAX)] * 3 + [_number(-MAX_COORD, MAX_COORD)]}
_LAST_ROW = {"type": "array", "minItems": 4, "maxItems": 4, "prefixItems": [
    _number(-LAST_ROW_ATOL, LAST_ROW_ATOL)] * 3 + [_number(1 - LAST_ROW_ATOL, 1 + LAST_ROW_ATOL)]}
MATRIX4_SCHEMA: dict[str, Any] = {
    "type": "array", "minItems": 4, "maxItems": 4, "prefixItems": [_ROW, _ROW, _ROW, _LAST_ROW],
    "description": "4x4 row-major camera-to-world matrix (OpenCV axes): rotation block "
    "orthonormal within max |R^T R - I| <= 1e-3 with det R > 0 (so its entries lie within "
    "+-sqrt(1.001)), translation within +-1e6, last row [0, 0, 0, 1] within 1e-6",
}
"""The published schema of a pose matrix: the bounds its validation implies, row by row."""
Matrix4 = Annotated[list[Vec4], Len(4, 4), WithJsonSchema(MATRIX4_SCHEMA)]
Quaternion = Annotated[
    list[Annotated[float, Field(allow_inf_nan=False, ge=-QUATERNION_ENTRY_MAX,
                                le=QUATERNION_ENTRY_MAX)]],
    Len(4, 4),
]


def rotation_error(matrix: list[list[float]]) -> float:
    """``max |R^T R - I|`` of the upper-left 3x3 block (plain Python: cheap per pose)."""
    r0, r1, r2 = matrix[0], matrix[1], matrix[2]
    err = 0.0
    for i in range(3):
        for j in range(i, 3):
            s = r0[i] * r0[j] + r1[i] * r1[j] + r2[i] * r2[j]
            e = abs(s - 1.0) if i == j else abs(s)
            if e > err:
                err = e
    return err


def _det3(m: list[list[float]]) -> float:
    return (
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    )


def quaternion_xyzw_to_matrix(q: list[float] | np.ndarray) -> np.ndarray:
    """Rotation matrix [3, 3] of the quaternion ``q`` = (x, y, z, w) (normalised first);
    ValueError for a zero or non-finite quaternion."""
    x, y, z, w = (float(v) for v in q)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not math.isfinite(n) or n < 1e-12:
        raise ValueError(f"quaternion {[x, y, z, w]} has zero or non-finite norm")
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quaternion_xyzw(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w >= 0, of a rotation matrix ``r`` [3, 3]."""
    r = np.asarray(r, dtype=np.float64)
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        q = [0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif r[1, 1] > r[2, 2]:
        s = math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        q = [(r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s]
    out = np.asarray(q)
    out /= np.linalg.norm(out)
    return -out if out[3] < 0 else out


class Pose(BaseModel):
    """A camera-to-world pose (OpenCV axes): ``matrix`` (4x4 row-major) **or**
    ``position`` + ``orientation_xyzw`` (unit quaternion, ROS order x, y, z, w).

    The rotation must be orthonormal within ``max |R^T R - I| <= 1e-3`` with ``det R > 0``
    and the last row ``[0, 0, 0, 1]``; a quaternion's norm must be within 1e-3 of 1.
    Poses the server sends back always use ``matrix``.
    """

    model_config = ConfigDict(
        extra="forbid", strict=True,
        json_schema_extra=one_of(
            [Form("PoseMatrix", ("matrix",), ("position", "orientation_xyzw")),
             Form("PosePositionQuaternion", ("position", "orientation_xyzw"), ("matrix",))],
            rules=("rotation", "unit-quaternion")),
    )

    matrix: Matrix4 | None = Field(
        default=None, description="4x4 row-major camera-to-world matrix (OpenCV axes)"
    )
    position: Vec3 | None = Field(default=None, description="camera centre in world [x, y, z]")
    orientation_xyzw: Quaternion | None = Field(
        default=None, description="camera-to-world rotation, unit quaternion (x, y, z, w): "
        "its norm within 1e-3 of 1"
    )

    @field_validator("matrix")
    @classmethod
    def _check_matrix(cls, m: list[list[float]] | None) -> list[list[float]] | None:
        if m is None:
            return m
        last = m[3]
        if (
            abs(last[0]) > LAST_ROW_ATOL
            or abs(last[1]) > LAST_ROW_ATOL
            or abs(last[2]) > LAST_ROW_ATOL
            or abs(last[3] - 1.0) > LAST_ROW_ATOL
        ):
            raise ValueError(f"last row must be [0, 0, 0, 1], got {last}")
        if max(abs(m[0][3]), abs(m[1][3]), abs(m[2][3])) > MAX_COORD:
            raise ValueError(f"translation must lie within +-{MAX_COORD:g}")
        err = rotation_error(m)
        if err > ORTHONORMAL_ATOL:
            raise ValueError(
                f"rotation is not orthonormal: max |R^T R - I| = {err:.3g} > {ORTHONORMAL_ATOL}"
            )
        if _det3(m) <= 0:
            raise ValueError("rotation has det <= 0 (a reflection, not a rotation)")
        return m

    @field_validator("orientation_xyzw")
    @classmethod
    def _check_quaternion(cls, q: list[float] | None) -> list[float] | None:
        if q is None:
            return q
        n = math.sqrt(sum(v * v for v in q))
        if abs(n - 1.0) > QUATERNION_NORM_ATOL:
            raise ValueError(
                f"quaternion must have unit norm (|q| = {n:.6g}, tolerance "
                f"{QUATERNION_NORM_ATOL})"
            )
        return q

    @model_validator(mode="after")
    def _one_form(self) -> Pose:
        has_m = self.matrix is not None
        has_p = self.position is not None
        has_q = self.orientation_xyzw is not None
        if has_m and (has_p or has_q):
            raise ValueError("give either matrix or position + orientation_xyzw, not both")
        if not has_m and not (has_p and has_q):
            raise ValueError("give matrix, or both position and orientation_xyzw")
        return self

    def to_matrix(self) -> np.ndarray:
        """The 4x4 camera-to-world matrix as float64."""
        if self.matrix is not None:
            return np.asarray(self.matrix, dtype=np.float64)
        assert self.position is not None and self.orientation_xyzw is not None
        out = np.eye(4)
        out[:3, :3] = quaternion_xyzw_to_matrix(self.orientation_xyzw)
        out[:3, 3] = self.position
        return out

    def to_position_quaternion(self) -> tuple[np.ndarray, np.ndarray]:
        """``(position [3], orientation_xyzw [4])`` of this pose."""
        m = self.to_matrix()
        return m[:3, 3].copy(), matrix_to_quaternion_xyzw(m[:3, :3])

    @classmethod
    def from_matrix(cls, matrix: np.ndarray | list[list[float]], validate: bool = True) -> Pose:
        """A pose from a 4x4 camera-to-world matrix (validated unless ``validate=False``)."""
        rows = np.asarray(matrix, dtype=np.float64).tolist()
        if validate:
            return cls(matrix=rows)
        return cls.model_construct(matrix=rows, position=None, orientation_xyzw=None)

    @classmethod
    def from_position_quaternion(cls, position: list[float], orientation_xyzw: list[float]) -> Pose:
        """A pose from a position and a unit quaternion in ROS order (x, y, z, w)."""
        return cls(
            position=[float(v) for v in position],
            orientation_xyzw=[float(v) for v in orientation_xyzw],
        )


class Intrinsics(BaseModel):
    """Pinhole intrinsics in pixels (OpenCV): focal lengths, principal point, image size
    (width x height at most the server's ``max_image_pixels``)."""

    model_config = ConfigDict(extra="forbid", strict=True,
                              json_schema_extra={"x-agilegs-rules": ["pixels"]})

    fx: float = Field(ge=1e-3, le=1e7, allow_inf_nan=False, description="focal length x (px)")
    fy: float = Field(ge=1e-3, le=1e7, allow_inf_nan=False, description="focal length y (px)")
    cx: float = Field(ge=-1e7, le=1e7, allow_inf_nan=False, description="principal point x (px)")
    cy: float = Field(ge=-1e7, le=1e7, allow_inf_nan=False, description="principal point y (px)")
    width: WireInt = Field(ge=1, le=16384, description="image width (px)")
    height: WireInt = Field(ge=1, le=16384, description="image height (px)")

    @classmethod
    def from_fov(cls, fov_x_deg: float, width: int, height: int) -> Intrinsics:
        """Square pixels, principal point at the image centre, horizontal field of view."""
        fx = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
        return cls(fx=fx, fy=fx, cx=width / 2, cy=height / 2, width=width, height=height)


class Bounds(BaseModel):
    """An axis-aligned box in world coordinates: ``min`` < ``max`` on every axis."""

    model_config = ConfigDict(extra="forbid", populate_by_name=True, strict=True,
                              json_schema_extra={"x-agilegs-rules": ["ordered-bounds"]})

    min: Vec3 = Field(description="lower corner [x, y, z]")
    max: Vec3 = Field(description="upper corner [x, y, z]")

    @model_validator(mode="after")
    def _ordered(self) -> Bounds:
        for axis, (lo, hi) in enumerate(zip(self.min, self.max, strict=True)):
            if not lo < hi:
                raise ValueError(f"min must be below max on every axis (axis {axis}: {lo} >= {hi})")
        return self


# ---------------------------------------------------------------------------- pose lists
_POSE_KEYS = frozenset(("matrix", "position", "orientation_xyzw"))
_NUMBER_TYPES = frozenset((float, int))
_FAST_ATOL = ORTHONORMAL_ATOL * (1 - 1e-6)  # near the tolerance the per-pose check decides


def check_matrices(m: np.ndarray) -> np.ndarray:
    """Which of the camera-to-world matrices ``m`` [D, 4, 4] (float64, finite) meet every rule
    of :attr:`Pose.matrix`, in one vectorised pass: bool [D].

    Matches the per-pose validation except within 1e-9 of the orthonormality tolerance,
    where it says False (the caller then validates those poses one by one).
    """
    last = m[:, 3, :]
    ok = (np.abs(last[:, :3]) <= LAST_ROW_ATOL).all(axis=1)
    ok &= np.abs(last[:, 3] - 1.0) <= LAST_ROW_ATOL
    ok &= (np.abs(m[:, :3, 3]) <= MAX_COORD).all(axis=1)
    r = m[:, :3, :3]
    gram = np.einsum("dki,dkj->dij", r, r) - np.eye(3)
    ok &= np.abs(gram).max(axis=(1, 2), initial=0.0) <= _FAST_ATOL
    det = (r[:, 0, 0] * (r[:, 1, 1] * r[:, 2, 2] - r[:, 1, 2] * r[:, 2, 1])
           - r[:, 0, 1] * (r[:, 1, 0] * r[:, 2, 2] - r[:, 1, 2] * r[:, 2, 0])
           + r[:, 0, 2] * (r[:, 1, 0] * r[:, 2, 1] - r[:, 1, 1] * r[:, 2, 0]))
    ok &= det > 0
    return ok


class PoseArrayList(list[Pose]):
    """A list of matrix-form poses validated as one array; ``matrices`` [D, 4, 4] (float64)
    holds them."""

    matrices: np.ndarray


def _matrix_only(value: list[Any]) -> bool:
    """Whether every item of ``value`` is a wire pose in the matrix form only."""
    keys = _POSE_KEYS
    return all(type(p) is dict and p.keys() <= keys and p.get("matrix") is not None
               and p.get("position") is None and p.get("orientation_xyzw") is None
               for p in value)


def _trusted_pose(matrix: list[list[float]], fields_set: set[str]) -> Pose:
    """A :class:`Pose` of an already validated matrix, built without validating it again."""
    pose = _new_pose(Pose)
    _set(pose, "__dict__", {"matrix": matrix, "position": None, "orientation_xyzw": None})
    _set(pose, "__pydantic_fields_set__", fields_set)
    _set(pose, "__pydantic_extra__", None)
    _set(pose, "__pydantic_private__", None)
    return pose


_new_pose = Pose.__new__
_set = object.__setattr__


def trusted_poses(matrices: np.ndarray) -> PoseArrayList:
    """Poses of camera-to-world matrices [D, 4, 4] taken as they are, without validation
    (poses the server made, or a client's, which the server validates on arrival)."""
    a = np.asarray(matrices, dtype=np.float64)
    out = PoseArrayList(_trusted_pose(m, {"matrix"}) for m in a.tolist())
    out.matrices = a
    return out


def _as_matrices(value: list[Any]) -> tuple[np.ndarray, bool] | None:
    """The poses ``value`` (wire data, all in the matrix form) as one float64 array [D, 4, 4]
    and whether an entry is an int, or None unless every entry is a number (not a bool) and
    every matrix passes :func:`check_matrices`."""
    mats = [p["matrix"] for p in value]
    if not all(type(m) is list and len(m) == 4 for m in mats):
        return None
    rows = [r for m in mats for r in m]
    if not all(type(r) is list and len(r) == 4 for r in rows):
        return None
    flat = list(itertools.chain.from_iterable(rows))
    types = set(map(type, flat))
    if not types <= _NUMBER_TYPES:
        return None
    try:
        a = np.array(flat, dtype=np.float64).reshape(len(value), 4, 4)
    except OverflowError:  # an int beyond float64
        return None
    if not np.isfinite(a).all() or not check_matrices(a).all():
        return None
    return a, int in types


def _validate_poses(value: Any, handler: ValidatorFunctionWrapHandler) -> list[Pose]:
    """A list of poses: wire data in the matrix form is checked as one array (types, shapes,
    finiteness and every rule in :func:`check_matrices`); anything else, or a list in which
    any pose fails, goes through :class:`Pose` one by one, which names the field of every
    error (``poses[3].matrix``)."""
    if type(value) is list and value and _matrix_only(value):
        checked = _as_matrices(value)
        if checked is not None:
            a, has_ints = checked
            rows = a.tolist() if has_ints else [p["matrix"] for p in value]  # floats, as Pose
            out = PoseArrayList(_trusted_pose(m, set(p)) for p, m in zip(value, rows,
                                                                          strict=True))
            out.matrices = a
            return out
    return handler(value)  # type: ignore[no-any-return]


def _dump_poses(value: list[Pose], handler: SerializerFunctionWrapHandler) -> Any:
    """A list validated as one array is written from its array (as each pose would be)."""
    if isinstance(value, PoseArrayList):
        return [{"matrix": p.matrix, "position": None, "orientation_xyzw": None} for p in value]
    return handler(value)


PoseList = Annotated[list[Pose], WrapValidator(_validate_poses), WrapSerializer(_dump_poses)]
"""Poses validated as an array (see :func:`_validate_poses`): the same rules and error paths
as a ``list[Pose]``."""
