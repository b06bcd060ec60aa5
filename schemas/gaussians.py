"""The Gaussians of a session on the wire: uploaded (a file or arrays), read back, in brief."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from agilegs.config.selection import FIELD_NAMES

from .arrays import B64Bytes, NDArray
from .forms import RULES_KEY, Form, one_of

__all__ = [
    "GaussianArrays",
    "GaussiansIn",
    "GaussiansOut",
    "GaussiansSummary",
]


class GaussianArrays(BaseModel):
    """The five parameter tensors (float32 or float64): means [N,3], log_scales [N,3]
    (log standard deviations), quats [N,4] (w, x, y, z), opacity_logits [N] (pre-sigmoid),
    sh [N,(d+1)^2,3] (DC first, d <= 3)."""

    model_config = ConfigDict(extra="forbid", strict=True,
                              json_schema_extra={RULES_KEY: ["gaussian-arrays"]})

    means: NDArray
    log_scales: NDArray
    quats: NDArray
    opacity_logits: NDArray
    sh: NDArray

class GaussiansIn(BaseModel):
    """Gaussians as a file (``ply``: Inria 3DGS PLY; ``splat``: antimatter15 32-byte
    records) in ``data``, or as ``arrays``."""

    model_config = ConfigDict(extra="forbid", strict=True, json_schema_extra=one_of([
        Form("GaussiansFile", ("format", "data"), ("arrays",),
             {"format": {"type": "string", "enum": ["ply", "splat"]}}),
        Form("GaussiansArrays", ("format", "arrays"), ("data",),
             {"format": {"type": "string", "const": "arrays"}}),
    ], rules=("gaussians-file",)))

    format: Literal["ply", "splat", "arrays"]
    data: B64Bytes | None = Field(default=None, description="file bytes (ply / splat)")
    arrays: GaussianArrays | None = Field(default=None, description="tensors (arrays)")

    @model_validator(mode="after")
    def _consistent(self) -> GaussiansIn:
        if self.format == "arrays":
            if self.arrays is None or self.data is not None:
                raise ValueError("format 'arrays' takes arrays and no data")
        elif self.data is None or self.arrays is not None:
            raise ValueError(f"format {self.format!r} takes data (the file bytes) and no arrays")
        return self

class GaussiansOut(BaseModel):
    """A session's current (published) Gaussians as float32 arrays, with the session
    ``version`` they belong to and the mapper's training steps they hold."""

    arrays: GaussianArrays
    count: int
    sh_degree: int
    version: int
    mapper_steps: int = Field(description="training steps of the mapper this map holds")

    def to_numpy(self) -> dict[str, np.ndarray]:
        """The five parameter arrays (means, log_scales, quats, opacity_logits, sh)."""
        return {k: getattr(self.arrays, k).to_numpy() for k in FIELD_NAMES}

class GaussiansSummary(BaseModel):
    """The session's Gaussians in brief."""

    count: int
    sh_degree: int
    means_min: list[float] | None = Field(default=None, description="lower corner of the means")
    means_max: list[float] | None = Field(default=None, description="upper corner of the means")
