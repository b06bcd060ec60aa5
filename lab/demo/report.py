"""The demo's report: the PSNR table of both methods per event, each method's mean selection
time (the first selection's kernel compile apart), where AGILE-GS+ stands against Random, and
the plot."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rich.console import Console

__all__ = ["LEVEL_DB", "METHODS", "plot", "summary"]

METHODS: tuple[tuple[str, str], ...] = (("agile_plus", "AGILE-GS+"), ("random", "Random"))


LEVEL_DB = 0.1
"""PSNR differences smaller than this are reported as level."""


def summary(console: Console, results: dict[str, Any]) -> str:
    """Print the PSNR table of both methods per event, each method's mean selection time (over
    the events after the first, the first's apart) and where AGILE-GS+ stands against Random,
    as this run measured them; returns the table and those lines as Markdown."""
    from rich.table import Table

    names = dict(METHODS)
    keys = list(results["methods"])
    table = Table(title="test PSNR (dB) per event")
    head = ["event", "views"] + [names.get(k, k) for k in keys] + (["Δ"] if len(keys) == 2
                                                                   else [])
    for h in head:
        table.add_column(h, justify="right")
    md = ["| " + " | ".join(head) + " |", "|" + "---:|" * len(head)]
    curves = [results["methods"][k]["curve"] for k in keys]
    deltas: list[tuple[int, float]] = []
    for i in range(min(len(cv) for cv in curves)):
        vals = [cv[i]["psnr"] for cv in curves]
        row = [str(i), str(curves[0][i]["views"])] + [f"{v:.2f}" for v in vals]
        if len(vals) == 2:
            row.append(f"{vals[0] - vals[1]:+.2f}")
            if i > 0:
                deltas.append((i, vals[0] - vals[1]))
        table.add_row(*row)
        md.append("| " + " | ".join(row) + " |")
    console.print(table)
    lines = []
    for k in keys:
        ev = results["methods"][k]["events"]
        if ev:
            tot = [e["latency_ms"].get("total", math.nan) for e in ev]
            # the first selection apart: it carries whatever the server had not compiled yet
            rest = tot[1:] or tot
            lines.append(f"{names.get(k, k)}: mean selection {sum(rest) / len(rest):.1f} ms "
                         + (f"over event{'s 2-' if len(ev) > 2 else ' '}{len(ev)}; the first "
                            f"{tot[0]:.1f} ms" if len(ev) > 1 else "over 1 event"))
    views = [{e["chosen"] for e in results["methods"][k]["events"]} for k in keys]
    if len(keys) == 2 and views[0] and views[0] == views[1]:
        lines.append(f"Both methods acquired the same {len(views[0])} views (the pool left no "
                     "other choice): their PSNR differs by the mapper's training alone")
    if deltas and len(keys) == 2:
        a, b = (names.get(k, k) for k in keys)
        groups = {"ahead of": [i for i, d in deltas if d >= LEVEL_DB],
                  "level with": [i for i, d in deltas if abs(d) < LEVEL_DB],
                  "behind": [i for i, d in deltas if d <= -LEVEL_DB]}
        parts = [f"{what} {b} at event{'s' if len(idx) > 1 else ''} "
                 f"{', '.join(str(i) for i in idx)}" for what, idx in groups.items() if idx]
        lines.append(f"{a} is " + "; ".join(parts) + f" (|Δ| < {LEVEL_DB} dB: level); "
                     f"last event Δ {deltas[-1][1]:+.2f} dB")
    for line in lines:
        console.print(line, soft_wrap=True)
    return "\n".join(md + [""] + lines) + "\n"


def plot(results: dict[str, Any], path: Path) -> Path:
    """PSNR against views for both methods, saved as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"agile_plus": "#d62728", "random": "#7f7f7f"}
    names = dict(METHODS)
    fig, ax = plt.subplots(figsize=(5.2, 3.6))
    for k, r in results["methods"].items():
        x = [c["views"] for c in r["curve"]]
        y = [c["psnr"] for c in r["curve"]]
        ax.plot(x, y, marker="o", ms=3, color=colors.get(k), label=names.get(k, k))
    ax.set_xlabel("views")
    ax.set_ylabel("test PSNR (dB)")
    ax.set_title(f"agilegs demo: {results.get('scene', '')}")
    ax.grid(alpha=0.3)
    ax.legend(frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
