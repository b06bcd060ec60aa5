"""The live view of one session: ``agilegs view URL --session ID``.

:class:`SessionViewer` is a client of the service (the SDK's :class:`~agilegs.client.Client`
over HTTP, or :class:`~agilegs.client.ZenohClient`) that serves a viser page: the session's
map, its candidate pool coloured by the last selection's scores (the shortlist filled), the
anchor, the chosen view and the path of acquired views (:mod:`.canvas`), and a panel with
the method, each decision's latency breakdown, the mapper's progress and, when the caller
reports it (:meth:`SessionViewer.report_psnr`), the PSNR against views.

It follows the session: new decisions arrive by long poll (``get_decisions`` with a wait;
over HTTP it holds no server thread) or, with a Zenoh client, from the publication on
``agilegs/<session>/decisions``; after each round it reads the session's state and fetches
what changed (the pool and the views when the version moved, the map when the mapper
published a new one). A deleted session, a missing one, a refused token or a server that
goes away are said in the panel, and the viewer keeps trying (the scene keeps the last
state it saw) until the session is back.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np

from agilegs import schemas as m
from agilegs.client import (
    AgileGSError,
    APIError,
    AuthenticationError,
    NotFoundError,
    TransportError,
)

from .canvas import SceneCanvas
from .extra import quiet, require_viser
from .panel import Chart, add_display_controls, latency_markdown, page_url

__all__ = ["SessionViewer"]

log = logging.getLogger(__name__)

HISTORY = 500
"""Decisions kept for the latency chart."""


class _Reload(Exception):
    """The session's decision log started again (a restart, or the session created again)."""


class _Closed(Exception):
    """The decisions feed says the session was deleted."""


class _PollFeed:
    """Decisions by long poll: ``get_decisions(after=..., wait=...)`` (HTTP or Zenoh query)."""

    def __init__(self, client: Any, session: str) -> None:
        self.client = client
        self.session = session
        self.after = 0
        self.epoch: str | None = None

    def reset(self) -> list[m.SelectResponse]:
        """Start over: every decision the server holds, oldest first."""
        out = self.client.get_decisions(self.session, after=0, limit=1000)
        self.epoch, self.after = out.epoch, out.next_after
        return [e.decision for e in out.decisions]

    def take(self, wait: float) -> list[m.SelectResponse]:
        try:
            out = self.client.get_decisions(self.session, after=self.after, wait=wait)
        except NotFoundError:
            if self.epoch is None:
                raise
            self.epoch = None  # the feed it followed is gone: the session was deleted
            raise _Closed() from None
        if out.epoch != self.epoch:
            raise _Reload("the session's decisions start again (server restarted, or the "
                          "session was created again)")
        self.after = out.next_after
        if out.missed:
            log.info("viewer: %d decision(s) of %s no longer held by the server", out.missed,
                     self.session)
        if out.closed:
            raise _Closed()
        return [e.decision for e in out.decisions]

    def close(self) -> None:
        pass


class _SubscriptionFeed(_PollFeed):
    """Decisions as Zenoh publishes them on ``agilegs/<session>/decisions``."""

    def __init__(self, client: Any, session: str) -> None:
        super().__init__(client, session)
        self.inbox: queue.Queue[m.SelectResponse] = queue.Queue()
        self.sub = client.subscribe_decisions(session, self.inbox.put)

    def reset(self) -> list[m.SelectResponse]:
        while not self.inbox.empty():  # what the history below holds already
            self.inbox.get_nowait()
        return super().reset()

    def take(self, wait: float) -> list[m.SelectResponse]:
        out: list[m.SelectResponse] = []
        try:
            out.append(self.inbox.get(timeout=wait) if wait > 0 else self.inbox.get_nowait())
            while True:
                out.append(self.inbox.get_nowait())
        except queue.Empty:
            return out

    def close(self) -> None:
        try:
            self.sub.undeclare()
        except Exception:  # already gone with the client's session
            log.debug("viewer: undeclare failed", exc_info=True)


def _map_key(info: m.SessionInfo) -> tuple[Any, ...]:
    g = info.gaussians
    published = info.mapper.published_steps if info.mapper is not None else None
    return (g.count, tuple(g.means_min or ()), tuple(g.means_max or ()), published)


