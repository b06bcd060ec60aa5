"""The candidate pool on the wire: poses with stable ids."""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from .fields import MAX_POOL_WIRE, UNIQUE, Id, unique
from .forms import RULES_KEY
from .geometry import Pose, PoseList, trusted_poses

__all__ = [
    "Candidate",
    "PoolIn",
    "PoolOut",
]


class PoolIn(BaseModel):
    """Candidate poses (camera-to-world), optionally with client-chosen ``ids``; without
    ids the server numbers them on from the session's counter. The poses are validated as
    one array (:data:`~agilegs.schemas.geometry.PoseList`)."""

    model_config = ConfigDict(extra="forbid", strict=True,
                              json_schema_extra={RULES_KEY: ["same-length"]})

    poses: PoseList = Field(max_length=MAX_POOL_WIRE)
    ids: list[Id] | None = Field(default=None, description="one id per pose, unique",
                                 json_schema_extra=UNIQUE)

    @model_validator(mode="after")
    def _ids(self) -> PoolIn:
        if self.ids is not None:
            if len(self.ids) != len(self.poses):
                raise ValueError(f"ids has {len(self.ids)} entries for {len(self.poses)} poses")
            unique(self.ids, "ids")
        return self

    @classmethod
    def from_numpy(cls, poses: Any, ids: list[int] | None = None, validate: bool = True) -> PoolIn:
        """A pool from camera-to-world matrices [D, 4, 4]."""
        m = np.asarray(poses, dtype=np.float64)
        if m.ndim != 3 or m.shape[1:] != (4, 4):
            raise ValueError(f"poses must have shape [D, 4, 4], got {list(m.shape)}")
        if validate:  # checked as one array (PoseList)
            return cls.model_validate({"poses": [{"matrix": r} for r in m.tolist()], "ids": ids})
        return cls.model_construct(poses=trusted_poses(m), ids=ids)

class Candidate(BaseModel):
    id: int
    pose: Pose

class PoolOut(BaseModel):
    candidates: list[Candidate]
    version: int

    def ids(self) -> list[int]:
        return [c.id for c in self.candidates]

    def matrices(self) -> np.ndarray:
        """Candidate poses [D, 4, 4]."""
        if not self.candidates:
            return np.zeros((0, 4, 4))
        return np.stack([c.pose.to_matrix() for c in self.candidates])
