"""Every change of a session's state, as a function from one :class:`SessionRecord` to the next.

Pure: nothing here locks, persists or reads a clock other than the ``now`` given (default:
the time of the call); a refused change raises a
:class:`~agilegs.service.errors.ServiceError` naming the field and returns nothing. The
:class:`~agilegs.service.sessions.session.Session` holds the lock, persists the record a
function returns and swaps it in; the benchmark's protocol runs the same functions on a record
of its own.

The state a change touches: the acquired views, the candidate pool, Hhat, the warm state of
the selector, and the counters (version, next view and candidate ids, the event counter in the
warm state). :func:`acquire` is the one way a view is acquired (a commit, a selection with
commit, an observation of a new view, the benchmark's events): it appends the view, takes its
candidate out of the pool, adds the view's Fisher to Hhat and, when a selection chose it,
moves the warm state on to that selection's. A selection made without commit leaves the record
as it was and hands back a :class:`PendingSelection`, which the next acquisition takes, so a
selection followed by a commit leaves the state a selection with commit leaves.
"""

from __future__ import annotations

import io
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..errors import conflict, too_large, too_many
from ..mapper.topology import remap_per_gaussian
from ..nbv import (
    GaussianMap,
    Intrinsics,
    accumulate_information,
    information_of_views,
    init_information,
    view_information,
)
from ..settings import Settings
from ..store.records import SessionRecord, ViewRecord
from .convert import Frame, nbv_intrinsics, storable_state

__all__ = [
    "KEEP",
    "Limits",
    "PendingSelection",
    "acquire",
    "background_of",
    "background_setting",
    "bump",
    "carry_information",
    "check_view_room",
    "commit_view",
    "integrate_frames",
    "intrinsics_of",
    "new_record",
    "pool_index",
    "recompute_information",
    "replace_map",
    "same_pool",
    "set_pool",
    "with_pool",
]

KEEP: Any = object()
"""``acquire(..., next_state=KEEP)``: the warm state stays as it is."""


@dataclass(frozen=True)
class Limits:
    """The server's limits a change is checked against (see :class:`Settings`)."""

    max_pool_size: int
    max_views: int
    max_gaussians: int
    max_shortlist: int
    max_image_pixels: int
    max_select_seconds: float = float("inf")
    max_select_bytes: int = 1 << 62
    device: str = "cpu"
    """Not a limit: where a selection computes (``Settings.device``)."""

    @classmethod
    def of(cls, settings: Settings) -> Limits:
        return cls(max_pool_size=settings.max_pool_size, max_views=settings.max_views,
                   max_gaussians=settings.max_gaussians, max_shortlist=settings.max_shortlist,
                   max_image_pixels=settings.max_image_pixels,
                   max_select_seconds=settings.max_select_seconds,
                   max_select_bytes=settings.max_select_bytes, device=settings.device)


@dataclass(frozen=True)
class PendingSelection:
    """A selection made without commit, for the next acquisition to take.

    Attributes:
        next_state: the warm state the selection leads to (storable).
        candidate_id: the chosen candidate.
        pose: its pose [4, 4] (float64, camera-to-world).
        gmap: the map the selection ran on.
        information: the chosen view's Fisher on ``gmap`` with the session's background and
            every block (None: the method did not compute it, or with other settings).
    """

    next_state: dict[str, Any] | None
    candidate_id: int
    pose: np.ndarray
    gmap: GaussianMap
    information: dict[str, Tensor] | None = None

    def information_for(self, rec: SessionRecord, pose: np.ndarray) -> dict[str, Tensor] | None:
        """The kept Fisher if it is the one of ``pose`` on ``rec``'s map, else None."""
        if self.information is None or rec.gmap is not self.gmap:
            return None
        return self.information if np.array_equal(pose, self.pose) else None


# ============================================================================ helpers
def new_record(sid: str, intrinsics: Mapping[str, Any], gmap: GaussianMap, *,
               defaults: Mapping[str, Any], information_config: Mapping[str, Any],
               bounds: Mapping[str, Any] | None = None, mapper: Mapping[str, Any] | None = None,
               now: float | None = None) -> SessionRecord:
    """A session's first record (version 1): ``gmap``, Hhat = lambda I, no views, no pool.

    Args:
        intrinsics: the session's camera (``fx, fy, cx, cy, width, height``).
        defaults: the selection defaults (``SelectDefaults`` as plain data; its ``config``
            patch's ``fisher_background`` is the background of every Fisher render).
        information_config: ``InformationConfig`` as plain data (``lambda``, ...).
        mapper: the mapper's options and progress.
    """
    t = time.time() if now is None else now
    return SessionRecord(
        id=sid, created_at=t, updated_at=t, version=1, intrinsics=dict(intrinsics),
        bounds=None if bounds is None else dict(bounds), defaults=dict(defaults),
        information_config=dict(information_config), gmap=gmap,
        h_acc=init_information(gmap, float(information_config["lambda"])),
        pool_ids=np.zeros(0, dtype=np.int64), pool_poses=np.zeros((0, 4, 4)),
        next_candidate_id=0, views=(), next_view_id=0,
        mapper=None if mapper is None else dict(mapper),
    )


