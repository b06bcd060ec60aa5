"""All sessions of one server: loading them, creating and deleting them, and the table that
names each operation's handler.

:data:`HANDLERS` maps every operation of :data:`agilegs.schemas.ops.OPERATIONS` to the
function that runs it on a validated request; :meth:`SessionRegistry.execute` looks it up.
The transports never call it directly: :mod:`agilegs.service.transports.gateway` decodes and
validates a
request and dispatches it here (or, in a cluster, to the instance that owns the session).
"""

from __future__ import annotations

import logging
import re
import threading
import time
import uuid
from collections.abc import Callable, Iterable
from dataclasses import replace
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import torch
from pydantic import BaseModel, ValidationError

from agilegs import schemas as m
from agilegs.schemas import OPERATIONS, DecisionsOut, DecisionsRequest
from agilegs.schemas.config import patch_dict
from agilegs.schemas.requests import session_id_for

from ..errors import (
    ServiceError,
    conflict,
    invalid,
    is_disk_full,
    not_found,
    session_damaged,
    too_large,
    too_many,
)
from ..errors import validation_error as _validation_error
from ..nbv import cancel
from ..settings import Settings
from ..store.blobs import BlobError
from ..store.integrity import Damage, FileProblem
from ..store.objects import AnyStore, Fenced, ObjectSessionStore, open_store
from ..store.records import SessionRecord
from ..store.write import StoreError
from . import requests as rq
from .convert import (
    empty_map,
    gaussians_from_depth,
    parse_frame,
    parse_gaussians,
    poses_array,
    random_gaussians,
)
from .decisions import DecisionLog
from .listing import damaged_error, damaged_summary
from .mapper_state import initial_mapper_state, mapper_config
from .selection import check_render_widths
from .session import Session, SessionEnv, store_unavailable
from .trainer import Trainer
from .transitions import Limits, integrate_frames, new_record, set_pool

__all__ = ["HANDLERS", "Handler", "SessionRegistry"]

log = logging.getLogger(__name__)

_SESSION_RE = re.compile(m.SESSION_ID_PATTERN)

Handler = Callable[["SessionRegistry", "str | None", Any], BaseModel]
"""``handler(registry, session id, validated request or None) -> response model``."""


