"""What a session's record says about its mapper: options, progress, steps owed.

Pure functions of a :class:`~agilegs.service.store.write.SessionRecord` (no training here; the
trainer in :mod:`agilegs.service.sessions.trainer` does that), shared by the sessions and the
trainer.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel

from agilegs import schemas as m
from agilegs.config.mapper import MapperConfig
from agilegs.config.types import validate_config
from agilegs.schemas.config import patch_dict

from ..store.records import SessionRecord

__all__ = [
    "image_views",
    "initial_mapper_state",
    "mapper_config",
    "mapper_options",
    "mapper_status",
    "steps_per_view",
]


def mapper_config(config: BaseModel | Mapping[str, Any], *, max_gaussians: int | None = None
                  ) -> MapperConfig:
    """The :class:`MapperConfig` of a session's ``MapperOptions.config`` (a patch), validated;
    ``max_gaussians`` (the server's cap) bounds the map the mapper may grow."""
    cfg = validate_config(MapperConfig, patch_dict(config))
    if max_gaussians is not None and (cfg.max_gaussians is None
                                      or cfg.max_gaussians > max_gaussians):
        cfg = dataclasses.replace(cfg, max_gaussians=int(max_gaussians))
    return cfg


def initial_mapper_state(options: m.MapperOptions) -> dict[str, Any]:
    """The ``SessionRecord.mapper`` of a new session: its options and no progress."""
    return {"options": options.model_dump(mode="json"), "steps": 0, "last_loss": None}


def mapper_options(rec: SessionRecord) -> m.MapperOptions:
    state = rec.mapper or {}
    return m.MapperOptions.model_validate(state.get("options") or {})


def image_views(rec: SessionRecord) -> int:
    """Acquired views with an image (what the mapper trains on)."""
    return sum(1 for v in rec.views if v.image_file is not None)


def steps_per_view(options: m.MapperOptions, default: int) -> int:
    return int(options.steps_per_view if options.steps_per_view is not None else default)


def mapper_status(rec: SessionRecord, default_steps_per_view: int) -> m.MapperStatus:
    """The status of a session whose mapper does not run (server or session mapper off)."""
    state = rec.mapper or {}
    options = mapper_options(rec)
    steps = int(state.get("steps", 0))
    spv = steps_per_view(options, default_steps_per_view)
    views = image_views(rec)
    return m.MapperStatus(
        enabled=False, state="off", steps=steps, published_steps=steps,
        pending_steps=max(0, spv * views - steps), steps_per_view=spv, views=views,
        num_gaussians=len(rec.gmap), last_loss=state.get("last_loss"), error=None,
        options=options,
    )