def bump(rec: SessionRecord, now: float | None = None, **changes: Any) -> SessionRecord:
    """``rec`` with ``changes``, its version incremented and ``updated_at`` = ``now``."""
    return replace(rec, version=rec.version + 1,
                   updated_at=time.time() if now is None else now, **changes)


def pool_index(rec: SessionRecord, cid: int, field: str) -> int:
    """The position of candidate ``cid`` in the pool; 409 naming ``field`` if absent."""
    hits = np.nonzero(rec.pool_ids == cid)[0]
    if hits.size == 0:
        raise conflict(field, f"candidate {cid} is not in the pool")
    return int(hits[0])


def check_view_room(rec: SessionRecord, n: int, field: str, limits: Limits) -> None:
    """429 naming ``field`` if ``n`` more views would exceed ``max_views``."""
    if len(rec.views) + n > limits.max_views:
        raise too_many(field, f"the session would hold {len(rec.views) + n} views; "
                              f"max_views is {limits.max_views}")


def intrinsics_of(rec: SessionRecord) -> Intrinsics:
    """The session's camera (the candidates' and Hhat's)."""
    return nbv_intrinsics(rec.intrinsics)


def background_setting(rec: SessionRecord) -> tuple[float, ...] | None:
    """The session's ``fisher_background`` setting (its default select config's)."""
    bg = ((rec.defaults or {}).get("config") or {}).get("fisher_background")
    return None if bg is None else tuple(float(c) for c in bg)


def background_of(rec: SessionRecord, dtype: torch.dtype) -> Tensor | None:
    """The background [3] of the session's Fisher renders (None: black), so that Hhat and
    the selections agree."""
    bg = background_setting(rec)
    return None if bg is None else torch.tensor(list(bg), dtype=dtype)


def _view_information(rec: SessionRecord, gmap: GaussianMap, pose: np.ndarray
                      ) -> dict[str, Tensor]:
    return view_information(gmap, torch.from_numpy(pose).to(gmap.dtype), intrinsics_of(rec),
                            background_of(rec, gmap.dtype))


def recompute_information(rec: SessionRecord, gmap: GaussianMap) -> dict[str, Tensor]:
    """Hhat of ``rec``'s acquired views on ``gmap``: lambda I + their Fisher."""
    return information_of_views(
        gmap, (torch.from_numpy(v.pose).to(gmap.dtype) for v in rec.views), intrinsics_of(rec),
        float(rec.information_config["lambda"]), background_of(rec, gmap.dtype))


def carry_information(rec: SessionRecord, gmap: GaussianMap, src: Tensor) -> dict[str, Tensor]:
    """Hhat of ``rec`` carried to ``gmap`` along ``src`` (new Gaussians: lambda)."""
    h = remap_per_gaussian(rec.h_acc, src, 0.0)
    new = src.to(torch.long) < 0
    if bool(new.any()):
        prior = init_information(gmap, float(rec.information_config["lambda"]))
        for k in h:
            h[k][new] = prior[k][new].to(h[k].dtype)
    return h


# ============================================================================ the pool
def same_pool(rec: SessionRecord, poses: np.ndarray, ids: Sequence[int] | None) -> bool:
    """Whether ``poses`` [D, 4, 4] (and ``ids``, or none) are the session's pool as it is: the
    same poses in the same order (a robot that sends its candidates with every selection)."""
    if len(poses) != len(rec.pool_ids):
        return False
    if ids is not None and not np.array_equal(np.asarray(ids), rec.pool_ids):
        return False
    return bool(np.array_equal(poses, rec.pool_poses))


