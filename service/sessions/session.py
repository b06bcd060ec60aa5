"""One session: the lock, the persisted record and the operations on it.

The state is an immutable :class:`~agilegs.service.store.records.SessionRecord`. Every change is a
function of it (:mod:`agilegs.service.sessions.transitions`, the select step in
:mod:`agilegs.service.sessions.selection`) that validates everything (a
:class:`~agilegs.service.errors.ServiceError` leaves the session as it was) and returns the
next record; the session holds its lock around that call, persists the record (the store
writes, fsyncs and renames) and only then swaps it in and acknowledges the change. Reads take
the current record without the lock (records are never mutated), so they never wait behind a
selection.

Beside the record, a session holds in memory the selection last made without commit (a
:class:`~agilegs.service.sessions.transitions.PendingSelection`, taken by the next
acquisition) and the decoded frames its mapper has not read yet.

The mapper (:mod:`agilegs.service.sessions.trainer`) plugs in as ``Session.mapper``: a
:class:`MapperHook` told of new frames, which publishes trained maps back through
:meth:`Session.replace_map`.
"""

from __future__ import annotations

import io
import logging
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, TypeVar

import numpy as np
from pydantic import BaseModel
from torch import Tensor

from agilegs import schemas as m
from agilegs.schemas import Intrinsics as WireIntrinsics

from ..errors import ServiceError, conflict, not_found, session_damaged
from ..nbv import GaussianMap
from ..nbv.cancel import checkpoint
from ..settings import Settings
from ..store.blobs import BlobError
from ..store.integrity import DamagedFile, FileProblem
from ..store.objects import AnyStore, Fenced
from ..store.records import SessionRecord, ViewRecord
from . import requests as rq
from . import transitions as tr
from .convert import (
    Frame,
    information_summary,
    parse_frame,
    parse_gaussians,
    pool_out,
    poses_array,
    view_out,
)
from .listing import record_summary
from .mapper_state import mapper_options, mapper_status
from .selection import select_response, select_step

__all__ = ["MapperHook", "Session", "SessionEnv", "changed_roles", "store_unavailable"]


log = logging.getLogger(__name__)

T = TypeVar("T", bound=BaseModel)


def store_unavailable(exc: BaseException) -> ServiceError:
    """503 ``unavailable``: the object store could not be written (nothing was changed)."""
    return ServiceError(503, "unavailable", f"the session store could not be written ({exc}): "
                        "nothing was changed, retry", retry_after=1.0)


@dataclass(frozen=True)
class SessionEnv:
    """What every session shares: the server's settings, the store, a scratch folder, whom
    to tell when a file read back does not check out (``report_damage(session, problem)``:
    the registry marks the session damaged), and whom to tell when a commit is fenced
    because another instance took the session over (``report_lost(session, why)``: the
    registry drops it)."""

    settings: Settings
    store: AnyStore
    tmp_dir: Path
    report_damage: Callable[[Session, FileProblem], None] | None = None
    report_lost: Callable[[Session, str], None] | None = None


class MapperHook(Protocol):
    """The trainer's side of a session (``Session.mapper``)."""

    def integrate(self, session: Session, views: list[ViewRecord]) -> None:
        """New frames were persisted: queue their training (return quickly)."""

    def status(self, rec: SessionRecord) -> m.MapperStatus:
        """The mapper's progress as of ``rec``."""


def changed_roles(old: SessionRecord, new: SessionRecord) -> list[str]:
    """The store's roles (files) of ``new`` that differ from ``old``'s: the transitions keep
    every part they do not change as the same object."""
    out = []
    if new.gmap is not old.gmap:
        out.append("gaussians")
    if new.h_acc is not old.h_acc:
        out.append("information")
    if new.pool_ids is not old.pool_ids or new.pool_poses is not old.pool_poses:
        out.append("pool")
    if new.warm_state is not old.warm_state:
        out.append("warm")
    return out


