"""The accumulated information Ĥ on the wire: how a session keeps it, and reading it back."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .arrays import NDArray

__all__ = [
    "FieldSummary",
    "InformationConfig",
    "InformationOut",
    "InformationSummary",
]


class InformationConfig(BaseModel):
    """How the accumulated information Ĥ = λI + Σ_views H_v is kept.

    Ĥ is accumulated at the session's intrinsics (each acquired view's pose with the
    session camera), so it is on the scale of the H_v the selectors compute.
    """

    model_config = ConfigDict(extra="forbid", populate_by_name=True, serialize_by_alias=True,
                              strict=True)

    lambda_: float = Field(
        default=1e-3,
        alias="lambda",
        gt=0,
        le=1e12,
        allow_inf_nan=False,
        description="ridge λ added to every diagonal entry of Ĥ",
    )
    recompute_on_map_change: bool = Field(
        default=True,
        description=(
            "when the Gaussians are replaced, recompute Ĥ from every acquired view on the new "
            "map (always done when the Gaussian count changes)"
        ),
    )
    mapper_update: Literal["carry", "recompute"] = Field(
        default="carry",
        description=(
            "when the service's mapper publishes a trained map: 'carry' Ĥ over per Gaussian "
            "(kept Gaussians keep their row, clones and split children copy their source's, "
            "new Gaussians start at λ), or 'recompute' it from every acquired view on the new "
            "map (one Fisher pass per view per publication)"
        ),
    )

class FieldSummary(BaseModel):
    """One block of Ĥ in brief (None where a value is not finite, or the block is empty)."""

    shape: list[int]
    sum: float | None
    min: float | None
    max: float | None

class InformationSummary(BaseModel):
    """Ĥ in brief: per-field shape and sums, and a digest of all its bytes."""

    fields: dict[str, FieldSummary]
    digest: str = Field(description="sha256 over every field's float32 little-endian bytes")

class InformationOut(BaseModel):
    """Ĥ per parameter block (float32), with its summary."""

    fields: dict[str, NDArray]
    summary: InformationSummary
    version: int

    def arrays(self) -> dict[str, np.ndarray]:
        """Ĥ per parameter block as numpy arrays."""
        return {k: v.to_numpy() for k, v in self.fields.items()}
