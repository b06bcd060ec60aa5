"""The select operation as a function of the session's record: the session's settings merged
with the request's (validated once, here), its cost estimated up front and refused beyond
``max_select_seconds`` / ``max_select_bytes`` (:func:`check_cost`), the maths' choice, and,
when asked, the chosen view acquired (:func:`~agilegs.service.sessions.transitions.acquire`)
in the same step; without commit, the selection is handed back as a
:class:`~agilegs.service.sessions.transitions.PendingSelection` for the next acquisition."""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from pydantic import ValidationError
from torch import Tensor

from agilegs import schemas as m
from agilegs.config.selection import SelectConfig, objective_of
from agilegs.config.types import deep_merge, validate_config
from agilegs.schemas.config import patch_dict
from agilegs.schemas.errors import ErrorCode

from ..errors import ServiceError, conflict, invalid, too_large, validation_error
from ..nbv import Selection
from ..nbv.budget import KINDS, Estimate, SpeedCalibration, estimate
from ..nbv.errors import InputError
from ..nbv.kernels.backend import default_backend, kernels_available
from ..nbv.methods.base import get_method
from ..nbv.selectors import SelectInputs, select_from, state_to
from ..nbv.targets import target_size
from ..store.records import SessionRecord, ViewRecord
from .convert import finite_float, pose_out, poses_array, view_out
from .transitions import (
    Limits,
    PendingSelection,
    acquire,
    background_setting,
    check_view_room,
    intrinsics_of,
    pool_index,
    with_pool,
)

__all__ = ["RENDER_WIDTHS", "SPEED", "TOP_LEVEL", "Selected", "check_cost", "check_render_widths",
           "resolve_config", "select_estimate", "select_response", "select_step"]

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


SPEED = SpeedCalibration()
"""This process's speed against the reference CPU, learnt from the selections it timed: a
select's time estimate is bounded by ``SPEED.bound`` before it is compared with
``max_select_seconds``."""

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


def select_estimate(rec: SessionRecord, method: str, config: SelectConfig) -> Estimate:
    """The up-front estimate (:func:`agilegs.service.nbv.budget.estimate`) of a select of
    ``method`` on ``rec``: its Gaussians, its pool (the ``embodied_k`` nearest in embodied
    mode), its views, the session's image size (COVER: ``cover_resolution``); with the
    ``target`` objective, plus ``target_views`` Fisher passes at ``target_scale``."""
    g = rec.gmap
    intr = rec.intrinsics
    w, h = int(intr["width"]), int(intr["height"])
    if method == "cover" and config.cover_resolution is not None:
        w, h = config.cover_resolution, max(1, round(config.cover_resolution * h / w))
    pool = len(rec.pool_ids)
    if config.embodied_k is not None:
        pool = min(pool, config.embodied_k)
    kernels = default_backend() in ("auto", "numba") and kernels_available()
    sizes: dict[str, Any] = dict(
        sh_coeffs=int(g.sh.shape[1]), dtype_bytes=g.means.element_size(),
        backend="numba" if kernels else "torch", threads=torch.get_num_threads())
    est = estimate(method, len(g), w * h, pool=pool,  # type: ignore[arg-type]
                   shortlist=config.shortlist_size, acquired=len(rec.views), **sizes)
    if objective_of(method, config) == "target" and method in ("full_eig", "agile_plus"):
        # the targets' Fisher T: one pass per target view, once per selection
        tw, th = target_size(w, h, config.target_scale)
        one = estimate("fisher", len(g), tw * th, **sizes)
        est = dataclasses.replace(est, seconds=est.seconds + config.target_views * one.seconds)
    return est