def set_pool(rec: SessionRecord, poses: np.ndarray, ids: Sequence[int] | None, limits: Limits,
             field: str, *, replace_pool: bool, now: float | None = None) -> SessionRecord:
    """The pool replaced by (``replace_pool``) or extended with the candidates ``poses``
    [D, 4, 4] (validated, float64) and their ``ids`` (None: numbered on from the counter)."""
    d = len(poses)
    base = 0 if replace_pool else len(rec.pool_ids)
    limit = limits.max_pool_size
    if d > limit:
        raise too_large(f"{field}.poses", f"{d} candidates exceed max_pool_size ({limit})")
    if base + d > limit:
        raise too_many(f"{field}.poses", f"the pool would hold {base + d} candidates; "
                                         f"max_pool_size is {limit}")
    if ids is not None:
        new_ids = np.asarray(ids, dtype=np.int64)
        if not replace_pool and len(rec.pool_ids):
            clash = np.nonzero(np.isin(new_ids, rec.pool_ids))[0]
            if clash.size:
                i = int(clash[0])
                raise conflict(f"{field}.ids[{i}]", f"candidate {int(new_ids[i])} is already "
                                                    "in the pool")
        next_id = max(rec.next_candidate_id, int(new_ids.max()) + 1 if d else 0)
    else:
        new_ids = np.arange(rec.next_candidate_id, rec.next_candidate_id + d, dtype=np.int64)
        next_id = rec.next_candidate_id + d
    if not replace_pool:
        new_ids = np.concatenate([rec.pool_ids, new_ids])
        poses = np.concatenate([rec.pool_poses, poses]) if d else rec.pool_poses
    return bump(rec, now, pool_ids=new_ids, pool_poses=poses, next_candidate_id=next_id)


def with_pool(rec: SessionRecord, poses: np.ndarray, ids: Sequence[int] | None, limits: Limits,
              field: str) -> SessionRecord:
    """``rec`` with its pool replaced by ``poses`` and ``ids``, or ``rec`` itself when they are
    its pool as it is (its ids and version unchanged)."""
    if same_pool(rec, poses, ids):
        return rec
    return set_pool(rec, poses, ids, limits, field, replace_pool=True)


def _without(rec: SessionRecord, index: int) -> dict[str, np.ndarray]:
    keep = np.ones(len(rec.pool_ids), dtype=bool)
    keep[index] = False
    return {"pool_ids": rec.pool_ids[keep], "pool_poses": rec.pool_poses[keep]}


# ============================================================================ acquisitions
def acquire(rec: SessionRecord, pose: np.ndarray, *, candidate_id: int | None = None,
            keep_in_pool: bool = False, h_view: Mapping[str, Tensor] | None = None,
            update_information: bool = True, next_state: Any = KEEP,
            field: str = "body.candidate_id", now: float | None = None,
            ) -> tuple[SessionRecord, ViewRecord]:
    """Acquire the view at ``pose`` [4, 4] (float64, camera-to-world): the next record and the
    new view.

    Args:
        candidate_id: the candidate it is, taken out of the pool unless ``keep_in_pool``
            (409 naming ``field`` if it is not in the pool).
        h_view: the view's Fisher on ``rec``'s map with the session's background, every block,
            when the caller has it (a selection's ``chosen_information``); None: computed here.
        update_information: False leaves Hhat as it is, for a caller that rebuilds it from the
            views before it is read again (the benchmark, whose map trains between events).
        next_state: the selection's next warm state (:attr:`Selection.state`; stored as
            :func:`~agilegs.service.sessions.convert.storable_state` keeps it), or
            :data:`KEEP`.
    """
    changes: dict[str, Any] = {}
    if candidate_id is not None:
        i = pool_index(rec, candidate_id, field)
        if not keep_in_pool:
            changes.update(_without(rec, i))
    t = time.time() if now is None else now
    view = ViewRecord(id=rec.next_view_id, pose=pose, candidate_id=candidate_id, created_at=t)
    if update_information:
        hv = h_view if h_view is not None else _view_information(rec, rec.gmap, pose)
        changes["h_acc"] = accumulate_information(rec.h_acc, hv)
    if next_state is not KEEP:
        changes["warm_state"] = storable_state(next_state)
    new = bump(rec, t, views=rec.views + (view,), next_view_id=view.id + 1, **changes)
    return new, view


def commit_view(rec: SessionRecord, limits: Limits, *, candidate_id: int | None = None,
                pose: np.ndarray | None = None, keep_in_pool: bool = False,
                pending: PendingSelection | None = None, field: str = "body",
                now: float | None = None) -> tuple[SessionRecord, ViewRecord]:
    """Commit a candidate (its pose) or any ``pose`` as acquired; a ``pending`` selection
    gives its warm state (and its chosen view's Fisher, when that is the view)."""
    check_view_room(rec, 1, field, limits)
    if candidate_id is not None:
        pose = rec.pool_poses[pool_index(rec, candidate_id, f"{field}.candidate_id")]
    assert pose is not None
    h_view = pending.information_for(rec, pose) if pending is not None else None
    return acquire(rec, pose, candidate_id=candidate_id, keep_in_pool=keep_in_pool,
                   h_view=h_view, next_state=pending.next_state if pending else KEEP,
                   field=f"{field}.candidate_id", now=now)


