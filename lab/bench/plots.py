"""PNG plots of ``agilegs bench run`` (matplotlib, Agg backend).

- ``psnr_vs_views.png``: test PSNR against the number of acquired views, one panel per scene,
  one line per method (mean over seeds, the band spans ± one std);
- ``latency.png``: the selection latency of every event, per method, on a log axis (boxes
  over all events of all scenes and seeds, the mean marked);
- ``trajectories_<scene>.png``: the acquisition trajectories in 3D, one panel per method
  (first seed): the pool's camera centres in grey, the initial views as black squares, the
  selected views joined in acquisition order and coloured from early (dark) to late (light).
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from agilegs.lab.bench.scene_model import BenchScene
from agilegs.lab.bench.variants import display_name  # noqa: E402

log = logging.getLogger(__name__)

__all__ = ["write_plots", "plot_psnr_vs_views", "plot_latency", "plot_trajectories"]

COLORS = {
    "random": "#7f7f7f",
    "spread": "#17becf",
    "fisherrf": "#1f77b4",
    "cover": "#2ca02c",
    "full_eig": "#9467bd",
    "agile": "#ff7f0e",
    "agile_plus": "#d62728",
    "agile@paper": "#ffbb78",
    "agile_plus@paper": "#ff9896",
}


def _name(key: str) -> str:
    return display_name(key)


def _color(key: str, i: int) -> str:
    if key in COLORS:
        return COLORS[key]
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    return str(matplotlib.colors.to_hex(cycle[(i + 5) % len(cycle)]))


def _keys(results: Mapping[str, Any]) -> list[str]:
    """Variant keys with results: the five methods in the paper's order, then the others."""
    have = [v["key"] for v in results["variants"] if v["key"] in results["summary"]]
    main = [k for k in COLORS if k in have]
    return main + [k for k in have if k not in main]