def check_cost(rec: SessionRecord, method: str, config: SelectConfig, limits: Limits,
               speed: SpeedCalibration | None = None) -> Estimate | None:
    """422 ``limit_exceeded`` naming ``max_select_seconds`` or ``max_select_bytes``, with the
    estimate, when the select's up-front bound exceeds it: the time estimate as ``speed``
    (default :data:`SPEED`) bounds it on this machine, the memory estimate with its margin.
    Returns the estimate."""
    if method not in KINDS:
        return None
    est = select_estimate(rec, method, config)
    seconds = (speed or SPEED).bound(est.seconds)
    over = None
    if seconds > limits.max_select_seconds:
        over = ("max_select_seconds", f"{seconds:.3g} s", f"{limits.max_select_seconds:g} s")
    elif est.peak_bytes > limits.max_select_bytes:
        over = ("max_select_bytes", f"{est.peak_bytes / 2**20:.0f} MiB",
                f"{limits.max_select_bytes / 2**20:.0f} MiB")
    if over is None:
        return est
    name, got, limit = over
    intr = rec.intrinsics
    raise ServiceError(
        422, ErrorCode.LIMIT_EXCEEDED,
        f"a {method} select over {len(rec.pool_ids)} candidates of {len(rec.gmap)} Gaussians "
        f"at {intr['width']}x{intr['height']} is estimated at {got} ({seconds:.3g} s, "
        f"{est.peak_bytes / 2**20:.0f} MiB peak), over {name} ({limit}): use a cheaper method, "
        "a smaller pool or embodied_k, or a smaller map", "body.method", limit=name,
        estimate={"peak_bytes": float(est.peak_bytes), "seconds": float(seconds)})


@dataclass(frozen=True)
class Selected:
    """What a select step leaves.

    Attributes:
        record: the record after it (the one given when nothing changed).
        selection: the maths' :class:`~agilegs.service.nbv.selectors.Selection`.
        chosen_id: the chosen candidate's id.
        chosen_pose: its pose [4, 4].
        ids: the pool's ids the selection's indices refer to.
        committed: the acquired view (with commit), else None.
        pending: the selection for the next acquisition (without commit), else None.
    """

    record: SessionRecord
    selection: Selection
    chosen_id: int
    chosen_pose: np.ndarray
    ids: np.ndarray
    committed: ViewRecord | None
    pending: PendingSelection | None


def _reusable(rec: SessionRecord, config: SelectConfig, sel: Selection
              ) -> dict[str, Tensor] | None:
    """The selection's Fisher of the chosen view if it is what Hhat adds for that view (every
    block, the session's background), else None."""
    info = sel.chosen_information
    if info is None or set(info) != set(rec.h_acc):
        return None
    bg = config.fisher_background
    return info if (None if bg is None else tuple(float(c) for c in bg)) == background_setting(
        rec) else None


