"""The anchor's stages as the selections report them: ``latency_ms["anchor.<stage>"]``
(ms, within ``latency_ms["anchor"]``, not added to it), and ``bench run``'s table of them."""

from __future__ import annotations

import statistics
from collections.abc import Callable, Mapping
from typing import Any

ANCHOR_STAGES = ("envelope", "visibility", "rates", "unexplored", "starts", "ascent")
"""The anchor's stages, in order: the pool's envelope, the visibility (the map's sample and
the opacity maps), the model's rates (fitted over the acquired views, the new ones' terms
added to the carried ones between refits, and the importance sample), unexplored space, the
starts (the coarse psi of the pool, the full psi of the refined candidates), the ascent."""
TABLE_STAGES = ANCHOR_STAGES[:4] + ("targets",) + ANCHOR_STAGES[4:]
"""The stages of the tables: :data:`ANCHOR_STAGES` and, under the ``target`` objective only,
the samples' weighting by their information at the targets (after unexplored space)."""
RUN_STAGES = TABLE_STAGES + ("ascent.gradients", "ascent.values")
"""The same and, within the ascent, its evaluations with their gradient and of values alone."""


def anchor_split_table(results: Mapping[str, Any], keys: list[str],
                       display: Callable[[str], str]) -> list[str]:
    """``bench run``'s table of the anchor's time by stage (ms, mean over events, then over
    scenes) for the methods whose selections report it; ``display`` names a method."""
    body = []
    for k in keys:
        stages: dict[str, list[float]] = {}
        for s in results["scenes"].values():
            summ = s["summary"].get(k)
            if summ is None:
                continue
            for st, v in summ["stages_ms_mean"].items():
                stages.setdefault(st, []).append(v)
        if "anchor.ascent" not in stages:
            continue
        cells = " | ".join(
            f"{statistics.fmean(stages[f'anchor.{st}']):.1f}" if stages.get(f"anchor.{st}")
            else "–" for st in RUN_STAGES)
        body.append(f"| {display(k)} | {statistics.fmean(stages['anchor']):.1f} | {cells} |")
    if not body:
        return []
    return [
        "## Where the anchor's time goes",
        "",
        "The anchor's stages, ms per event (means over events, then scenes): the pool's "
        "envelope, the visibility (the map's sample, opacity maps), the model's rates (fitted "
        "over the acquired views), unexplored space, the targets' weighting (the `target` "
        "objective only), the starts (the coarse ψ of the pool, "
        "the full ψ of the best), the ascent, and within it the "
        "evaluations with their gradient and those of values alone.",
        "",
        "| Method | anchor | " + " | ".join(RUN_STAGES) + " |",
        "|---|---|" + "---|" * len(RUN_STAGES),
        *body,
        "",
    ]
