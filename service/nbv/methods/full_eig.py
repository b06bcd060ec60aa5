"""The full-pool expected information gain: phi(v) = sum_q log(1 + H_v,qq / Hhat_qq) of every
eligible candidate (one exact ``fisher_diag`` pass each), argmax. The ceiling AGILE-GS+
approximates: AGILE-GS+ reranks its shortlist by this same score. With
``SelectConfig.objective = "target"`` both maximise the target views' variance reduction
instead (:mod:`.objective`)."""

from __future__ import annotations

from .base import MethodResult, SelectionContext, register, timed
from .common import argmax_first
from .objective import objective_scores_keeping_best


class FullEIGMethod:
    name = "full_eig"
    uses_information = True

    def __call__(self, ctx: SelectionContext) -> MethodResult:
        lat: dict[str, float] = {}
        with timed(lat, "scoring"):
            phi, chosen = objective_scores_keeping_best(ctx, ctx.eligible_poses, lat, "scoring")
        scores = {v: float(p) for v, p in zip(ctx.eligible, phi)}
        return MethodResult(index=ctx.eligible[argmax_first(phi)], scores=scores, latency_ms=lat,
                            chosen_information=chosen)


register(FullEIGMethod())