class Session:
    """One session's state and operations (see the module docstring)."""

    def __init__(self, record: SessionRecord, env: SessionEnv) -> None:
        self.record = record
        self.env = env
        self.limits = tr.Limits.of(env.settings)
        self.lock = threading.Lock()
        self.closed = False
        self.damaged: str | None = None  # why, once a file read back did not check out
        self.lost: str | None = None  # why, once another instance took the session over
        self.mapper: MapperHook | None = None  # the trainer plugs in (on_observation)
        self.pending: tr.PendingSelection | None = None  # the last selection without commit
        self._frames: dict[int, tuple[np.ndarray | None, np.ndarray | None]] = {}
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
        if self.lost is not None:
            raise ServiceError(404, "session_unavailable", f"session {self.id!r} moved to "
                               f"another instance ({self.lost}): retry", "path.session",
                               retry_after=0.2)
        if self.closed:
            raise not_found("session", f"session {self.id!r} was deleted")

    def apply(self, new: SessionRecord, blobs: dict[str, bytes] | None = None) -> SessionRecord:
        """Persist ``new`` (the next record a transition returned; the lock is held) and swap
        it in; ``new`` itself when it is the current record."""
        old = self.record
        if new is old:
            return old
        try:
            saved = self.env.store.save(new, changed_roles(old, new), blobs)
        except Fenced as exc:
            self.closed = True
            self.lost = str(exc)
            if self.env.report_lost is not None:
                self.env.report_lost(self, str(exc))
            raise ServiceError(404, "session_unavailable", f"session {self.id!r} moved to "
                               "another instance while this change was made (nothing was "
                               "changed): retry", "path.session", retry_after=0.2) from None
        except BlobError as exc:
            raise store_unavailable(exc) from None
        self.record = saved
        return saved

    def write(self, new: SessionRecord, blobs: dict[str, bytes] | None = None,
              answer: BaseModel | None = None) -> SessionRecord:
        """:meth:`apply` for a request's write: the request id it carries, if any, is
        recorded in the same commit with ``answer`` (:mod:`~agilegs.service.sessions.requests`)."""
        if new is not self.record:
            new = rq.remember(new, answer)
        return self.apply(new, blobs)

    def replayed(self, response: type[T], remake: Callable[[], T] | None = None) -> T | None:
        """The answer to the request being served when its request id names a write this
        session applied already (the lock is held): the answer kept, else ``remake()``; None
        when the write is new. 409 when it was applied and its answer is no longer kept."""
        found = rq.applied(self.record)
        if found is None:
            return None
        got = rq.replay(found, response)
        if got is None and remake is not None:
            got = remake()
        if got is None:
            raise conflict("request_id", f"request {found.id!r} was applied already (version "
                           f"{found.version}); its answer is no longer kept: read the session")
        log.info("session %s: request %s (%s) was applied already (version %d): answered "
                 "again, nothing applied", self.id, found.id, found.op, found.version)
        return got  # type: ignore[return-value]

    @contextmanager
    def locked(self) -> Iterator[None]:
        """Hold the session's lock for a change; while waiting for it, the request's
        cancellation is checked every 50 ms (:func:`agilegs.service.nbv.cancel.checkpoint`),
        so a cancelled request stops waiting and frees its worker."""
        while not self.lock.acquire(timeout=0.05):
            checkpoint()
        try:
            yield
        finally:
            self.lock.release()

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

    def get_frames(self, req: m.FramesRequest) -> m.FramesOut:
        """Acquired views with their frames as stored (one view, or all)."""
        rec = self.record
        views = rec.views if req.view_id is None else (self._find_view(rec, req.view_id),)
        out = []
        for v in views:
            image = depth = None
            if v.image_file is not None:
                data = self._read_frame_file(v.image_file)
                image = (m.ImageData.from_numpy(np.load(io.BytesIO(data), allow_pickle=False))
                         if v.image_encoding == "raw" else m.ImageData(
                             encoding="jpeg" if v.image_encoding == "jpeg" else "png", data=data))
            if req.depth and v.depth_file is not None:
                depth = m.NDArray.from_numpy(np.load(io.BytesIO(
                    self._read_frame_file(v.depth_file)), allow_pickle=False).astype("<f4"))
            out.append(m.Frame(view=view_out(v), image=image, depth=depth))
        return m.FramesOut(frames=out, version=rec.version)

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
        with self.locked():
            self.check_open()
            if (done := self.replayed(m.SessionInfo, self.info)) is not None:
                return done
            self.write(tr.replace_map(self.record, gmap, self.limits))
        return self.info()

    def replace_map(self, gmap: GaussianMap, *, src: Tensor | None = None,
                    mapper_progress: Mapping[str, Any] | None = None) -> SessionRecord:
        """Swap in a new map (:func:`~agilegs.service.sessions.transitions.replace_map`: a
        trainer's push, or the mapper's update with ``src``); the lock is held."""
        return self.apply(tr.replace_map(self.record, gmap, self.limits, src=src,
                                         mapper_progress=mapper_progress))

    # ------------------------------------------------------------------ pool
    def set_pool(self, req: m.PoolIn) -> m.PoolOut:
        return self._pool(req, replace_pool=True)

    def extend_pool(self, req: m.PoolIn) -> m.PoolOut:
        return self._pool(req, replace_pool=False)

    def _pool(self, req: m.PoolIn, *, replace_pool: bool) -> m.PoolOut:
        poses = poses_array(req.poses)
        with self.locked():
            self.check_open()
            if (done := self.replayed(m.PoolOut)) is not None:
                return done
            new = tr.set_pool(self.record, poses, req.ids, self.limits, "body",
                              replace_pool=replace_pool)
            out = pool_out(new)
            self.write(new, answer=out)
            return out

    # ------------------------------------------------------------------ views
    def commit(self, req: m.CommitRequest) -> m.View:
        pose = req.pose.to_matrix() if req.pose is not None else None
        with self.locked():
            self.check_open()
            if (done := self.replayed(m.View)) is not None:
                return done
            new, view = tr.commit_view(self.record, self.limits, candidate_id=req.candidate_id,
                                       pose=pose, keep_in_pool=req.keep_in_pool,
                                       pending=self.pending)
            out = view_out(view)
            self.write(new, answer=out)
            self.pending = None
            return out

    def add_observations(self, req: m.ObservationsIn) -> m.ViewsOut:
        frames = [parse_frame(o, i, "body.observations", self.record.intrinsics,
                              max_image_pixels=self.settings.max_image_pixels)
                  for i, o in enumerate(req.observations)]
        with self.locked():
            self.check_open()
            if (done := self.replayed(m.ViewsOut)) is not None:
                return done
            new, blobs, touched = tr.integrate_frames(self.record, frames, "body.observations",
                                                      self.limits, pending=self.pending)
            out = m.ViewsOut(views=[view_out(v) for v in touched], version=new.version)
            self.write(new, blobs, answer=out)
            if any(f.obs.view_id is None for f in frames):
                self.pending = None
            self.on_observation(touched, frames)
            return out

    def on_observation(self, views: list[ViewRecord], frames: Sequence[Frame] = ()) -> None:
        """Hook: where the mapper integrates new frames.

        Called with the session lock held, after ``views`` (new or given a frame) are
        persisted and Ĥ updated; ``frames`` are their decoded frames, in the same order (kept
        for the mapper, which reads them with :meth:`take_frame`, so that an image is decoded
        once). The mapper attaches itself as ``self.mapper`` and is handed the session and the
        views; it must return quickly (queue the work) and push the trained map back through
        :meth:`replace_map` (under ``self.lock``). Images and depth of other views are read
        with :meth:`view_image` / :meth:`view_depth`.
        """
        if self.mapper is None:
            return
        if frames and mapper_options(self.record).enabled:
            for view, fr in zip(views, frames, strict=True):
                if fr.image_rgb is not None:
                    self._frames[view.id] = (fr.image_rgb, fr.depth)
        self.mapper.integrate(self, views)

    def take_frame(self, view_id: int) -> tuple[np.ndarray | None, np.ndarray | None] | None:
        """The decoded image [H, W, 3] and depth [H, W] (None: none) of a view whose frame came
        in since the mapper last read it, forgotten once taken; None otherwise (read the
        store)."""
        return self._frames.pop(view_id, None)

    def forget_frames(self) -> None:
        """Drop the decoded frames kept for the mapper (it reads them from the store)."""
        self._frames.clear()

    # ------------------------------------------------------------------ select
    def select(self, req: m.SelectRequest) -> m.SelectResponse:
        """Choose the next view (:func:`~agilegs.service.sessions.selection.select_step`);
        with ``req.pool`` and / or ``req.commit`` the new pool and the acquired view are
        persisted together, after the selection succeeded. Without commit the selection is
        kept for the next acquisition to take its warm state."""
        with self.locked():
            self.check_open()
            if (done := self.replayed(m.SelectResponse)) is not None:
                return done
            t_core = time.perf_counter()
            out = select_step(self.record, req, self.limits)
            answer = select_response(out.record, out, t_core)
            self.write(out.record, answer=answer)
            self.pending = out.pending
            answer.core_ms = (time.perf_counter() - t_core) * 1e3
            return answer