def integrate_frames(rec: SessionRecord, frames: Sequence[Frame], field: str, limits: Limits,
                     *, pending: PendingSelection | None = None, now: float | None = None,
                     ) -> tuple[SessionRecord, dict[str, bytes], list[ViewRecord]]:
    """``frames`` added as new views (each acquired by :func:`acquire`) or attached to views
    acquired already, in one version; the next record, the files to write (name under
    ``views/`` -> bytes) and the views touched, in order. A ``pending`` selection is taken by
    the first new view."""
    check_view_room(rec, sum(1 for f in frames if f.obs.view_id is None), field, limits)
    t = time.time() if now is None else now
    version = rec.version
    blobs: dict[str, bytes] = {}
    touched: list[ViewRecord] = []
    for fr in frames:
        o = fr.obs
        where = f"{field}[{fr.index}]"
        if o.view_id is not None:
            pos = next((k for k, v in enumerate(rec.views) if v.id == o.view_id), None)
            if pos is None:
                raise conflict(f"{where}.view_id", f"view {o.view_id} does not exist")
            view = rec.views[pos]
            if view.image_file is not None or view.depth_file is not None:
                raise conflict(f"{where}.view_id", f"view {o.view_id} already has a frame")
        else:
            pose = fr.pose
            if o.candidate_id is not None and pose is None:
                pose = rec.pool_poses[pool_index(rec, o.candidate_id, f"{where}.candidate_id")]
            assert pose is not None
            rec, view = acquire(
                rec, pose, candidate_id=o.candidate_id, field=f"{where}.candidate_id",
                h_view=pending.information_for(rec, pose) if pending is not None else None,
                next_state=pending.next_state if pending is not None else KEEP, now=t)
            pending = None
            pos = len(rec.views) - 1
        files: dict[str, Any] = {}
        if fr.image_bytes is not None:
            name = f"v{view.id:08d}.rgb.{fr.image_ext}"
            blobs[name] = fr.image_bytes
            files.update(image_file=name, image_encoding=o.image.encoding if o.image else None)
        if fr.depth is not None:
            name = f"v{view.id:08d}.depth.npy"
            buf = io.BytesIO()
            np.save(buf, fr.depth, allow_pickle=False)
            blobs[name] = buf.getvalue()
            files.update(depth_file=name, depth_scale=1.0)
        if files:
            files["intrinsics"] = fr.intrinsics
            view = replace(view, **files)
            rec = replace(rec, views=rec.views[:pos] + (view,) + rec.views[pos + 1:])
        touched.append(view)
    return replace(rec, version=version + 1, updated_at=t), blobs, touched


# ============================================================================ the map
def replace_map(rec: SessionRecord, gmap: GaussianMap, limits: Limits, *,
                src: Tensor | None = None, mapper_progress: Mapping[str, Any] | None = None,
                now: float | None = None) -> SessionRecord:
    """``rec`` with a new map (a trainer's push, or the mapper's update) and Hhat following it.

    Args:
        gmap: the new Gaussians [N_new].
        src: the mapper's update: LongTensor [N_new], new Gaussian j descends from the
            current map's Gaussian ``src[j]`` (-1: new). Hhat then follows
            ``information.mapper_update``: ``carry`` (default) remaps it per Gaussian
            (:func:`~agilegs.service.mapper.topology.remap_per_gaussian`; new Gaussians get lambda),
            ``recompute`` recomputes it from every acquired view on the new map.
            None (a push): Hhat is recomputed from every acquired view when the Gaussian
            count changes or ``information.recompute_on_map_change`` is set, else kept.
        mapper_progress: the mapper's progress to persist with the map (merged into the
            record's ``mapper`` state).
    """
    if len(gmap) > limits.max_gaussians:
        raise too_large("body", f"{len(gmap)} Gaussians exceed max_gaussians "
                                f"({limits.max_gaussians})")
    cfg = rec.information_config
    if src is not None:
        if tuple(src.shape) != (len(gmap),):
            raise ValueError(f"src must have shape [{len(gmap)}], got {list(src.shape)}")
        if cfg.get("mapper_update", "carry") == "recompute":
            h = recompute_information(rec, gmap)
        else:
            h = carry_information(rec, gmap, src)
    elif len(gmap) != len(rec.gmap) or cfg.get("recompute_on_map_change", True):
        h = recompute_information(rec, gmap)
    else:
        h = rec.h_acc
    changes: dict[str, Any] = {}
    if mapper_progress is not None:
        changes["mapper"] = {**(rec.mapper or {}), **mapper_progress}
    return bump(rec, now, gmap=gmap, h_acc=h, **changes)
