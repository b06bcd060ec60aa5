"""The service's mapper on the wire: a session's training options and the mapper's progress."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field

from .config import MapperConfigPatch
from .fields import STRICT, StepsPerView

__all__ = [
    "MapperOptions",
    "MapperState",
    "MapperStatus",
]


class MapperOptions(BaseModel):
    """How the service's mapper trains a session's Gaussians from the images sent to it.

    After each observation batch the mapper (one background worker per server) trains
    ``steps_per_view`` steps per new view with an image, on all the session's views with
    images, then idles; every burst of steps is published as the session's map (persisted,
    then visible). With ``enabled`` false (or the server's ``AGILEGS_MAPPER=0``) images are
    only stored.
    """

    model_config = STRICT

    enabled: bool = Field(default=True, description="train this session's map from its images")
    steps_per_view: StepsPerView | None = Field(
        default=None,
        description="training steps per view with an image (None: the server's "
                    "AGILEGS_MAPPER_STEPS_PER_VIEW)",
    )
    config: MapperConfigPatch = Field(
        default_factory=MapperConfigPatch,
        description="MapperConfig fields (3DGS training settings), e.g. {'background': "
        "[1, 1, 1], 'sh_degree': 0, 'densify_from': 50}",
    )

MapperState = Literal["off", "idle", "training", "error"]

class MapperStatus(BaseModel):
    """The mapper's progress on a session.

    ``state``: ``off`` (the server's or the session's mapper is disabled), ``training``
    (steps are pending, or trained steps are not yet published), ``idle`` (every step owed
    is trained and the map holding them is published), ``error`` (training failed; see
    ``error``; new observations retry). Steps owed = ``steps_per_view`` x views with an
    image; ``pending_steps`` = owed - ``steps``.
    """

    enabled: bool
    state: MapperState
    steps: int = Field(description="training steps done (the burst in progress included)")
    published_steps: int = Field(description="training steps held by the published map")
    pending_steps: int = Field(description="steps still owed to the views sent")
    steps_per_view: int
    views: int = Field(description="acquired views with an image (what the mapper trains on)")
    num_gaussians: int = Field(description="Gaussians in the mapper's current map")
    last_loss: float | None = Field(
        default=None, description="mean training loss (L1 + D-SSIM) of the last burst"
    )
    error: str | None = None
    options: MapperOptions
