"""The viewer's side panel pieces shared by the live view and the replay: the latency table
of a decision, line charts (viser's uPlot), the map display controls."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from contextlib import nullcontext
from typing import Any

import numpy as np

from .canvas import MAP_MODES, SceneCanvas

__all__ = ["STAGES", "Chart", "add_display_controls", "latency_markdown", "page_url"]

STAGES = ("anchor", "scoring", "leverage", "rerank", "total")
"""The selection core's stages, in the order the panel lists them."""

_COLORS = ("#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#ff7f0e")


def page_url(host: str, port: int) -> str:
    """The address a browser on this machine opens for a page served on ``host:port`` (a
    wildcard address is reached on the loopback)."""
    return f"http://{'127.0.0.1' if host in ('0.0.0.0', '::') else host}:{port}"


def _ms(value: float | None) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{value:.1f}"


def latency_markdown(latency_ms: Mapping[str, float], core_ms: float | None = None,
                     server_ms: float | None = None) -> str:
    """A markdown table of a decision's latency breakdown (ms): the core's stages, then the
    session work around it and the server's time, when known."""
    names = [s for s in STAGES if s in latency_ms] + sorted(
        k for k in latency_ms if k not in STAGES)
    rows = [f"| {k} | {_ms(latency_ms[k])} |" for k in names]
    if core_ms is not None:
        rows.append(f"| core (with the session) | {_ms(core_ms)} |")
    if server_ms is not None:
        rows.append(f"| server (arrival to answer) | {_ms(server_ms)} |")
    return "| stage | ms |\n|---|---:|\n" + "\n".join(rows)


class Chart:
    """A line chart in the panel, created on first data (uPlot needs two points to draw a
    line, it draws markers for one).

    Args:
        gui: the viser GUI API (``server.gui``).
        title: the chart's title.
        x_label, y_labels: the x axis, and one label per line.
        container: the folder it goes in (None: the panel's root).
    """

    def __init__(self, gui: Any, title: str, x_label: str, y_labels: Sequence[str],
                 container: Any = None) -> None:
        self.gui = gui
        self.container = container
        self.title = title
        self.x_label = x_label
        self.y_labels = tuple(y_labels)
        self.handle: Any = None
        self.data: tuple[np.ndarray, ...] = ()

    def set(self, x: Sequence[float], ys: Sequence[Sequence[float]]) -> None:
        """Replace the chart's data: ``x`` [n] and one [n] series per y label (NaN: gap)."""
        data = (np.asarray(x, dtype=np.float64),
                *(np.asarray(y, dtype=np.float64) for y in ys))
        self.data = data
        if self.handle is None:
            from viser import uplot

            series = (uplot.Series(label=self.x_label),
                      *(uplot.Series(label=lab, stroke=_COLORS[i % len(_COLORS)], width=2,
                                     points={"show": True, "size": 5})
                        for i, lab in enumerate(self.y_labels)))
            with self.container if self.container is not None else nullcontext():
                self.handle = self.gui.add_uplot(
                    data=data, series=series, title=self.title, aspect=1.6,
                    scales={"x": uplot.Scale(time=False, auto=True)})
        else:
            self.handle.data = data


def add_display_controls(gui: Any, canvas: SceneCanvas) -> dict[str, Any]:
    """The display controls (map as splats / points, pool and path shown) wired to
    ``canvas``; their handles by name."""
    mode = gui.add_dropdown("map as", MAP_MODES, initial_value=canvas.map_mode,
                            hint="splats need WebGL 2 and WebAssembly; points draw anywhere")
    pool = gui.add_checkbox("candidate pool", initial_value=canvas.show_pool)
    path = gui.add_checkbox("acquired path", initial_value=canvas.show_path)

    @mode.on_update
    def _(_: Any) -> None:
        canvas.set_map_mode(mode.value)

    @pool.on_update
    def _(_: Any) -> None:
        canvas.set_pool_visible(bool(pool.value))

    @path.on_update
    def _(_: Any) -> None:
        canvas.set_path_visible(bool(path.value))

    return {"map": mode, "pool": pool, "path": path}
