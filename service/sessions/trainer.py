"""The service's mapper: sessions' maps trained in the background from the images sent.

One :class:`Trainer` per server (a single worker thread) serves every session with work,
round-robin, one burst at a time. Each session holds a :class:`SessionTrainer` (attached as
``Session.mapper``; :meth:`Session.on_observation` wakes the worker) that owns a
:class:`~agilegs.service.mapper.mapper.Mapper`, built lazily from the session's published Gaussians
and its acquired views that have an image.

Work owed: ``steps_per_view`` training steps per acquired view with an image (the session's
``MapperOptions.steps_per_view``, else the server's ``AGILEGS_MAPPER_STEPS_PER_VIEW``), minus
the steps done. The frames of new views come decoded from the request that sent them
(:meth:`Session.take_frame`); frames the session no longer holds (after a restart) are read
back from the store. A burst:

1. outside the session lock, on the mapper's own copy: sync the mapper with the session's
   record (a map replaced by ``set_gaussians`` is taken over, Adam restarting; new views with
   images are added, and with depth they extend the map where it does not cover them), then
   train ``min(AGILEGS_MAPPER_BURST, pending)`` steps (L1 + D-SSIM, densify / prune, as
   :class:`~agilegs.config.mapper.MapperConfig` says);
2. under the session lock: publish a snapshot of the trained map through
   :meth:`Session.replace_map`, which persists it (Gaussians, Ĥ and the mapper's progress
   in the manifest, one atomic commit) before swapping it in. Selections never see a
   half-trained map, and a map replaced meanwhile by a trainer's push wins (the burst is
   dropped). When a selection holds the lock and steps are still pending, the worker trains
   on and publishes after the next burst instead of waiting.

Ĥ across a publication (``InformationConfig.mapper_update``): by default ``carry``: Ĥ is
carried over per Gaussian with :func:`~agilegs.service.mapper.topology.remap_per_gaussian` along the
composed :class:`~agilegs.service.mapper.topology.TopologyChange` ``src`` of the burst (Gaussians
kept as themselves keep their row, clones and split children copy their source's row, Gaussians
added from depth start at λ), so Ĥ always has the published map's Gaussian count; the
information of the views is not re-evaluated on the moved Gaussians (the paper's
incremental Ĥ). ``recompute`` re-evaluates Ĥ = λI + Σ_v H_v on the new map from every
acquired view at each publication (FisherRF's way; one Fisher pass per view).

Restart: the published map and the step count are in the store, so after a restart the
mapper is rebuilt from the persisted map and trains the steps still owed. What is not
persisted: Adam's moments (they restart at zero), the densification statistics, and the
mapper's step-indexed schedules (position learning-rate decay, densification window, SH
degree growth), which count from the rebuild. Views present when a mapper is built do not
extend the map from their depth (the map already holds them; an empty map is initialised
from them); views sent later do.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor

from agilegs import schemas as m
from agilegs.schemas.mapper import MapperState

from ..errors import is_disk_full
from ..mapper.mapper import Mapper
from ..mapper.topology import TopologyChange
from ..nbv import Camera, GaussianMap
from ..settings import Settings
from ..store.records import SessionRecord
from .convert import nbv_intrinsics
from .mapper_state import image_views, mapper_config, mapper_options, steps_per_view
from .session import Session

__all__ = ["SessionTrainer", "Trainer", "compose_src"]

log = logging.getLogger(__name__)


# ============================================================================ helpers
def compose_src(prev: Tensor, src: Tensor) -> Tensor:
    """Compose two topology changes: ``prev`` [N_mid] relates the middle set to a base set,
    ``src`` [N_new] the new set to the middle one; returns [N_new] relating the new set to the
    base (-1 where a Gaussian is new in either step)."""
    s = src.to(prev.device).long()
    if s.numel() == 0:
        return s.clone()
    if prev.numel() == 0:
        return torch.full_like(s, -1)
    return torch.where(s >= 0, prev[s.clamp_min(0)], torch.full_like(s, -1))


# ============================================================================ per session
class SessionTrainer:
    """A session's mapper and training progress (``Session.mapper``).

    Written by the trainer's worker thread only; the request threads read the counters.
    """

    def __init__(self, trainer: Trainer, session: Session) -> None:
        self.trainer = trainer
        self.session = session
        state = session.record.mapper or {}
        self.mapper: Mapper | None = None
        self.base: GaussianMap | None = None  # the record's map the mapper descends from
        self.src: Tensor | None = None  # mapper Gaussian j descends from base[src[j]] (-1: new)
        self.view_ids: set[int] = set()
        self.steps = int(state.get("steps", 0))
        self.published_steps = self.steps
        self.last_loss: float | None = state.get("last_loss")
        self.dirty = False  # the mapper's map differs from the published one
        self.published_version = 0  # the session version of the last publication
        self.error: str | None = None
        self.error_owed: int | None = None
        self.full_until: float | None = None  # monotonic time: a publication refused for space

    # ------------------------------------------------------------------ hook
    def integrate(self, session: Session, views: list[Any]) -> None:
        """``Session.on_observation``: new frames are persisted; wake the worker."""
        self.trainer.wake()

    # ------------------------------------------------------------------ accounting
    @property
    def options(self) -> m.MapperOptions:
        return mapper_options(self.session.record)

    def steps_per_view(self, options: m.MapperOptions | None = None) -> int:
        return steps_per_view(options or self.options,
                               self.trainer.settings.mapper_steps_per_view)

    def owed(self, rec: SessionRecord | None = None) -> int:
        """Steps owed to the views sent: steps_per_view x views with an image."""
        rec = rec or self.session.record
        return self.steps_per_view(mapper_options(rec)) * image_views(rec)

    def pending(self, rec: SessionRecord | None = None) -> int:
        return max(0, self.owed(rec) - self.steps)

    def failed(self, rec: SessionRecord | None = None) -> bool:
        """Training failed and nothing new arrived since (new views retry)."""
        return (self.error is not None and self.full_until is None
                and self.error_owed == self.owed(rec))

    def waiting_for_space(self) -> bool:
        """A publication was refused for lack of space moments ago (retried after a wait)."""
        return self.full_until is not None and time.monotonic() < self.full_until

    def has_work(self) -> bool:
        s = self.session
        if s.closed or not self.options.enabled:
            return False
        rec = s.record
        if self.failed(rec) or self.waiting_for_space():
            return False
        return self.pending(rec) > 0 or self.dirty

    def status(self, rec: SessionRecord | None = None) -> m.MapperStatus:
        """The progress as of record ``rec`` (default: the current one): ``idle`` only once
        ``rec`` is (or follows) the publication holding every step owed."""
        rec = rec or self.session.record
        options = mapper_options(rec)
        views = image_views(rec)
        published = int((rec.mapper or {}).get("steps", 0))
        if not options.enabled:
            state: MapperState = "off"
        elif self.failed(rec) or self.full_until is not None:
            state = "error"
        elif (self.pending(rec) > 0 or self.dirty or self.steps != published
              or rec.version < self.published_version):
            state = "training"
        else:
            state = "idle"
        mapper = self.mapper
        return m.MapperStatus(
            enabled=options.enabled,
            state=state,
            steps=self.steps,
            published_steps=published,
            pending_steps=self.pending(rec),
            steps_per_view=self.steps_per_view(options),
            views=views,
            num_gaussians=mapper.num_gaussians if mapper is not None else len(rec.gmap),
            last_loss=self.last_loss if self.last_loss is None or math.isfinite(self.last_loss)
            else None,
            error=self.error if state == "error" else None,
            options=options,
        )

    def progress(self) -> dict[str, Any]:
        """What the record keeps of the progress (with the map it belongs to)."""
        return {"steps": self.steps, "last_loss": self.last_loss}

    # ------------------------------------------------------------------ worker side
    def _on_change(self, change: TopologyChange) -> None:
        assert self.src is not None
        self.src = compose_src(self.src, change.src)
        self.dirty = True

    def _reset_base(self, gmap: GaussianMap) -> None:
        self.base = gmap
        self.src = torch.arange(len(gmap), dtype=torch.long)

    def drop(self) -> None:
        """Forget the mapper (rebuilt from the record on the next burst)."""
        self.mapper = None
        self.base = None
        self.src = None
        self.view_ids = set()
        self.steps = self.published_steps
        self.dirty = False
        self.session.forget_frames()

    def _load_view(self, view: Any, rec: SessionRecord) -> tuple[Camera, Tensor, Tensor | None]:
        """The view's camera, image and depth: as decoded when its frame came in, if the
        session still holds them, else read back from the store."""
        s = self.session
        fresh = s.take_frame(view.id)
        img, d = fresh if fresh is not None else (s.view_image(view.id), None)
        assert img is not None
        image = torch.from_numpy(np.array(img, copy=True))  # stored images are read-only
        depth = None
        if view.depth_file is not None:
            if fresh is None:
                d = s.view_depth(view.id)
            if d is not None:
                depth = torch.from_numpy(np.array(d, dtype=np.float32, copy=True))
        intr = nbv_intrinsics(view.intrinsics or rec.intrinsics)
        cam = Camera(c2w=torch.from_numpy(np.asarray(view.pose, dtype=np.float64)).float(),
                     intrinsics=intr)
        return cam, image, depth

    def sync(self, rec: SessionRecord) -> None:
        """Bring the mapper up to ``rec``: build it, take over a replaced map, add new views.
        Runs outside the session lock (records are immutable)."""
        if self.mapper is None:
            options = mapper_options(rec)
            cfg = mapper_config(options.config,
                                max_gaussians=self.trainer.settings.max_gaussians)
            extend = cfg.extend_from_depth
            empty = len(rec.gmap) == 0
            mapper = Mapper(rec.gmap, dataclasses.replace(cfg, extend_from_depth=extend and empty),
                            device=self.trainer.settings.device)
            self.mapper = mapper
            self._reset_base(rec.gmap)
            self.view_ids = set()
            mapper.on_topology_change.append(self._on_change)
            self._add_views(rec)
            mapper.config = cfg  # views sent from now on extend the map from their depth
            self.dirty = empty and mapper.num_gaussians > 0
            log.info("mapper of session %s built: %d Gaussians, %d views", rec.id,
                     mapper.num_gaussians, mapper.num_views)
            return
        if rec.gmap is not self.base:  # replaced by a trainer's push: train that one
            self.mapper.replace_gmap(rec.gmap)
            self._reset_base(rec.gmap)
            self.steps = self.published_steps
            self.dirty = False
            log.info("mapper of session %s: map replaced (%d Gaussians)", rec.id, len(rec.gmap))
        self._add_views(rec)

    def _add_views(self, rec: SessionRecord) -> None:
        assert self.mapper is not None
        for v in rec.views:
            if v.image_file is None or v.id in self.view_ids:
                continue
            cam, image, depth = self._load_view(v, rec)
            self.mapper.add_view(cam, image, depth, name=f"view_{v.id}")
            self.view_ids.add(v.id)

    def train(self, n: int, stop: threading.Event) -> int:
        """Up to ``n`` steps (fewer when ``stop`` is set); returns how many were taken."""
        assert self.mapper is not None
        losses: list[float] = []
        for _ in range(n):
            if stop.is_set():
                break
            info = self.mapper.step(1)
            self.steps += 1
            self.dirty = True
            losses.append(float(info["loss"]))
        if losses:
            self.last_loss = sum(losses) / len(losses)
        return len(losses)

    def publish(self, *, block: bool) -> bool:
        """Publish the mapper's map (persisted, then visible); False if the session lock was
        busy and ``block`` is false."""
        if self.mapper is None or not self.dirty:
            return True
        gmap = self.mapper.gmap.to(device="cpu")  # a detached copy: records are never mutated
        assert self.src is not None
        src = self.src.clone()
        s = self.session
        if not s.lock.acquire(blocking=block):
            return False
        try:
            if s.closed:
                return True
            if s.record.gmap is not self.base:  # a push replaced the map: drop this burst
                log.info("session %s: map replaced during a burst; dropping %d steps", s.id,
                         self.steps - self.published_steps)
                self.steps = self.published_steps
                self.dirty = False
                return True
            rec = s.replace_map(gmap, src=src, mapper_progress=self.progress())
            self._reset_base(rec.gmap)
            self.published_steps = self.steps
            self.published_version = rec.version
            self.dirty = False
        finally:
            s.lock.release()
        return True


# ============================================================================ the worker
class Trainer:
    """The background worker that trains every session's map.

    Args:
        sessions: returns the sessions to serve (the registry's, at the time of the call).
        settings: the server's ``mapper_steps_per_view``, ``mapper_burst`` and
            ``max_gaussians``.
        idle_wait: seconds the worker sleeps when no session has work, unless woken; also
            how long a session whose publication was refused for lack of space waits
            before the next try (its trained steps are kept meanwhile).
        on_refused_write: called each time a publication is refused for lack of space.
    """

    def __init__(self, sessions: Callable[[], list[Session]], settings: Settings, *,
                 idle_wait: float = 5.0,
                 on_refused_write: Callable[[], None] | None = None) -> None:
        self.sessions = sessions
        self.settings = settings
        self.idle_wait = float(idle_wait)
        self.on_refused_write = on_refused_write
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last: str | None = None  # round-robin position

    # ------------------------------------------------------------------ lifecycle
    def attach(self, session: Session) -> SessionTrainer:
        st = SessionTrainer(self, session)
        session.mapper = st
        return st

    def start(self) -> None:
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name="agilegs-mapper", daemon=True)
        self._thread.start()
        self.wake()

    def close(self, timeout: float = 60.0) -> None:
        """Stop after the current step, publishing what was trained."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout)
            if self._thread.is_alive():
                log.warning("the mapper did not stop within %.0f s", timeout)
            self._thread = None

    def wake(self) -> None:
        self._wake.set()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # ------------------------------------------------------------------ loop
    def _next(self) -> SessionTrainer | None:
        """The next session with work, round-robin after the last one served."""
        sessions = [s for s in self.sessions() if isinstance(s.mapper, SessionTrainer)]
        if not sessions:
            return None
        ids = [s.id for s in sessions]
        start = ids.index(self._last) + 1 if self._last in ids else 0
        for k in range(len(sessions)):
            s = sessions[(start + k) % len(sessions)]
            st = s.mapper
            assert isinstance(st, SessionTrainer)
            if st.has_work():
                return st
        return None

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.clear()
            st = self._next()
            if st is None:
                self._wake.wait(self.idle_wait)
                continue
            self._last = st.session.id
            self.burst(st)

    def burst(self, st: SessionTrainer) -> int:
        """One burst on ``st``'s session: sync, train, publish. Returns the steps taken."""
        s = st.session
        burst = self.settings.mapper_burst
        t0 = time.perf_counter()
        try:
            rec = s.record
            st.sync(rec)
            n = st.train(min(burst, st.pending(rec)), self._stop)
            more = st.pending(s.record) > 0 and not self._stop.is_set()
            if not st.publish(block=not more):
                log.debug("session %s is busy; publishing after the next burst", s.id)
            st.error = None
            st.error_owed = None
            st.full_until = None
        except Exception as exc:  # a failing session must not stop the others
            if s.closed:  # deleted (its files are gone) or found damaged under the burst
                log.debug("session %s was closed during a burst", s.id)
                st.drop()
                return 0
            if is_disk_full(exc):  # keep what was trained; publish once space is freed
                log.warning("mapper of session %s: the state folder is full; publishing "
                            "again in %.0f s", s.id, self.idle_wait)
                st.error = f"the state folder is full ({exc}); publishing again soon"
                st.full_until = time.monotonic() + self.idle_wait
                if self.on_refused_write is not None:
                    self.on_refused_write()
                return 0
            log.exception("mapper of session %s failed", s.id)
            st.error = f"{type(exc).__name__}: {exc}"
            st.error_owed = st.owed()
            st.drop()
            return 0
        log.debug("session %s: %d steps in %.2f s (loss %.4g, %d Gaussians)", s.id, n,
                  time.perf_counter() - t0, st.last_loss or float("nan"),
                  st.mapper.num_gaussians if st.mapper is not None else 0)
        return n
