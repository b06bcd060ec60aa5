"""One session: its Gaussians, Hhat, acquired views, candidate pool and defaults.

The state is an immutable :class:`~agilegs.service.store.SessionRecord`. Every change follows
the same steps, under the session's lock: validate everything (a
:class:`~agilegs.service.errors.ServiceError` leaves the session as it was), build a new
record, persist it (the store writes, fsyncs and renames), then swap it in; only then is the
change acknowledged. Reads take the current record without the lock (records are never
mutated), so they never wait behind a selection. The selection itself is in
:mod:`agilegs.service.sessions.selection`.

The mapper (:mod:`agilegs.service.trainer`) plugs in as ``Session.mapper``: a
:class:`MapperHook` told of new frames, which publishes trained maps back through
:meth:`Session.replace_map`.
"""

from __future__ import annotations

import io
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor

from agilegs.schemas import models as m
from agilegs.schemas.geometry import Intrinsics as WireIntrinsics

from ..errors import conflict, not_found, session_damaged, too_large, too_many
from ..integrity import DamagedFile, FileProblem
from ..mapper import remap_per_gaussian
from ..nbv.camera import Camera, Intrinsics
from ..nbv.gaussians import GaussianMap
from ..nbv.information import accumulate_information, fisher_diag, init_information
from ..settings import Settings
from ..store import SessionRecord, SessionStore, ViewRecord
from .convert import (
    Frame,
    information_summary,
    nbv_intrinsics,
    parse_frame,
    parse_gaussians,
    pool_out,
    poses_array,
    view_out,
)
from .listing import record_summary
from .mapper_state import mapper_status
from .selection import run_select

__all__ = ["MapperHook", "Session", "SessionEnv", "fisher_background", "view_information"]


@dataclass(frozen=True)
class SessionEnv:
    """What every session shares: the server's settings, the store, a scratch folder, and
    whom to tell when a file read back does not check out (``report_damage(session,
    problem)``: the registry marks the session damaged)."""

    settings: Settings
    store: SessionStore
    tmp_dir: Path
    report_damage: Callable[[Session, FileProblem], None] | None = None


class MapperHook(Protocol):
    """The trainer's side of a session (``Session.mapper``)."""

    def integrate(self, session: Session, views: list[ViewRecord]) -> None:
        """New frames were persisted: queue their training (return quickly)."""

    def status(self, rec: SessionRecord) -> m.MapperStatus:
        """The mapper's progress as of ``rec``."""


def view_information(gmap: GaussianMap, c2w: Tensor, intrinsics: Intrinsics,
                     background: Tensor | None = None) -> dict[str, Tensor]:
    """The exact diagonal Fisher of one view of ``gmap`` rendered on ``background`` [3]
    (None: black); zeros for an empty map."""
    if gmap.num_gaussians == 0:
        return {k: torch.zeros_like(v) for k, v in gmap.items()}
    with torch.no_grad():
        return fisher_diag(gmap.detach(), Camera(c2w=c2w.to(gmap.dtype), intrinsics=intrinsics),
                           background=background)


def fisher_background(rec: SessionRecord, dtype: torch.dtype) -> Tensor | None:
    """The background of the session's Fisher renders: its default select config's
    ``fisher_background`` (None: black), so that Hhat and the selections agree."""
    bg = ((rec.defaults or {}).get("config") or {}).get("fisher_background")
    return None if bg is None else torch.tensor(list(bg), dtype=dtype)


