"""The select operation: the session's settings merged with the request's, the maths' choice,
and, when asked, the chosen view acquired in the same atomic step."""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from pydantic import ValidationError

from agilegs.schemas import models as m
from agilegs.schemas.config import SelectConfig, deep_merge, patch_dict, validate_config
from agilegs.schemas.errors import ErrorCode

from ..errors import conflict, invalid, too_large, validation_error
from ..nbv.errors import InputError
from ..nbv.selectors import select
from ..store import SessionRecord, ViewRecord
from .convert import finite_float, pose_out, poses_array, storable_state, view_out

if TYPE_CHECKING:
    from .session import Session

__all__ = ["RENDER_WIDTHS", "TOP_LEVEL", "check_render_widths", "resolve_config", "run_select",
           "same_pool"]

TOP_LEVEL = ("shortlist_size", "shortlist", "embodied_k", "seed", "fields")
"""SelectConfig fields a select request carries at its top level."""

#: where an argument the maths refuses comes from, in the request or the session's state
_ARGUMENT_FIELDS = {
    "candidates": "pool",
    "current_pose": "body.current_pose",
    "current": "body.current_id",
    "h_acc": "information",
    "gmap": "gaussians",
    "acquired": "views",
}


RENDER_WIDTHS = (("anchor", "resolution"), ("cover_resolution",))
"""Paths of the SelectConfig fields that set a render's width; its square must stay within the
server's ``max_image_pixels``."""


def check_render_widths(patch: dict[str, Any], field: str, max_pixels: int) -> None:
    """422 naming the field if a render width in the SelectConfig patch ``patch`` (plain data)
    squared exceeds ``max_pixels``."""
    for path in RENDER_WIDTHS:
        value: Any = patch
        for key in path:
            value = value.get(key) if isinstance(value, dict) else None
        if isinstance(value, int) and value * value > max_pixels:
            raise too_large(".".join((field, *path)), f"{value} x {value} pixels exceed "
                            f"max_image_pixels ({max_pixels})")


def same_pool(rec: SessionRecord, pool: m.PoolIn) -> bool:
    """Whether ``pool`` is the session's pool as it is: the same poses in the same order, and
    the same ids or none (a robot that sends its candidates with every selection)."""
    if len(pool.poses) != len(rec.pool_ids):
        return False
    if pool.ids is not None and not np.array_equal(np.asarray(pool.ids), rec.pool_ids):
        return False
    return bool(np.array_equal(poses_array(pool.poses), rec.pool_poses))


def resolve_config(defaults: dict[str, Any], req: m.SelectRequest, top: dict[str, Any]
                   ) -> SelectConfig:
    """The session's config patch, the request's over it, then the top-level fields:
    validated once; a 422 names the request field."""
    merged = deep_merge(deep_merge(defaults.get("config") or {}, patch_dict(req.config)), top)
    try:
        return validate_config(SelectConfig, merged)
    except ValidationError as exc:
        raise validation_error(exc, "body.config",
                               rename={k: f"body.{k}" for k in TOP_LEVEL}) from None


def run_select(s: Session, req: m.SelectRequest) -> m.SelectResponse:
    """Choose the next view; with ``req.pool`` and / or ``req.commit``, the new pool and the
    acquired view are persisted together, after the selection succeeded."""
    with s.lock:
        s.check_open()
        t_core = time.perf_counter()
        rec = s.record
        dirty: list[str] = []
        if req.pool is not None and not same_pool(rec, req.pool):
            rec = s.pool_changed(rec, req.pool, "body.pool", replace_pool=True)
            dirty.append("pool")
        d = rec.defaults
        method = req.method or d["method"]
        size = req.shortlist_size or d["shortlist_size"]
        embodied_k = req.embodied_k if req.embodied_k is not None else d["embodied_k"]
        fields = req.fields if req.fields is not None else d["fields"]
        if size > s.settings.max_shortlist:
            raise invalid("body.shortlist_size",
                          f"must be <= {s.settings.max_shortlist} (max_shortlist)")
        if len(rec.pool_ids) == 0:
            raise conflict("pool", "the candidate pool is empty: set it first",
                           ErrorCode.EMPTY_POOL)
        if len(rec.gmap) == 0:
            raise conflict("gaussians", "the session has no Gaussians yet", ErrorCode.MAP_EMPTY)
        check_render_widths(patch_dict(req.config), "body.config", s.settings.max_image_pixels)
        config = resolve_config(d, req, {
            "shortlist_size": size,
            "shortlist": req.shortlist or d["shortlist"],
            "embodied_k": embodied_k,
            "seed": req.seed if req.seed is not None else d["seed"],
            "fields": tuple(fields) if fields else None,
        })
        dt = rec.gmap.dtype
        current = None
        current_pose = None
        if req.current_id is not None:
            current = s.pool_index(rec, req.current_id, "body.current_id")
        elif req.current_pose is not None:
            current_pose = torch.from_numpy(req.current_pose.to_matrix()).to(dt)
        elif embodied_k is not None:
            if not rec.views:
                raise conflict("body.embodied_k", "embodied mode needs the current view: "
                               "give current_id or current_pose, or acquire a view first")
            current_pose = torch.from_numpy(rec.views[-1].pose).to(dt)
        acquired = (torch.from_numpy(np.stack([v.pose for v in rec.views])).to(dt)
                    if rec.views else None)
        try:
            sel = select(
                method, rec.gmap, rec.h_acc, torch.from_numpy(rec.pool_poses).to(dt),
                s.intrinsics(rec), config=config, acquired=acquired, current=current,
                current_pose=current_pose, state=rec.warm_state,
                lam=float(rec.information_config["lambda"]),
            )
        except InputError as exc:
            raise invalid(_ARGUMENT_FIELDS.get(exc.argument, "body"), str(exc)) from None
        ids = rec.pool_ids
        chosen = int(sel.index)
        chosen_id = int(ids[chosen])
        chosen_pose = rec.pool_poses[chosen]
        committed = None
        if req.commit:
            s.check_view_room(rec, 1, "body.commit")
            view = ViewRecord(id=rec.next_view_id, pose=chosen_pose, candidate_id=chosen_id,
                              created_at=time.time())
            h = s.accumulate(rec.h_acc, rec.gmap, [chosen_pose], rec)
            rec = s.bump(rec, views=rec.views + (view,), next_view_id=view.id + 1,
                         h_acc=h, warm_state=storable_state(sel.state),
                         **s.without(rec, chosen))
            dirty += ["information", "pool", "warm"]
            committed = view_out(view)
        if dirty:
            rec = s.commit_record(rec, dirty)
        scores = sel.scores
        return m.SelectResponse.model_construct(
            session=rec.id,
            method=sel.method,
            chosen=m.Candidate.model_construct(id=chosen_id, pose=pose_out(chosen_pose)),
            shortlist=[
                m.ScoredCandidate.model_construct(
                    id=int(ids[i]), score=finite_float(scores[i]) if i in scores else None)
                for i in sel.shortlist
            ],
            anchor=pose_out(sel.anchor_c2w) if sel.anchor_c2w is not None else None,
            scores=[m.ScoredCandidate.model_construct(id=int(ids[i]), score=finite_float(v))
                    for i, v in scores.items()],
            eligible=ids[np.asarray(sel.eligible, dtype=np.int64)].tolist(),
            psi_trace=[float(x) for x in sel.psi_trace if math.isfinite(x)],
            latency_ms={k: float(v) for k, v in sel.latency_ms.items()},
            core_ms=(time.perf_counter() - t_core) * 1e3,
            server_ms=None,
            committed=committed,
            version=rec.version,
            time=time.time(),
        )