class SessionViewer:
    """A live browser view of one session (see the module docstring).

    Args:
        client: a :class:`~agilegs.client.Client` or :class:`~agilegs.client.ZenohClient`
            (the viewer uses it from its own thread; the caller closes it).
        session: the session id to follow (it may not exist yet).
        host, port: where the page is served (``http://host:port``).
        where: the server, as the panel names it.
        decisions: ``"poll"`` (``get_decisions`` long polls) or ``"zenoh"`` (the client's
            decision subscription; a ZenohClient).
        max_frustums: most candidate frustums drawn.
    """

    def __init__(self, client: Any, session: str, *, host: str = "127.0.0.1", port: int = 8080,
                 where: str = "", decisions: Literal["poll", "zenoh"] = "poll",
                 max_frustums: int = 2000) -> None:
        viser = require_viser()
        self.client = client
        self.session = session
        self.where = where or "the server"
        self.host, self.port = host, port
        with quiet("start"):
            self.server = viser.ViserServer(host=host, port=port, verbose=False,
                                            label=f"agilegs · {session}")
        self.port = int(self.server.get_port())  # viser takes the next port if it is taken
        self.canvas = SceneCanvas(self.server, max_frustums=max_frustums)
        try:
            self.feed = (_SubscriptionFeed(client, session) if decisions == "zenoh"
                         else _PollFeed(client, session))
        except BaseException:
            with quiet("stop"):
                self.server.stop()
            raise
        self.decisions: list[m.SelectResponse] = []
        self.psnr: list[tuple[float, float]] = []
        self.info: m.SessionInfo | None = None
        self.problem: str | None = None
        self.loaded = False  # the session was loaded once
        self._need_load = True
        self._version = -1
        self._map_key: tuple[Any, ...] = ()
        self._view_ids: tuple[int, ...] | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._build_panel()

    @property
    def url(self) -> str:
        return page_url(self.host, self.port)

    # ------------------------------------------------------------------ the panel
    def _build_panel(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large", show_share_button=False)
        gui.add_markdown(f"**agilegs** · session `{self.session}` on {self.where}")
        self.status_md = gui.add_markdown("connecting…")
        with gui.add_folder("Session"):
            self.session_md = gui.add_markdown("–")
        with gui.add_folder("Last decision"):
            self.decision_md = gui.add_markdown("no decision yet")
        with gui.add_folder("Mapper"):
            self.mapper_md = gui.add_markdown("–")
        self.charts = gui.add_folder("Charts")
        self.latency_chart = Chart(gui, "selection latency per decision (ms)", "decision",
                                   ["total"], container=self.charts)
        self.psnr_chart = Chart(gui, "test PSNR against views (dB)", "views", ["PSNR"],
                                container=self.charts)
        with gui.add_folder("Display"):
            self.controls = add_display_controls(gui, self.canvas)

    def _set_status(self, text: str) -> None:
        self.status_md.content = text

    def report_psnr(self, views: int | float, psnr: float) -> None:
        """Add a point to the PSNR chart (the caller measures it, e.g. the demo's robot)."""
        self.psnr.append((float(views), float(psnr)))
        self.psnr_chart.set([v for v, _ in self.psnr], [[p for _, p in self.psnr]])

    # ------------------------------------------------------------------ following
    def step(self, wait: float = 0.0) -> bool:
        """One round: (re)load the session when needed, take the decisions that came (waiting
        up to ``wait`` s for one), fetch what changed. False when something is wrong; the
        panel then says what, and the next round tries again."""
        sid = self.session
        try:
            if self._need_load:
                self._load()
                self._need_load = False
                self.loaded = True
            for d in self.feed.take(wait):
                self._on_decision(d)
            self._sync(self.client.get_session(sid))
        except _Reload as exc:
            self._need_load = True
            self._set_status(f"reloading: {exc}")
            return False
        except _Closed:
            return self._trouble(f"the session `{sid}` was deleted on {self.where}; this page "
                                 "shows its last state and waits for a session of that id")
        except NotFoundError as exc:  # it may come: a viewer can start before the robot
            return self._trouble(f"no session `{sid}` on {self.where} ({exc.message}); waiting "
                                 "for it", level=logging.INFO)
        except AuthenticationError:
            return self._trouble(f"{self.where} refused the viewer's token (401): start it "
                                 "with the server's --token")
        except TransportError as exc:
            return self._trouble(f"{self.where} does not answer ({exc}); retrying")
        except APIError as exc:
            return self._trouble(f"{self.where} refused a request: {exc}")
        except AgileGSError as exc:
            return self._trouble(f"{self.where} answered something unexpected: {exc}")
        except Exception as exc:  # a bug here must not end the page
            log.exception("viewer: following %s failed", sid)
            return self._trouble(f"viewer error ({type(exc).__name__}: {exc}); retrying")
        self.problem = None
        last = f", the last #{len(self.decisions)}" if self.decisions else ""
        self._set_status(f"following live · {len(self.decisions)} decision(s){last} · "
                         f"updated {time.strftime('%H:%M:%S')}")
        return True

    def _trouble(self, text: str, level: int = logging.WARNING) -> bool:
        self._need_load = True
        if text != self.problem:  # said once, not at every retry
            log.log(level, "viewer: %s", text)
        self.problem = text
        self._set_status(f"**⚠ {text}**")
        return False

    def _load(self) -> None:
        sid = self.session
        info = self.client.get_session(sid)
        self.canvas.set_camera(info.intrinsics.model_dump())
        history = self.feed.reset()
        pool = self.client.get_pool(sid)
        views = self.client.list_views(sid)
        gauss = self.client.get_gaussians(sid)
        arrays = gauss.to_numpy()
        cameras = np.concatenate([pool.matrices().reshape(-1, 4, 4),
                                  _stack([v.pose.to_matrix() for v in views.views])])
        self.canvas.fit(cameras, arrays["means"])
        self.canvas.set_map(arrays)
        self._map_key = _map_key(info)
        self.canvas.set_pool(pool.ids(), pool.matrices())
        self._view_ids = None
        self._show_views(views)
        self.decisions = []
        if history:
            self.decisions = history[-HISTORY:-1]
            self._on_decision(history[-1])
        else:
            self.canvas.set_decision(None, None)
            self.canvas.color_pool({}, [])
            self.decision_md.content = "no decision yet"
            self._chart_latency()
        self._version = info.version
        self._show_info(info)

    def _sync(self, info: m.SessionInfo) -> None:
        sid = self.session
        if info.version != self._version:
            pool = self.client.get_pool(sid)
            self.canvas.set_pool(pool.ids(), pool.matrices())
            self._show_views(self.client.list_views(sid))
            key = _map_key(info)
            if key != self._map_key:
                self.canvas.set_map(self.client.get_gaussians(sid).to_numpy())
                self._map_key = key
            self._version = info.version
        self._show_info(info)

    def _show_views(self, views: m.ViewsOut) -> None:
        ordered = sorted(views.views, key=lambda v: v.id)
        ids = tuple(v.id for v in ordered)
        if ids != self._view_ids:
            self.canvas.set_path([v.pose.to_matrix() for v in ordered])
            self._view_ids = ids

    def _on_decision(self, d: m.SelectResponse) -> None:
        self.decisions = (self.decisions + [d])[-HISTORY:]
        self.canvas.color_pool({s.id: s.score for s in d.scores}, [s.id for s in d.shortlist])
        self.canvas.set_decision(d.chosen.pose.to_matrix(),
                                 d.anchor.to_matrix() if d.anchor is not None else None)
        acquired = f", acquired as view {d.committed.id}" if d.committed is not None else ""
        shortlist = ", ".join(str(s.id) for s in d.shortlist) or "–"
        self.decision_md.content = (
            f"**{d.method}** chose candidate **{d.chosen.id}**{acquired}  \n"
            f"shortlist: {shortlist}  \n"
            f"anchor: {'shown (orange)' if d.anchor is not None else 'none (this method)'}"
            f" · {len(d.eligible)} eligible\n\n"
            + latency_markdown(d.latency_ms, d.core_ms, d.server_ms))
        self._chart_latency()

    def _chart_latency(self) -> None:
        totals = [d.latency_ms.get("total", float("nan")) for d in self.decisions]
        if totals:
            self.latency_chart.set(list(range(1, len(totals) + 1)), [totals])

    def _show_info(self, info: m.SessionInfo) -> None:
        self.info = info
        hidden = (f" ({self.canvas.pool_hidden} not drawn)" if self.canvas.pool_hidden
                  else "")
        self.session_md.content = (
            f"method (default) **{info.defaults.method}** · version {info.version}  \n"
            f"views **{info.num_views}** · pool **{info.pool_size}**{hidden} · "
            f"Gaussians **{info.gaussians.count}**")
        mp = info.mapper
        if mp is None or not mp.enabled:
            self.mapper_md.content = "off (the map is kept as pushed)"
            return
        loss = f"{mp.last_loss:.4f}" if mp.last_loss is not None else "–"
        err = f"  \nerror: {mp.error}" if mp.error else ""
        self.mapper_md.content = (
            f"**{mp.state}** · steps {mp.steps} (published {mp.published_steps}, pending "
            f"{mp.pending_steps})  \nloss {loss} · Gaussians {mp.num_gaussians} · "
            f"views trained {mp.views}{err}")

    # ------------------------------------------------------------------ lifecycle
    def start(self, poll: float = 1.0) -> SessionViewer:
        """Follow the session in a background thread (a long poll of ``poll`` s per round)."""
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._loop, args=(poll,),
                                            name=f"agilegs-view-{self.session}", daemon=True)
            self._thread.start()
        return self

    def _loop(self, poll: float) -> None:
        backoff = 0.5
        while not self._stop.is_set():
            if self.step(wait=poll):
                backoff = 0.5
            elif self.problem is not None:  # else: a reload, at once
                self._stop.wait(backoff)
                backoff = min(backoff * 2, 5.0)

    def wait_until(self, predicate: Any, timeout: float = 30.0) -> bool:
        """Poll ``predicate(self)`` until it holds (True) or ``timeout`` s pass (False)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate(self):
                return True
            time.sleep(0.05)
        return False

    def close(self) -> None:
        """Stop following and stop the page's server (the client stays open)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=30)
            self._thread = None
        self.feed.close()
        with quiet("stop"):
            self.server.stop()

    def __enter__(self) -> SessionViewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _stack(poses: Sequence[np.ndarray]) -> np.ndarray:
    return np.stack(poses) if poses else np.zeros((0, 4, 4))