def select_step(rec: SessionRecord, req: m.SelectRequest, limits: Limits, *,
                now: float | None = None) -> Selected:
    """Choose the next view; with ``req.pool`` the pool is replaced first (unless it is the
    session's as it is), with ``req.commit`` the chosen candidate is acquired."""
    if req.pool is not None:
        rec = with_pool(rec, poses_array(req.pool.poses), req.pool.ids, limits, "body.pool")
    d = rec.defaults
    method = req.method or d["method"]
    size = req.shortlist_size or d["shortlist_size"]
    embodied_k = req.embodied_k if req.embodied_k is not None else d["embodied_k"]
    fields = req.fields if req.fields is not None else d["fields"]
    if size > limits.max_shortlist:
        raise invalid("body.shortlist_size",
                      f"must be <= {limits.max_shortlist} (max_shortlist)")
    if len(rec.pool_ids) == 0:
        raise conflict("pool", "the candidate pool is empty: set it first", ErrorCode.EMPTY_POOL)
    if len(rec.gmap) == 0 and getattr(get_method(method), "uses_map", True):
        raise conflict("gaussians", f"the session has no Gaussians yet ({method} needs a map; "
                       "spread does not)", ErrorCode.MAP_EMPTY)
    check_render_widths(patch_dict(req.config), "body.config", limits.max_image_pixels)
    config = resolve_config(d, req, {
        "shortlist_size": size,
        "shortlist": req.shortlist or d["shortlist"],
        "embodied_k": embodied_k,
        "seed": req.seed if req.seed is not None else d["seed"],
        "fields": tuple(fields) if fields else None,
    })
    est = check_cost(rec, method, config, limits)
    dt = rec.gmap.dtype
    targets = None
    if req.targets is not None:
        objective = objective_of(method, config)
        if objective != "target":
            raise invalid("body.targets", "targets are the views of interest of "
                          "config.objective 'target'; this select's objective is "
                          f"{objective!r}")
        targets = torch.from_numpy(poses_array(req.targets)).to(dt)
    current = None
    current_pose = None
    if req.current_id is not None:
        current = pool_index(rec, req.current_id, "body.current_id")
    elif req.current_pose is not None:
        current_pose = torch.from_numpy(req.current_pose.to_matrix()).to(dt)
    elif embodied_k is not None:
        if not rec.views:
            raise conflict("body.embodied_k", "embodied mode needs the current view: "
                           "give current_id or current_pose, or acquire a view first")
        current_pose = torch.from_numpy(rec.views[-1].pose).to(dt)
    acquired = (torch.from_numpy(np.stack([v.pose for v in rec.views])).to(dt)
                if rec.views else None)
    t0 = time.perf_counter()
    dev = torch.device(limits.device)
    gmap, h_acc = rec.gmap, rec.h_acc  # on the CPU, the record's own objects
    if dev.type != "cpu":
        gmap, h_acc = gmap.to(device=dev), state_to(dev, h_acc)
    try:
        inputs = SelectInputs(
            method, gmap, h_acc,
            torch.from_numpy(rec.pool_poses).to(device=dev, dtype=dt),
            intrinsics_of(rec), config=config,
            acquired=None if acquired is None else acquired.to(dev), current=current,
            current_pose=None if current_pose is None else current_pose.to(dev),
            lam=float(rec.information_config["lambda"]),
            targets=None if targets is None else targets.to(dev),
        )
        sel = select_from(inputs, state=state_to(dev, rec.warm_state))
    except InputError as exc:
        raise invalid(_ARGUMENT_FIELDS.get(exc.argument, "body"), str(exc)) from None
    if dev.type != "cpu":  # the record keeps host tensors
        sel = dataclasses.replace(sel, state=state_to("cpu", sel.state),
                                  chosen_information=state_to("cpu", sel.chosen_information))
    if est is not None:
        SPEED.observe(est.seconds, time.perf_counter() - t0)
    ids = rec.pool_ids
    chosen_id = int(ids[sel.index])
    chosen_pose = rec.pool_poses[sel.index]
    information = _reusable(rec, config, sel)
    if not req.commit:
        pending = PendingSelection(next_state=sel.state, candidate_id=chosen_id,
                                   pose=chosen_pose, gmap=rec.gmap, information=information)
        return Selected(rec, sel, chosen_id, chosen_pose, ids, None, pending)
    check_view_room(rec, 1, "body.commit", limits)
    rec, view = acquire(rec, chosen_pose, candidate_id=chosen_id, h_view=information,
                        next_state=sel.state, now=now)
    return Selected(rec, sel, chosen_id, chosen_pose, ids, view, None)


def select_response(rec: SessionRecord, out: Selected, t_core: float) -> m.SelectResponse:
    """The decision of a select step (``rec``: the record as persisted); ``core_ms`` runs from
    ``t_core`` (``time.perf_counter()``) to now."""
    sel, ids = out.selection, out.ids
    scores = sel.scores
    return m.SelectResponse.model_construct(
        session=rec.id,
        method=sel.method,
        chosen=m.Candidate.model_construct(id=out.chosen_id, pose=pose_out(out.chosen_pose)),
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
        committed=view_out(out.committed) if out.committed is not None else None,
        version=rec.version,
        time=time.time(),
    )