def plot_psnr_vs_views(results: Mapping[str, Any], path: Path) -> Path:
    """Test PSNR against the number of views, per scene and method."""
    scenes = list(results["scenes"])
    n = max(len(scenes), 1)
    cols = min(n, 3)
    rows = math.ceil(n / cols)
    n_keys = max(len(_keys(results)), 1)
    ncol = min(n_keys, 3 * cols)
    leg_h = 0.3 * math.ceil(n_keys / ncol)
    height = 3.6 * rows + leg_h
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, height), squeeze=False)
    for ax, s in zip(axes.flat, scenes):
        for i, k in enumerate(_keys(results)):
            summ = results["scenes"][s]["summary"].get(k)
            if not summ or not summ["curve"]:
                continue
            x = [c["views"] for c in summ["curve"]]
            y = [c["psnr_mean"] for c in summ["curve"]]
            sd = [c["psnr_std"] or 0.0 for c in summ["curve"]]
            ls = "-" if k in COLORS else "--"
            ax.plot(x, y, ls, marker="o", ms=3, color=_color(k, i), label=_name(k))
            ax.fill_between(x, [a - b for a, b in zip(y, sd)], [a + b for a, b in zip(y, sd)],
                            color=_color(k, i), alpha=0.12, lw=0)
        ax.set_title(s)
        ax.set_xlabel("views")
        ax.set_ylabel("test PSNR (dB)")
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(scenes):]:
        ax.axis("off")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="lower center", ncol=ncol, fontsize="small",
                   frameon=False)
    fig.tight_layout(rect=(0, (leg_h + 0.1) / height if handles else 0, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_latency(results: Mapping[str, Any], path: Path) -> Path:
    """Per-event selection latency per method, log axis."""
    keys = _keys(results)
    data, labels, colors = [], [], []
    for i, k in enumerate(keys):
        lat = [max(e["latency_ms"]["total"], 1e-3) / 1e3
               for s in results["scenes"].values()
               for r in s["runs"].get(k, {}).values() for e in r["events"]]
        if lat:
            data.append(lat)
            labels.append(_name(k))
            colors.append(_color(k, i))
    fig, ax = plt.subplots(figsize=(max(5.0, 1.2 * len(labels) + 2), 3.8))
    if data:
        bp = ax.boxplot(data, showmeans=True, patch_artist=True, widths=0.6)
        for patch, c in zip(bp["boxes"], colors):
            patch.set_facecolor(c)
            patch.set_alpha(0.5)
        ax.set_xticks(range(1, len(labels) + 1), labels, rotation=20, ha="right")
    ax.set_yscale("log")
    ax.set_ylabel("selection latency per event (s)")
    ax.grid(axis="y", which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_trajectories(
    results: Mapping[str, Any], scene_name: str, scene: BenchScene | None, path: Path
) -> Path | None:
    """The acquisition trajectories of one scene in 3D (first seed), one panel per method."""
    runs = results["scenes"][scene_name]["runs"]
    keys = [k for k in _keys(results) if runs.get(k)]
    if not keys:
        return None
    cols = min(len(keys), 3)
    rows = math.ceil(len(keys) / cols)
    fig = plt.figure(figsize=(4.2 * cols, 4.0 * rows))
    pool = scene.pool_poses[:, :3, 3].numpy() if scene is not None else None
    legend: list[tuple[Any, str]] = []
    for j, k in enumerate(keys):
        ax = fig.add_subplot(rows, cols, j + 1, projection="3d")
        seed = sorted(runs[k], key=int)[0]
        rec = runs[k][seed]
        if pool is not None:
            ax.scatter(pool[:, 0], pool[:, 2], -pool[:, 1], s=3, c="0.75", depthshade=False,
                       label="candidate pool")
            ini = pool[rec["initial"]]
            ax.scatter(ini[:, 0], ini[:, 2], -ini[:, 1], s=22, c="k", marker="s",
                       label="initial views")
        tr = rec["trajectory"]
        xs = [p[0] for p in tr]
        ys = [p[2] for p in tr]
        zs = [-p[1] for p in tr]  # world up is -y: plot it upwards
        ax.plot(xs, ys, zs, "-", color=_color(k, j), lw=1.2, label="path")
        points = ax.scatter(xs[1:], ys[1:], zs[1:], c=range(len(xs) - 1), cmap="viridis",
                            s=18, depthshade=False, label="views chosen")
        if j == 0:
            handles, labels = ax.get_legend_handles_labels()
            legend = [(h, lab) for h, lab in zip(handles, labels, strict=True)]
        if len(xs) > 1 and j == len(keys) - 1:
            bar = fig.colorbar(points, ax=ax, shrink=0.5, pad=0.1)
            bar.set_label("event (order chosen)", fontsize="x-small")
            bar.ax.tick_params(labelsize="xx-small")
        ax.set_title(f"{_name(k)} (seed {seed})", fontsize="small")
        ax.set_xlabel("x", fontsize="x-small")
        ax.set_ylabel("z", fontsize="x-small")
        ax.set_zlabel("-y (up)", fontsize="x-small")
        ax.tick_params(labelsize="xx-small")
        if pool is not None:  # equal scale on the three axes
            span = pool.max(0) - pool.min(0)
            ax.set_box_aspect((float(span[0]), float(span[2]), float(max(span[1], 1e-3))))
    fig.suptitle(f"{scene_name}: acquisition trajectories", fontsize="medium")
    fig.tight_layout(rect=(0.0, 0.06, 1.0, 1.0))
    fig.legend([h for h, _ in legend], [lab for _, lab in legend], loc="lower center",
               ncol=len(legend), fontsize="small", frameon=False)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)


def write_plots(
    results: Mapping[str, Any], scenes: Mapping[str, BenchScene], out: Path
) -> list[Path]:
    """Write every plot into ``out``; returns the files written."""
    out.mkdir(parents=True, exist_ok=True)
    written = [
        plot_psnr_vs_views(results, out / "psnr_vs_views.png"),
        plot_latency(results, out / "latency.png"),
    ]
    for name in results["scenes"]:
        p = plot_trajectories(results, name, scenes.get(name),
                              out / f"trajectories_{_safe(name)}.png")
        if p is not None:
            written.append(p)
    return written