class SessionRegistry:
    """The sessions of one server, its store, and the mapper's lifecycle.

    Sessions whose files do not check out (found on loading, or when a frame is read back)
    are held apart in :attr:`damaged`: listed with state ``damaged``, their operations
    refused with 409 ``session_damaged`` but for ``repair_session`` and ``delete_session``.

    Args:
        settings: the server's settings (limits, state folder or URL, mapper schedule).
        store: the session store (default: the one the settings name, :func:`open_store
            <agilegs.service.store.objects.open_store>`).
    """

    def __init__(self, settings: Settings, store: AnyStore | None = None) -> None:
        self.settings = settings
        self.store = store if store is not None else open_store(
            settings.state_url or settings.state_dir, fsync=settings.fsync,
            endpoint=settings.state_endpoint)
        self.sessions: dict[str, Session] = {}
        self.damaged: dict[str, Damage] = {}
        self.lost: dict[str, str] = {}  # sessions another instance took over: why
        self.lock = threading.Lock()
        self._repairing = threading.Lock()  # one repair or deletion of a damaged session
        self.started = time.time()
        self.zenoh_enabled = False
        self.trainer: Trainer | None = None  # while the mapper runs (see load)
        self.on_refused_write: Callable[[str, str], None] | None = None  # (source, op)
        # the decisions feed; the server hooks record() to the gateway's decisions
        self.decisions = DecisionLog(settings.decision_log,
                                     max_waiters=max(1, settings.workers // 2))
        self.env = SessionEnv(settings=settings, store=self.store,
                              tmp_dir=Path(settings.state_dir) / "tmp",
                              report_damage=self.report_damage, report_lost=self.drop_lost)
        if settings.torch_threads:
            torch.set_num_threads(settings.torch_threads)

    # ------------------------------------------------------------------ lifecycle
    def load(self) -> int:
        """Load every persisted session (checked; damaged ones are held apart) and start the
        mapper (when on); returns how many intact sessions were loaded."""
        tmp = self.env.tmp_dir
        try:
            tmp.mkdir(parents=True, exist_ok=True)
            for stale in tmp.iterdir():
                stale.unlink(missing_ok=True)
        except OSError as exc:  # a full disk: serve what is there (uploads answer 507)
            if not is_disk_full(exc):
                raise
            log.warning("the state folder is full: %s", exc)
        records: list[SessionRecord] = []
        damaged: list[Damage] = []
        if not self.fleet:  # a fleet's node takes the sessions no live instance owns
            records, damaged = self.store.load_all()
        for rec in records:
            self.sessions[rec.id] = Session(rec, self.env)
        for d in damaged:
            self.damaged[d.session] = d
        log.info("loaded %d session(s) from %s%s", len(self.sessions), self.store.where,
                 f" ({len(damaged)} damaged: {', '.join(sorted(self.damaged))})"
                 if damaged else "")
        if self.settings.mapper:
            self.start_mapper()
        return len(self.sessions)

    def start_mapper(self) -> None:
        """Start the background mapper (:mod:`agilegs.service.sessions.trainer`) for every
        session; sessions with steps still owed (e.g. after a restart) resume training."""
        if self.trainer is None:
            self.trainer = Trainer(lambda: list(self.sessions.values()), self.settings,
                                   on_refused_write=self._refused_publication)
            for s in list(self.sessions.values()):
                self.trainer.attach(s)
        self.trainer.start()

    def close(self) -> None:
        self.decisions.shutdown()
        if self.trainer is not None:
            self.trainer.close()

    # ------------------------------------------------------------------ dispatch
    def execute(self, op: str, session: str | None, req: BaseModel | None, *,
                check: Callable[[], None] | None = None, request_id: str | None = None
                ) -> BaseModel:
        """Run operation ``op`` with its validated request; a :class:`ServiceError` for
        anything refused (the session is then unchanged). ``check`` is the request's
        cancellation check (:mod:`agilegs.service.nbv.cancel`): called while waiting for the
        session's lock and between the steps of a selection, it raises to stop there.
        ``request_id``: a write's request id (:mod:`agilegs.service.sessions.requests`): a
        write the session applied under it already is answered again, not applied."""
        handler = HANDLERS.get(op)
        if handler is None:
            raise not_found("op", f"unknown operation {op!r}")
        with rq.serving(op, request_id if OPERATIONS[op].http_method != "GET" else None):
            if check is None:
                return handler(self, session, req)
            with cancel.scope(check):
                return handler(self, session, req)

    def session(self, sid: str | None) -> Session:
        sid = self._checked_id(sid)
        s = self.sessions.get(sid)
        if s is None or s.closed:
            d = self.damaged.get(sid)
            if d is not None:
                raise damaged_error(d)
            why = self.lost.get(sid)
            if why is not None:
                raise ServiceError(404, "session_unavailable", f"session {sid!r} moved to "
                                   f"another instance ({why}): retry", "path.session",
                                   retry_after=0.2)
            raise not_found("session", f"session {sid!r} does not exist")
        return s

    @staticmethod
    def _checked_id(sid: str | None) -> str:
        if sid is None or not _SESSION_RE.match(sid):
            raise invalid("session", f"session id must match {m.SESSION_ID_PATTERN}")
        return sid

    def holds(self, sid: str) -> bool:
        """Whether session ``sid`` is here (intact or damaged)."""
        return sid in self.sessions or sid in self.damaged

    def held(self) -> set[str]:
        """The ids of the sessions here, intact (not deleted) and damaged."""
        return {sid for sid, s in list(self.sessions.items()) if not s.closed} | set(
            self.damaged)

    # ------------------------------------------------------------------ damage
    def report_damage(self, session: Session, problem: FileProblem) -> None:
        """A file of ``session`` read back does not check out (``problem``): the session's
        folder is checked again, and if it is damaged the session leaves service and is
        listed as damaged (a transient read error that checks out again changes nothing)."""
        log.error("session %s: %s", session.id, problem)
        # checked under the session's lock: no write of its own races the check (frames are
        # read outside that lock, by the mapper's worker)
        if not session.lock.acquire(timeout=60):
            log.warning("session %s is busy: its files are checked on the next read", session.id)
            return
        try:
            got = self.store.inspect(session.id)
        finally:
            session.lock.release()
        if not isinstance(got, Damage):
            log.warning("session %s checks out again after: %s", session.id, problem)
            return
        with self.lock:
            if self.sessions.get(session.id) is not session:
                return
            session.damaged = got.reason()
            session.closed = True
            self.sessions.pop(session.id, None)
            self.damaged[session.id] = got
        log.error("session %s is damaged: %s (repair: %s)", session.id, got.reason(), got.plan())

    @property
    def fleet(self) -> bool:
        """Whether this instance is one of a fleet: its sessions are in an object store and
        it joins Zenoh, where the instances hand the sessions over by lease
        (:mod:`agilegs.service.transports.zenoh.fleet`)."""
        return isinstance(self.store, ObjectSessionStore) and self.settings.zenoh

    def in_store(self, sid: str) -> bool:
        """Whether session ``sid`` is in the store (a folder store: held here)."""
        if isinstance(self.store, ObjectSessionStore):
            return self.store.exists(sid)
        return self.holds(sid)

    def set_owner(self, instance_id: str) -> None:
        """This instance's id, recorded in the leases it takes."""
        if isinstance(self.store, ObjectSessionStore):
            self.store.owner = instance_id

    def take_over(self, sid: str, live: Iterable[str] = ()) -> bool:
        """Take session ``sid`` over from the store (its lease, epoch + 1) and serve it; False
        when it is here already, gone, or another instance took it first (its lease names
        one of the ``live`` instances, or it changed while being taken)."""
        if not isinstance(self.store, ObjectSessionStore):
            return False
        with self.lock:
            if self.holds(sid):
                return False
        try:
            got = self.store.take_over(sid, unless=live)
        except (FileNotFoundError, Fenced):
            return False
        with self.lock:
            if self.holds(sid):
                return False
            self.lost.pop(sid, None)
            if isinstance(got, Damage):
                self.damaged[sid] = got
                log.error("session %s (taken over) is damaged: %s", sid, got.reason())
            else:
                s = Session(got, self.env)
                if self.trainer is not None:
                    self.trainer.attach(s)
                self.sessions[sid] = s
                self.decisions.open(sid)
        if self.trainer is not None:
            self.trainer.wake()
        log.info("session %s taken over (version %s)", sid,
                 got.version if isinstance(got, Damage) else got.version)
        return True

    def check_leases(self) -> list[str]:
        """Drop the sessions whose lease another instance took (their manifest changed in
        the store); the ids dropped."""
        if not isinstance(self.store, ObjectSessionStore):
            return []
        out = []
        for s in list(self.sessions.values()):
            if not self.store.still_owned(s.id):
                with s.lock:
                    if not s.closed and not self.store.still_owned(s.id):
                        self.drop_lost(s, "another instance holds it now")
                        out.append(s.id)
        for sid in list(self.damaged):
            if not self.store.still_owned(sid):
                with self.lock:
                    self.damaged.pop(sid, None)
                self.store.forget(sid)
                out.append(sid)
        return out

    def drop_lost(self, session: Session, why: str) -> None:
        """``session``'s commit was fenced: another instance owns it now. It leaves this
        instance (the store forgets it; its operations go to the new owner)."""
        log.warning("session %s: lost the lease (%s); dropping it here", session.id, why)
        session.lost = why
        session.closed = True
        with self.lock:
            self.lost[session.id] = why
            if self.sessions.get(session.id) is session:
                self.sessions.pop(session.id, None)
        self.store.forget(session.id)
        self.decisions.close(session.id)

    def repair_session(self, sid: str | None) -> m.Repaired:
        """Bring a damaged session back (:meth:`SessionStore.repair
        <agilegs.service.store.write.SessionStore.repair>`); nothing changes for an intact one."""
        sid = self._checked_id(sid)
        with self._repairing:
            s = self.sessions.get(sid)
            if s is not None and not s.closed:
                return m.Repaired(id=sid, repaired=False, version=s.record.version,
                                  message=f"session {sid!r} is not damaged: nothing to do")
            d = self.damaged.get(sid)
            if d is None:
                raise not_found("session", f"session {sid!r} does not exist")
            try:
                done = self.store.repair(sid)
            except StoreError:
                raise damaged_error(self._recheck(sid) or d) from None
            s = Session(done.record, self.env)
            with self.lock:
                if self.trainer is not None:
                    self.trainer.attach(s)
                self.damaged.pop(sid, None)
                self.sessions[sid] = s
        if self.trainer is not None:
            self.trainer.wake()
        what = []
        if done.rolled_back_to is not None:
            what.append(f"rolled back to version {done.rolled_back_to}")
        if done.dropped_frames:
            what.append("dropped the damaged frames of views "
                        + ", ".join(str(i) for i in done.dropped_frames))
        text = (" and ".join(what) or "rewrote the manifest") if done.repaired else (
            "the files check out again: nothing to do")
        return m.Repaired(id=sid, repaired=done.repaired, rolled_back_to=done.rolled_back_to,
                          dropped_frames=list(done.dropped_frames), version=done.record.version,
                          message=f"session {sid!r}: {text}; now version {done.record.version}")

    def _recheck(self, sid: str) -> Damage | None:
        """Damaged session ``sid`` checked again (its listing updated); None if it is not."""
        got = self.store.inspect(sid)
        if not isinstance(got, Damage):
            return None
        with self.lock:
            self.damaged[sid] = got
        return got

    def _refused_publication(self) -> None:
        if self.on_refused_write is not None:
            self.on_refused_write("mapper", "publish")

    # ------------------------------------------------------------------ service operations
    def health(self) -> m.Health:
        try:
            ver = version("agilegs")
        except PackageNotFoundError:  # pragma: no cover - running from a source tree
            ver = "0+unknown"
        return m.Health(version=ver, sessions=len(self.sessions) + len(self.damaged),
                        damaged=len(self.damaged), zenoh=self.zenoh_enabled,
                        uptime_s=time.time() - self.started)

    def list_sessions(self) -> m.SessionList:
        out = [s.summary() for s in list(self.sessions.values())]
        out += [damaged_summary(d) for d in sorted(list(self.damaged.values()),
                                                   key=lambda d: d.session)]
        return m.SessionList(sessions=out)

    def delete_session(self, sid: str | None) -> m.Deleted:
        sid = self._checked_id(sid)
        with self._repairing:
            if sid in self.damaged and sid not in self.sessions:
                self.store.delete(sid)
                with self.lock:
                    self.damaged.pop(sid, None)
                return m.Deleted(id=sid)
        s = self.session(sid)
        with s.lock:
            if s.closed:
                raise not_found("session", f"session {sid!r} does not exist")
            try:
                self.store.delete(s.id)
            except Fenced as exc:  # another instance holds it now: it deletes it
                self.drop_lost(s, str(exc))
                raise ServiceError(404, "session_unavailable", f"session {sid!r} moved to "
                                   "another instance (nothing was deleted): retry",
                                   "path.session", retry_after=0.2) from None
            s.closed = True
            with self.lock:
                self.sessions.pop(s.id, None)
        self.decisions.close(s.id)
        return m.Deleted(id=s.id)

    def get_decisions(self, sid: str | None, req: DecisionsRequest) -> DecisionsOut:
        """The decisions feed of a session (:mod:`agilegs.service.sessions.decisions`): after
        ``req.after``, waiting up to ``req.wait`` (at most ``max_poll_wait``) s for one. A
        poll waiting when the session is deleted answers ``closed``; a deleted session's feed
        is gone (404), as the session is."""
        self.session(sid)
        assert sid is not None
        wait = min(req.wait, self.settings.max_poll_wait)
        return self.decisions.read(sid, req.after, req.limit, wait)

    def create_session(self, req: m.SessionCreate) -> m.SessionInfo:
        settings = self.settings
        rid = rq.current()
        sid = req.id or (session_id_for(rid) if rid is not None else f"s-{uuid.uuid4().hex[:12]}")
        if (done := self._created_already(sid)) is not None:
            return done
        with self.lock:
            self._check_new_id(sid)
        intr = req.intrinsics.model_dump()
        defaults = req.defaults
        if defaults.shortlist_size > settings.max_shortlist:
            if "shortlist_size" in defaults.model_fields_set:
                raise invalid("body.defaults.shortlist_size",
                              f"must be <= {settings.max_shortlist} (max_shortlist)")
            defaults = defaults.model_copy(update={"shortlist_size": settings.max_shortlist})
        check_render_widths(patch_dict(req.defaults.config), "body.defaults.config",
                            settings.max_image_pixels)
        pixels = req.intrinsics.width * req.intrinsics.height
        if pixels > settings.max_image_pixels:
            raise too_large("body.intrinsics", f"{pixels} pixels exceed max_image_pixels "
                                               f"({settings.max_image_pixels})")
        count = req.init_gaussians  # the default is lowered to the limit; a value given is not
        if "init_gaussians" not in req.model_fields_set:
            count = min(count, settings.max_gaussians)
        if req.gaussians is None and count > settings.max_gaussians:
            raise too_large("body.init_gaussians", f"exceeds max_gaussians "
                                                   f"({settings.max_gaussians})")
        frames = [parse_frame(f, i, "body.frames", intr, max_image_pixels=settings.max_image_pixels)
                  for i, f in enumerate(req.frames)]
        if len(frames) > settings.max_views:
            raise too_many("body.frames", f"{len(frames)} frames exceed max_views "
                                          f"({settings.max_views})")
        if req.gaussians is not None:
            gmap = parse_gaussians(req.gaussians, "body.gaussians",
                                   max_gaussians=settings.max_gaussians, tmp_dir=self.env.tmp_dir)
        elif any(f.depth is not None for f in frames):
            gmap = gaussians_from_depth(frames, count, req.seed)
        elif req.bounds is not None:
            gmap = random_gaussians(req.bounds, count, req.seed)
        else:  # RGB frames only: no Gaussians until some are set (a selection says map_empty)
            gmap = empty_map()
        if len(gmap) > settings.max_gaussians:
            raise too_large("body", f"{len(gmap)} Gaussians exceed max_gaussians "
                                    f"({settings.max_gaussians})")
        try:
            mapper_config(req.mapper.config)
        except ValidationError as exc:
            raise _validation_error(exc, "body.mapper.config") from None
        now = time.time()
        rec = new_record(sid, intr, gmap, defaults=defaults.model_dump(),
                         information_config=req.information.model_dump(by_alias=True),
                         bounds=req.bounds.model_dump() if req.bounds else None,
                         mapper=initial_mapper_state(req.mapper), now=now)
        limits = Limits.of(settings)
        if req.pool is not None:
            rec = set_pool(rec, poses_array(req.pool.poses), req.pool.ids, limits, "body.pool",
                           replace_pool=True, now=now)
        blobs: dict[str, bytes] = {}
        if frames:
            rec, blobs, _ = integrate_frames(rec, frames, "body.frames", limits, now=now)
        rec = replace(rec, version=1, updated_at=now)
        with self.lock:
            self._check_new_id(sid)
            try:
                rec = self.store.create(rq.remember(rec, None), blobs)
            except FileExistsError:
                if (done := self._created_already(sid)) is not None:
                    return done
                raise conflict("body.id", f"session {sid!r} already exists") from None
            except BlobError as exc:
                raise store_unavailable(exc) from None
            s = Session(rec, self.env)
            if self.trainer is not None:
                self.trainer.attach(s)
            self.sessions[sid] = s
            self.decisions.open(sid)
        if frames:
            s.on_observation(list(rec.views), frames)
        return s.info()

    def _created_already(self, sid: str) -> m.SessionInfo | None:
        """The session ``sid`` when the create being served carries a request id and created
        it already (held here, or in a fleet's store); None otherwise."""
        if rq.current() is None:
            return None
        held = self.sessions.get(sid)
        if held is not None:
            with held.locked():
                return held.replayed(m.SessionInfo, held.info)
        if not self.fleet:
            return None
        got = self.store.inspect(sid) if self.in_store(sid) else None
        if not isinstance(got, SessionRecord) or rq.applied(got) is None:
            return None
        log.info("session %s: created already under request %s (held by another instance)",
                 sid, rq.current())
        return Session(got, self.env).info()

    def _check_new_id(self, sid: str) -> None:
        if sid in self.sessions:
            raise conflict("body.id", f"session {sid!r} already exists")
        if sid in self.damaged:
            raise session_damaged("body.id", f"session {sid!r} already exists and is damaged "
                                             "(see list_sessions): repair or delete it first")
        if len(self.sessions) + len(self.damaged) >= self.settings.max_sessions:
            raise too_many("body", f"max_sessions ({self.settings.max_sessions}) reached")


def _on_session(fn: Callable[[Session, Any], BaseModel]) -> Handler:
    return lambda reg, sid, req: fn(reg.session(sid), req)


HANDLERS: dict[str, Handler] = {
    "health": lambda reg, sid, req: reg.health(),
    "create_session": lambda reg, sid, req: reg.create_session(req),
    "list_sessions": lambda reg, sid, req: reg.list_sessions(),
    "get_session": _on_session(lambda s, req: s.info()),
    "delete_session": lambda reg, sid, req: reg.delete_session(sid),
    "repair_session": lambda reg, sid, req: reg.repair_session(sid),
    "set_gaussians": _on_session(Session.set_gaussians),
    "get_gaussians": _on_session(lambda s, req: s.get_gaussians()),
    "add_observations": _on_session(Session.add_observations),
    "list_views": _on_session(lambda s, req: s.list_views()),
    "get_frames": _on_session(lambda s, req: s.get_frames(req)),
    "commit": _on_session(Session.commit),
    "set_pool": _on_session(Session.set_pool),
    "extend_pool": _on_session(Session.extend_pool),
    "get_pool": _on_session(lambda s, req: s.get_pool()),
    "select": _on_session(Session.select),
    "get_information": _on_session(lambda s, req: s.get_information()),
    "get_decisions": lambda reg, sid, req: reg.get_decisions(sid, req),
}
"""Each operation's handler (a test checks that it covers :data:`OPERATIONS` exactly)."""

