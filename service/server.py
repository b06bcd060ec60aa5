"""One NBV server instance: HTTP (FastAPI on uvicorn) and Zenoh, each optional.

:class:`Server` wires one instance together: the sessions (:class:`SessionRegistry
<agilegs.service.sessions.registry.SessionRegistry>`), the request pipeline
(:class:`~agilegs.service.transports.gateway.Gateway`), the cluster node that routes operations to
the instance owning a session
(:class:`~agilegs.service.transports.zenoh.cluster.ClusterNode`), the Zenoh
transport (:class:`~agilegs.service.transports.zenoh.adapter.ZenohAdapter`) with the ROS 2 one on
its
session (:class:`~agilegs.service.transports.ros2.adapter.Ros2Adapter`) and the metrics; the HTTP
transport is an app around it (:func:`agilegs.service.transports.http.app.create_app`).

The command ``agilegs serve`` that runs one is :mod:`agilegs.service.serve`.
"""

from __future__ import annotations

import gc
import logging
import threading
import time
from typing import TYPE_CHECKING

from .sessions.registry import SessionRegistry
from .settings import Settings
from .store.state_dir import StateLock, claim_state_dir
from .transports.gateway import Gateway
from .transports.metrics import Metrics
from .transports.zenoh.adapter import ZenohAdapter
from .transports.zenoh.cluster import ClusterNode

if TYPE_CHECKING:
    from .transports.ros2.adapter import Ros2Adapter

__all__ = ["Server"]

log = logging.getLogger(__name__)


class Server:
    """One server instance: sessions, gateway, cluster node, Zenoh, metrics.

    The state folder is claimed exclusively (:mod:`agilegs.service.store.state_dir`) from
    :meth:`claim_state` (:meth:`start` claims it if that was not called) until :meth:`close`.

    Args:
        settings: the server's settings.
        freeze_gc: after starting, move every object alive to the collector's permanent
            generation (``gc.freeze``), so that the full collections that requests trigger do not
            walk the libraries' objects (for a process that only serves: ``agilegs serve``).
    """

    def __init__(self, settings: Settings, *, freeze_gc: bool = False) -> None:
        self.settings = settings
        self.freeze_gc = freeze_gc
        self.registry = SessionRegistry(settings)
        self.metrics = Metrics(sessions=lambda: len(self.registry.sessions),
                               damaged=lambda: len(self.registry.damaged))
        self.registry.on_refused_write = self.metrics.observe_refused_write
        self.gateway = Gateway(self.registry, settings, self.metrics)
        self.cluster = ClusterNode(self.registry, settings, self.gateway.executor)
        self.gateway.router = self.cluster
        self.gateway.decision_hooks.append(self.registry.decisions.record)
        self.zenoh: ZenohAdapter | None = None
        self.ros2: Ros2Adapter | None = None
        self.state_lock: StateLock | None = None
        self.warm: str | None = None  # "compiling", "done", "failed" (None: no warm-up)
        self.warm_seconds: float | None = None

    def warming(self) -> str | None:
        """The reason ``/readyz`` gives while the warm-up runs, or None."""
        if self.warm == "compiling":
            return "compiling the selection kernels (warm-up: AGILEGS_WARMUP)"
        return None

    def _warm_up(self) -> None:
        """Compile the kernels (:func:`~agilegs.service.nbv.warmup.warm_up`); a failure is
        logged and leaves the server ready (its first calls compile them instead)."""
        t0 = time.perf_counter()
        try:
            from .nbv.warmup import warm_up

            warm_up()
            self.warm = "done"
        except Exception:
            log.exception("warm-up failed: the first selection compiles the kernels instead")
            self.warm = "failed"
        self.warm_seconds = time.perf_counter() - t0
        log.info("warm-up: kernels ready in %.1f s", self.warm_seconds)

    def claim_state(self) -> None:
        """Claim the state folder (created if missing); a one-line
        :class:`~agilegs.service.store.state_dir.StateDirError` if it is read-only, cannot be
        created, or another server holds it."""
        if self.state_lock is None:
            self.state_lock = claim_state_dir(self.settings.state_dir, command="agilegs serve",
                                              instance=self.cluster.instance_id)

    def start(self) -> None:
        """Claim the state folder, load the sessions (the mapper starts with them) and join
        Zenoh when it is on; the warm-up starts in the background (``warmup``)."""
        self.claim_state()
        if self.settings.warmup and self.warm is None:
            self.warm = "compiling"
            threading.Thread(target=self._warm_up, name="agilegs-warmup", daemon=True).start()
        self.registry.load()
        if self.settings.zenoh:
            self.zenoh = ZenohAdapter(self.gateway, self.cluster, self.settings)
            self.zenoh.start()
            if self.settings.ros2:
                from .transports.ros2.adapter import Ros2Adapter

                self.ros2 = Ros2Adapter(self.gateway, self.settings.ros2)
                self.ros2.start(self.zenoh.session)
        if self.freeze_gc:
            gc.collect()
            gc.freeze()

    def close(self) -> None:
        """Leave Zenoh, stop the mapper and the worker threads."""
        if self.ros2 is not None:
            self.ros2.close()
            self.ros2 = None
        if self.zenoh is not None:
            self.zenoh.close()
            self.zenoh = None
        self.registry.close()
        self.gateway.close()
        if self.state_lock is not None:
            self.state_lock.release()
            self.state_lock = None
