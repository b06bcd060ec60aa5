"""The replay of a benchmark run: ``agilegs view --run DIR``.

:class:`RunReplay` reads the run records an ``agilegs bench run --out DIR`` folder holds
(``DIR/runs/<scene>/<variant>/seed<k>.json``; a run still in progress shows the records
written so far) and serves a viser page: pick the scene, the method and the seed, then step
event by event (a slider, or play). Event 0 shows the initial views and the pool; event k
the k-th selection: the chosen view (red), the shortlist (filled) and the candidates
coloured by the method's scores, the anchor (orange) where the method has one, and the path
of the views acquired so far (blue); the panel shows the event's latency breakdown, how
redundant the pick (and the anchor) are with the views already acquired (the record's
``redundancy``), and the run's PSNR curve against views, the current event marked.

Records written before the pool's poses were added to them (``pool_poses``, ``scores`` and
``anchor`` per event) are replayed from their camera centres (``trajectory``): the path as
points and a line, no frustums.
"""

from __future__ import annotations

import json
import logging
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .canvas import PATH, SceneCanvas
from .extra import quiet, require_viser
from .panel import Chart, add_display_controls, latency_markdown, page_url

__all__ = ["RunRecord", "RunReplay", "load_runs"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunRecord:
    """One (scene, variant, seed) run of ``bench run`` and where it was read from."""

    scene: str
    variant: str
    seed: int
    path: Path
    data: dict[str, Any]

    @property
    def events(self) -> list[dict[str, Any]]:
        return list(self.data.get("events", []))

    @property
    def pool_poses(self) -> np.ndarray | None:
        """The pool's camera-to-world poses [D, 4, 4], when the record holds them."""
        poses = self.data.get("pool_poses")
        return None if poses is None else np.asarray(poses, dtype=np.float64)

    def acquired(self, event: int) -> list[int]:
        """Pool indices acquired after ``event`` selections: the initial views, then the
        chosen ones, in order."""
        initial = list(self.data.get("initial", []))
        return initial + [int(e["choice"]) for e in self.events[:event]]


def load_runs(run_dir: Path | str) -> list[RunRecord]:
    """Every readable run record under ``run_dir/runs`` (sorted by scene, variant, seed);
    ValueError when there is none."""
    root = Path(run_dir)
    if not root.is_dir():
        raise ValueError(f"{root} is not a folder")
    out = []
    for path in sorted((root / "runs").glob("*/*/seed*.json")):
        try:
            data = json.loads(path.read_text())
            seed = int(data.get("seed", path.stem.removeprefix("seed")))
            out.append(RunRecord(str(data.get("scene", path.parent.parent.name)),
                                 str(data.get("variant", path.parent.name)), seed, path, data))
        except (OSError, ValueError) as exc:
            log.warning("replay: skipping %s (%s)", path, exc)
    if not out:
        raise ValueError(f"no run records under {root / 'runs'}: is it the --out folder of "
                         "agilegs bench run?")
    return sorted(out, key=lambda r: (r.scene, r.variant, r.seed))


class RunReplay:
    """The replay page of a ``bench run`` folder (see the module docstring).

    Args:
        run_dir: the ``--out`` folder of ``agilegs bench run``.
        host, port: where the page is served.
    """

    def __init__(self, run_dir: Path | str, *, host: str = "127.0.0.1", port: int = 8080
                 ) -> None:
        viser = require_viser()
        self.run_dir = Path(run_dir)
        self.runs = load_runs(self.run_dir)
        self.host = host
        with quiet("start"):
            self.server = viser.ViserServer(host=host, port=port, verbose=False,
                                            label=f"agilegs · {self.run_dir.name}")
        self.port = int(self.server.get_port())
        self.canvas = SceneCanvas(self.server)
        self.lock = threading.RLock()
        self.record = self.runs[0]
        self.event = 0
        self.trajectory: Any = None
        self._playing = threading.Event()
        self._stop = threading.Event()
        self._build_panel()
        self.select(self.record.scene, self.record.variant, self.record.seed)
        self._player = threading.Thread(target=self._play, name="agilegs-replay", daemon=True)
        self._player.start()

    @property
    def url(self) -> str:
        return page_url(self.host, self.port)

    # ------------------------------------------------------------------ the panel
    def _build_panel(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large", show_share_button=False)
        gui.add_markdown(f"**agilegs** · replay of `{self.run_dir}` ({len(self.runs)} runs)")
        scenes = sorted({r.scene for r in self.runs})
        self.scene_dd = gui.add_dropdown("scene", scenes, initial_value=self.record.scene)
        self.variant_dd = gui.add_dropdown("method", self._variants(self.record.scene),
                                           initial_value=self.record.variant)
        self.seed_dd = gui.add_dropdown("seed", self._seeds(self.record.scene,
                                                            self.record.variant),
                                        initial_value=str(self.record.seed))
        self.slider = gui.add_slider("event", min=0, max=max(1, len(self.record.events)),
                                     step=1, initial_value=0)
        buttons = gui.add_button_group("step", ("◀ previous", "next ▶", "play / pause"))
        self.run_md = gui.add_markdown("–")
        self.event_md = gui.add_markdown("–")
        self.charts = gui.add_folder("PSNR")
        self.psnr_chart = Chart(gui, "test PSNR against views (dB)", "views",
                                ["PSNR", "this event"], container=self.charts)
        with gui.add_folder("Display"):
            self.controls = add_display_controls(gui, self.canvas)

        @self.scene_dd.on_update
        def _(_: Any) -> None:
            scene = self.scene_dd.value
            variants = self._variants(scene)
            variant = self.variant_dd.value if self.variant_dd.value in variants else variants[0]
            seeds = self._seeds(scene, variant)
            self.select(scene, variant, int(seeds[0]))

        @self.variant_dd.on_update
        def _(_: Any) -> None:
            seeds = self._seeds(self.scene_dd.value, self.variant_dd.value)
            seed = self.seed_dd.value if self.seed_dd.value in seeds else seeds[0]
            self.select(self.scene_dd.value, self.variant_dd.value, int(seed))

        @self.seed_dd.on_update
        def _(_: Any) -> None:
            self.select(self.scene_dd.value, self.variant_dd.value, int(self.seed_dd.value))

        @self.slider.on_update
        def _(_: Any) -> None:
            self.show_event(int(self.slider.value))

        @buttons.on_click
        def _(_: Any) -> None:
            if buttons.value.startswith("◀"):
                self.show_event(self.event - 1)
            elif buttons.value.startswith("next"):
                self.show_event(self.event + 1)
            elif self._playing.is_set():
                self._playing.clear()
            else:
                self._playing.set()

    def _variants(self, scene: str) -> list[str]:
        return sorted({r.variant for r in self.runs if r.scene == scene})

    def _seeds(self, scene: str, variant: str) -> list[str]:
        return [str(r.seed) for r in self.runs if r.scene == scene and r.variant == variant]

    # ------------------------------------------------------------------ showing
    def select(self, scene: str, variant: str, seed: int) -> None:
        """Show the run (scene, variant, seed) from its event 0."""
        with self.lock:
            rec = next((r for r in self.runs if (r.scene, r.variant, r.seed)
                        == (scene, variant, seed)), None)
            if rec is None:
                raise ValueError(f"no run {scene} / {variant} / seed {seed} in {self.run_dir}")
            self.record = rec
            for dd, value, options in ((self.scene_dd, scene, None),
                                       (self.variant_dd, variant, self._variants(scene)),
                                       (self.seed_dd, str(seed), self._seeds(scene, variant))):
                if options is not None and tuple(dd.options) != tuple(options):
                    dd.options = options
                if dd.value != value:
                    dd.value = value
            self.slider.max = max(1, len(rec.events))
            intr = rec.data.get("intrinsics")
            if intr is not None:
                self.canvas.set_camera(intr)
            poses = rec.pool_poses
            if poses is not None:
                self.canvas.fit(poses)
            elif rec.data.get("trajectory"):
                self.canvas.fit(_centres_as_poses(np.asarray(rec.data["trajectory"])),
                                orient=False)
            d = rec.data
            lat = d.get("latency_ms", {}).get("mean")
            note = ("" if poses is not None else "  \n*this record has no pool poses (written "
                    "before the viewer): the path is drawn from its camera centres*")
            self.run_md.content = (
                f"**{d.get('method', variant)}** · `{variant}` · seed {seed} · profile "
                f"{d.get('profile', '?')}  \nfinal PSNR **{_num(d.get('psnr'))} dB** · SSIM "
                f"{_num(d.get('ssim'), 4)} · {len(rec.events)} events · mean selection "
                f"{_num(lat, 1)} ms · path length {_num(d.get('path_length'))}"
                f"{_redundancy_line(d.get('redundancy'))}{note}")
            self.show_event(0)

    def show_event(self, event: int) -> None:
        """Show the run after ``event`` selections (clamped to the run's events)."""
        with self.lock:
            rec = self.record
            event = max(0, min(int(event), len(rec.events)))
            self.event = event
            if int(self.slider.value) != event:
                self.slider.value = event
            poses = rec.pool_poses
            taken = rec.acquired(event)
            ev = rec.events[event - 1] if event > 0 else None
            if poses is not None:
                self._clear_trajectory()
                remaining = [i for i in range(len(poses)) if i not in set(taken)]
                self.canvas.set_pool(remaining, poses[remaining])
                self.canvas.set_path([poses[i] for i in taken])
                if ev is None:
                    self.canvas.color_pool({}, [])
                    self.canvas.set_decision(None, None)
                else:
                    scores = {int(i): float(v) for i, v in ev.get("scores", [])}
                    self.canvas.color_pool(scores, [int(i) for i in ev.get("shortlist", [])])
                    anchor = ev.get("anchor")
                    self.canvas.set_decision(poses[int(ev["choice"])],
                                             None if anchor is None else np.asarray(anchor))
            else:
                self._draw_trajectory(event)
            self.event_md.content = self._event_text(event, ev)
            self._chart(event)

    def _event_text(self, event: int, ev: dict[str, Any] | None) -> str:
        rec = self.record
        if ev is None:
            return (f"**event 0 of {len(rec.events)}**: the {len(rec.data.get('initial', []))} "
                    f"initial views (blue) and the pool")
        shortlist = ", ".join(str(i) for i in ev.get("shortlist", [])) or "–"
        red = (rec.data.get("redundancy") or {}).get("events") or []
        angles = ""
        if event - 1 < len(red):
            r = red[event - 1]
            angles = f"  \npick → nearest acquired view {_num(r.get('pick_angle_deg'), 1)}°"
            if r.get("anchor_angle_deg") is not None:
                angles += (f" · anchor → nearest acquired view "
                           f"{_num(r.get('anchor_angle_deg'), 1)}°")
            if r.get("psi_ratio") is not None:
                angles += f" · ψ(anchor) / ψ(best candidate) {_num(r.get('psi_ratio'), 2)}"
        return (f"**event {event} of {len(rec.events)}** (step {ev.get('step', '?')}, "
                f"{ev.get('views_before', '?')} views before): chose view **{ev['choice']}**  \n"
                f"shortlist: {shortlist} · {ev.get('eligible', '?')} eligible · "
                f"{ev.get('num_gaussians', '?')} Gaussians · Ĥ recomputed in "
                f"{_num(ev.get('information_ms'), 1)} ms{angles}\n\n"
                + latency_markdown(ev.get("latency_ms", {})))

    def _chart(self, event: int) -> None:
        curve = self.record.data.get("curve", [])
        if not curve:
            return
        views = [float(c["views"]) for c in curve]
        psnr = [float(c["psnr"]) if c.get("psnr") is not None else float("nan") for c in curve]
        now = len(self.record.acquired(event))
        mark = [p if v == now else float("nan") for v, p in zip(views, psnr, strict=True)]
        self.psnr_chart.set(views, [psnr, mark])

    def _draw_trajectory(self, event: int) -> None:
        """The path from the record's camera centres (records without pool poses)."""
        self._clear_trajectory()
        # the trajectory holds the last initial view's centre, then one per event
        upto = np.asarray(self.record.data.get("trajectory", []), dtype=np.float32)[: event + 1]
        if len(upto):
            self.trajectory = [self.canvas.scene.add_point_cloud(
                "/trajectory/points", points=upto, colors=PATH,
                point_size=self.canvas.point_size * 3, point_shape="circle")]
            if len(upto) >= 2:
                seg = np.stack([upto[:-1], upto[1:]], axis=1)
                self.trajectory.append(self.canvas.scene.add_line_segments(
                    "/trajectory/line", points=seg, colors=PATH, thickness=3.0,
                    thickness_units="screen"))

    def _clear_trajectory(self) -> None:
        for h in self.trajectory or []:
            h.remove()
        self.trajectory = None

    # ------------------------------------------------------------------ playing
    def _play(self) -> None:
        while not self._stop.wait(1.0):
            if self._playing.is_set():
                with self.lock:
                    nxt = self.event + 1 if self.event < len(self.record.events) else 0
                self.show_event(nxt)

    def close(self) -> None:
        self._stop.set()
        self._player.join(timeout=5)
        with quiet("stop"):
            self.server.stop()

    def __enter__(self) -> RunReplay:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _redundancy_line(red: dict[str, Any] | None) -> str:
    """The run's redundancy figures (``bench run``'s ``redundancy``), or nothing."""
    if not red:
        return ""
    return (f"  \npicks → nearest acquired view {_num(red.get('pick_angle_mean_deg'), 1)}° "
            f"(mean) · the pool's final gap {_num(red.get('final_gap_deg'), 1)}°")


def _num(value: Any, digits: int = 2) -> str:
    try:
        return f"{float(value):.{digits}f}"
    except (TypeError, ValueError):
        return "–"


def _centres_as_poses(centres: np.ndarray) -> np.ndarray:
    """Identity-rotation poses [N, 4, 4] at camera centres [N, 3] (only for sizing)."""
    out = np.tile(np.eye(4), (len(centres), 1, 1))
    out[:, :3, 3] = centres
    return out