class Session:
    """One session's state and operations (see the module docstring)."""

    def __init__(self, record: SessionRecord, env: SessionEnv) -> None:
        self.record = record
        self.env = env
        self.lock = threading.Lock()
        self.closed = False
        self.damaged: str | None = None  # why, once a file read back did not check out
        self.mapper: MapperHook | None = None  # the trainer plugs in (on_observation)
        self._summary: tuple[int, m.InformationSummary] | None = None  # (version, summary)

    # ------------------------------------------------------------------ helpers
    @property
    def id(self) -> str:
        return self.record.id

    @property
    def settings(self) -> Settings:
        return self.env.settings

    def check_open(self) -> None:
        if self.damaged is not None:
            raise session_damaged("path.session", f"session {self.id!r} is damaged: "
                                                  f"{self.damaged}")
        if self.closed:
            raise not_found("session", f"session {self.id!r} was deleted")

    def intrinsics(self, rec: SessionRecord | None = None) -> Intrinsics:
        return nbv_intrinsics((rec or self.record).intrinsics)

    def commit_record(self, new: SessionRecord, dirty: Iterable[str],
                      blobs: dict[str, bytes] | None = None) -> SessionRecord:
        """Persist ``new`` (version bumped by the caller) and swap it in."""
        saved = self.env.store.save(new, dirty, blobs)
        self.record = saved
        return saved

    def bump(self, rec: SessionRecord, **changes: Any) -> SessionRecord:
        return replace(rec, version=rec.version + 1, updated_at=time.time(), **changes)

    def _view_info(self, gmap: GaussianMap, pose: np.ndarray, rec: SessionRecord
                   ) -> dict[str, Tensor]:
        c2w = torch.from_numpy(pose).to(gmap.dtype)
        return view_information(gmap, c2w, self.intrinsics(rec),
                                fisher_background(rec, gmap.dtype))

    def accumulate(self, h: dict[str, Tensor], gmap: GaussianMap,
                          poses: Iterable[np.ndarray], rec: SessionRecord) -> dict[str, Tensor]:
        for pose in poses:
            h = accumulate_information(h, self._view_info(gmap, pose, rec))
        return h

    def _recompute_information(self, gmap: GaussianMap, rec: SessionRecord) -> dict[str, Tensor]:
        h = init_information(gmap, float(rec.information_config["lambda"]))
        return self.accumulate(h, gmap, (v.pose for v in rec.views), rec)

    def pool_index(self, rec: SessionRecord, cid: int, field: str) -> int:
        hits = np.nonzero(rec.pool_ids == cid)[0]
        if hits.size == 0:
            raise conflict(field, f"candidate {cid} is not in the pool")
        return int(hits[0])

    def without(self, rec: SessionRecord, index: int) -> dict[str, Any]:
        keep = np.ones(len(rec.pool_ids), dtype=bool)
        keep[index] = False
        return {"pool_ids": rec.pool_ids[keep], "pool_poses": rec.pool_poses[keep]}

    # ------------------------------------------------------------------ read
    def information_summary(self, rec: SessionRecord) -> m.InformationSummary:
        """Ĥ's summary and digest, computed once per version."""
        cached = self._summary
        if cached is not None and cached[0] == rec.version:
            return cached[1]
        summary = information_summary(rec.h_acc)
        self._summary = (rec.version, summary)
        return summary

    def info(self) -> m.SessionInfo:
        rec = self.record
        g = rec.gmap
        means_min = means_max = None
        if len(g):
            means_min = g.means.detach().amin(0).tolist()
            means_max = g.means.detach().amax(0).tolist()
        return m.SessionInfo(
            id=rec.id,
            created_at=rec.created_at,
            updated_at=rec.updated_at,
            version=rec.version,
            intrinsics=WireIntrinsics(**rec.intrinsics),
            bounds=m.Bounds(**rec.bounds) if rec.bounds else None,
            defaults=m.SelectDefaults(**rec.defaults),
            information_config=m.InformationConfig(**rec.information_config),
            gaussians=m.GaussiansSummary(count=len(g), sh_degree=g.sh_degree, means_min=means_min,
                                         means_max=means_max),
            information=self.information_summary(rec),
            pool_size=len(rec.pool_ids),
            next_candidate_id=rec.next_candidate_id,
            num_views=len(rec.views),
            last_view_id=rec.views[-1].id if rec.views else None,
            mapper=self.mapper_status(rec),
        )

    def mapper_status(self, rec: SessionRecord | None = None) -> m.MapperStatus:
        """The mapper's progress as of ``rec`` (default: the current record); state ``off``
        when the mapper does not run for this session."""
        rec = rec or self.record
        if self.mapper is not None:
            return self.mapper.status(rec)
        return mapper_status(rec, self.settings.mapper_steps_per_view)

    def get_gaussians(self) -> m.GaussiansOut:
        """The published Gaussians as float32 arrays."""
        rec = self.record
        g = rec.gmap
        arrays = m.GaussianArrays(**{
            k: m.NDArray.from_numpy(v.detach().cpu().numpy().astype("<f4")) for k, v in g.items()
        })
        steps = int((rec.mapper or {}).get("steps", 0))
        return m.GaussiansOut(arrays=arrays, count=len(g), sh_degree=g.sh_degree,
                              version=rec.version, mapper_steps=steps)

    def summary(self) -> m.SessionSummary:
        return record_summary(self.record)

    def get_pool(self) -> m.PoolOut:
        rec = self.record
        return pool_out(rec)

    def list_views(self) -> m.ViewsOut:
        rec = self.record
        return m.ViewsOut(views=[view_out(v) for v in rec.views], version=rec.version)

    def get_information(self) -> m.InformationOut:
        rec = self.record
        fields = {k: m.NDArray.from_numpy(v.detach().cpu().numpy().astype("<f4"))
                  for k, v in rec.h_acc.items()}
        return m.InformationOut(fields=fields, summary=self.information_summary(rec),
                                version=rec.version)

    def view_image(self, view_id: int) -> np.ndarray | None:
        """The stored image of a view as RGB [H, W, 3] (uint8 or float32), or None."""
        v = self._find_view(self.record, view_id)
        if v.image_file is None:
            return None
        data = self._read_frame_file(v.image_file)
        if v.image_encoding == "raw":
            return np.load(io.BytesIO(data), allow_pickle=False)
        from PIL import Image

        with Image.open(io.BytesIO(data)) as img:
            return np.asarray(img.convert("RGB"))

    def view_depth(self, view_id: int) -> np.ndarray | None:
        """The stored depth of a view [H, W] float32 in scene units (0: missing), or None."""
        v = self._find_view(self.record, view_id)
        if v.depth_file is None:
            return None
        return np.load(io.BytesIO(self._read_frame_file(v.depth_file)), allow_pickle=False)

    def _read_frame_file(self, name: str) -> bytes:
        """The bytes of ``views/<name>``, checked against the record's checksum; a file
        that does not check out is reported (the session becomes damaged) and raised."""
        rec = self.record
        try:
            return self.env.store.read_blob(self.id, name, rec.checksums.get(f"views/{name}"))
        except DamagedFile as exc:
            if self.env.report_damage is not None:
                self.env.report_damage(self, exc.problem)
            raise

    @staticmethod
    def _find_view(rec: SessionRecord, view_id: int, field: str = "view_id") -> ViewRecord:
        for v in rec.views:
            if v.id == view_id:
                return v
        raise not_found(field, f"view {view_id} does not exist")

    # ------------------------------------------------------------------ Gaussians
    def set_gaussians(self, req: m.GaussiansIn) -> m.SessionInfo:
        gmap = parse_gaussians(req, "body", max_gaussians=self.settings.max_gaussians,
                               tmp_dir=self.env.tmp_dir)
        with self.lock:
            self.check_open()
            self.replace_map(gmap)
        return self.info()

    def replace_map(self, gmap: GaussianMap, *, src: Tensor | None = None,
                    mapper_progress: Mapping[str, Any] | None = None) -> SessionRecord:
        """Swap in a new map (a trainer's push, or the mapper's update); the lock is held.

        Args:
            gmap: the new Gaussians [N_new].
            src: the mapper's update: LongTensor [N_new], new Gaussian j descends from the
                current map's Gaussian ``src[j]`` (-1: new). Ĥ then follows
                ``information.mapper_update``: ``carry`` (default) remaps it per Gaussian
                (:func:`~agilegs.service.mapper.remap_per_gaussian`; new Gaussians get λ),
                ``recompute`` recomputes it from every acquired view on the new map.
                None (a push): Ĥ is recomputed from every acquired view when the Gaussian
                count changes or ``information.recompute_on_map_change`` is set, else kept.
            mapper_progress: the mapper's progress to persist with the map (merged into
                the record's ``mapper`` state).
        """
        rec = self.record
        if len(gmap) > self.settings.max_gaussians:
            raise too_large("body", f"{len(gmap)} Gaussians exceed max_gaussians "
                                    f"({self.settings.max_gaussians})")
        cfg = rec.information_config
        if src is not None:
            if tuple(src.shape) != (len(gmap),):
                raise ValueError(f"src must have shape [{len(gmap)}], got {list(src.shape)}")
            if cfg.get("mapper_update", "carry") == "recompute":
                h = self._recompute_information(gmap, rec)
            else:
                h = self._carry_information(gmap, src, rec)
        elif len(gmap) != len(rec.gmap) or cfg.get("recompute_on_map_change", True):
            h = self._recompute_information(gmap, rec)
        else:
            h = rec.h_acc
        changes: dict[str, Any] = {}
        if mapper_progress is not None:
            changes["mapper"] = {**(rec.mapper or {}), **mapper_progress}
        new = self.bump(rec, gmap=gmap, h_acc=h, **changes)
        return self.commit_record(new, ("gaussians", "information"))

    def _carry_information(self, gmap: GaussianMap, src: Tensor, rec: SessionRecord
                           ) -> dict[str, Tensor]:
        """Ĥ of ``rec`` carried to ``gmap`` along ``src`` (new Gaussians: λ)."""
        h = remap_per_gaussian(rec.h_acc, src, 0.0)
        new = src.to(torch.long) < 0
        if bool(new.any()):
            prior = init_information(gmap, float(rec.information_config["lambda"]))
            for k in h:
                h[k][new] = prior[k][new].to(h[k].dtype)
        return h

    # ------------------------------------------------------------------ pool
    def set_pool(self, req: m.PoolIn) -> m.PoolOut:
        with self.lock:
            self.check_open()
            new = self.pool_changed(self.record, req, "body", replace_pool=True)
            return pool_out(self.commit_record(new, ("pool",)))

    def extend_pool(self, req: m.PoolIn) -> m.PoolOut:
        with self.lock:
            self.check_open()
            new = self.pool_changed(self.record, req, "body", replace_pool=False)
            return pool_out(self.commit_record(new, ("pool",)))

    def pool_changed(self, rec: SessionRecord, req: m.PoolIn, field: str, *,
                      replace_pool: bool) -> SessionRecord:
        d = len(req.poses)
        base = 0 if replace_pool else len(rec.pool_ids)
        limit = self.settings.max_pool_size
        if d > limit:
            raise too_large(f"{field}.poses", f"{d} candidates exceed max_pool_size ({limit})")
        if base + d > limit:
            raise too_many(f"{field}.poses", f"the pool would hold {base + d} candidates; "
                                             f"max_pool_size is {limit}")
        poses = poses_array(req.poses)
        if req.ids is not None:
            ids = np.asarray(req.ids, dtype=np.int64)
            if not replace_pool and len(rec.pool_ids):
                clash = np.nonzero(np.isin(ids, rec.pool_ids))[0]
                if clash.size:
                    i = int(clash[0])
                    raise conflict(f"{field}.ids[{i}]", f"candidate {int(ids[i])} is already "
                                                        "in the pool")
            next_id = max(rec.next_candidate_id, int(ids.max()) + 1 if d else 0)
        else:
            ids = np.arange(rec.next_candidate_id, rec.next_candidate_id + d, dtype=np.int64)
            next_id = rec.next_candidate_id + d
        if not replace_pool:
            ids = np.concatenate([rec.pool_ids, ids])
            poses = np.concatenate([rec.pool_poses, poses]) if d else rec.pool_poses
        return self.bump(rec, pool_ids=ids, pool_poses=poses, next_candidate_id=next_id)

    # ------------------------------------------------------------------ views
    def commit(self, req: m.CommitRequest) -> m.View:
        with self.lock:
            self.check_open()
            rec = self.record
            self.check_view_room(rec, 1, "body")
            changes: dict[str, Any] = {}
            if req.candidate_id is not None:
                i = self.pool_index(rec, req.candidate_id, "body.candidate_id")
                pose = rec.pool_poses[i]
                if not req.keep_in_pool:
                    changes.update(self.without(rec, i))
            else:
                assert req.pose is not None
                pose = req.pose.to_matrix()
            view = ViewRecord(id=rec.next_view_id, pose=pose, candidate_id=req.candidate_id,
                              created_at=time.time())
            h = accumulate_information(rec.h_acc, self._view_info(rec.gmap, pose, rec))
            new = self.bump(rec, views=rec.views + (view,), next_view_id=view.id + 1,
                             h_acc=h, **changes)
            self.commit_record(new, ("information", "pool") if changes else ("information",))
            return view_out(view)

    def check_view_room(self, rec: SessionRecord, n: int, field: str) -> None:
        if len(rec.views) + n > self.settings.max_views:
            raise too_many(field, f"the session would hold {len(rec.views) + n} views; "
                                  f"max_views is {self.settings.max_views}")

    def add_observations(self, req: m.ObservationsIn) -> m.ViewsOut:
        frames = [parse_frame(o, i, "body.observations", self.record.intrinsics,
                              max_image_pixels=self.settings.max_image_pixels)
                  for i, o in enumerate(req.observations)]
        with self.lock:
            self.check_open()
            new, blobs, touched = self.integrate_frames(self.record, frames, "body.observations")
            pool_changed = len(new.pool_ids) != len(self.record.pool_ids)
            dirty = ["information"] + (["pool"] if pool_changed else [])
            saved = self.commit_record(new, dirty, blobs)
            self.on_observation(touched)
            return m.ViewsOut(views=[view_out(v) for v in touched], version=saved.version)

    def integrate_frames(self, rec: SessionRecord, frames: list[Frame], field: str
                   ) -> tuple[SessionRecord, dict[str, bytes], list[ViewRecord]]:
        """A record with ``frames`` added as views (or attached to views), Ĥ updated."""
        views = list(rec.views)
        pool_ids, pool_poses = rec.pool_ids, rec.pool_poses
        next_view = rec.next_view_id
        blobs: dict[str, bytes] = {}
        touched: list[ViewRecord] = []
        new_poses: list[np.ndarray] = []
        n_new = sum(1 for f in frames if f.obs.view_id is None)
        self.check_view_room(rec, n_new, field)
        for fr in frames:
            o = fr.obs
            where = f"{field}[{fr.index}]"
            if o.view_id is not None:
                pos = next((k for k, v in enumerate(views) if v.id == o.view_id), None)
                if pos is None:
                    raise conflict(f"{where}.view_id", f"view {o.view_id} does not exist")
                if views[pos].image_file is not None or views[pos].depth_file is not None:
                    raise conflict(f"{where}.view_id", f"view {o.view_id} already has a frame")
                view = views[pos]
            else:
                candidate = None
                if o.candidate_id is not None:
                    hits = np.nonzero(pool_ids == o.candidate_id)[0]
                    if hits.size == 0:
                        raise conflict(f"{where}.candidate_id",
                                        f"candidate {o.candidate_id} is not in the pool")
                    i = int(hits[0])
                    candidate = o.candidate_id
                    pose = o.pose.to_matrix() if o.pose is not None else pool_poses[i]
                    keep = np.ones(len(pool_ids), dtype=bool)
                    keep[i] = False
                    pool_ids, pool_poses = pool_ids[keep], pool_poses[keep]
                else:
                    assert o.pose is not None
                    pose = o.pose.to_matrix()
                view = ViewRecord(id=next_view, pose=pose, candidate_id=candidate,
                                  created_at=time.time())
                next_view += 1
                new_poses.append(pose)
                pos = len(views)
                views.append(view)
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
                views[pos] = view
            touched.append(view)
        h = self.accumulate(rec.h_acc, rec.gmap, new_poses, rec)
        new = self.bump(rec, views=tuple(views), next_view_id=next_view, h_acc=h,
                         pool_ids=pool_ids, pool_poses=pool_poses)
        return new, blobs, touched

    def on_observation(self, views: list[ViewRecord]) -> None:
        """Hook: where the mapper integrates new frames.

        Called with the session lock held, after ``views`` (new or given a frame) are
        persisted and Ĥ updated. The mapper attaches itself as ``self.mapper`` and is handed
        the session and the views; it must return quickly (queue the work) and push the
        trained map back through :meth:`replace_map` (under ``self.lock``). Images and depth
        are read with :meth:`view_image` / :meth:`view_depth`.
        """
        if self.mapper is not None:
            self.mapper.integrate(self, views)

    # ------------------------------------------------------------------ select

    # ------------------------------------------------------------------ select
    def select(self, req: m.SelectRequest) -> m.SelectResponse:
        """Choose the next view (see :func:`~agilegs.service.sessions.selection.run_select`)."""
        return run_select(self, req)
