"""The full-pool expected information gain: phi(v) = sum_q log(1 + H_v,qq / Hhat_qq) of every
eligible candidate (one exact ``fisher_diag`` pass each), argmax. The ceiling AGILE-GS+
approximates: AGILE-GS+ reranks its shortlist by this same score. With
``SelectConfig.objective = "target"`` both maximise the target views' variance reduction
instead (:mod:`.objective`). ``SelectConfig.spread_filter`` scores only the candidates farthest
from the acquired views (spread broken by the objective)."""

from __future__ import annotations

import torch

from ..spread import nearest_distances
from .base import MethodResult, SelectionContext, register, timed
from .common import argmax_first
from .objective import objective_scores_keeping_best


class FullEIGMethod:
    name = "full_eig"
    uses_information = True

    def __call__(self, ctx: SelectionContext) -> MethodResult:
        lat: dict[str, float] = {}
        scored = ctx.eligible
        details: dict[str, object] = {}
        with timed(lat, "scoring"):
            if ctx.config.spread_filter > 0:
                with timed(lat, "scoring.spread"):
                    scored = far_candidates(ctx, ctx.config.spread_filter)
                details["spread_kept"] = len(scored)
            poses = ctx.pool[torch.as_tensor(scored, dtype=torch.long)]
            phi, chosen = objective_scores_keeping_best(ctx, poses, lat, "scoring")
        scores = {v: float(p) for v, p in zip(scored, phi)}
        return MethodResult(index=scored[argmax_first(phi)], scores=scores, latency_ms=lat,
                            chosen_information=chosen, details=details)


def far_candidates(ctx: SelectionContext, fraction: float) -> list[int]:
    """The eligible candidates whose distance to the nearest acquired view is at least
    ``fraction`` of the largest such distance (all of them without an acquired view)."""
    dist = nearest_distances(ctx.eligible_poses, ctx.acquired, ctx.rot_weight)
    if not bool(torch.isfinite(dist).all()):
        return list(ctx.eligible)
    bar = fraction * float(dist.max())
    return [v for v, d in zip(ctx.eligible, dist.tolist()) if d >= bar]


register(FullEIGMethod())
