"""The exact score a method maximises over a set of candidates, by ``SelectConfig.objective``:
``eig`` (the paper's phi = sum log(1 + H_v / Hhat)) or ``target`` (the fall of the target
views' predicted render variance, :mod:`agilegs.service.nbv.targets`). Each keeps the chosen
view's Fisher from its pass (``MethodResult.chosen_information``)."""

from __future__ import annotations

from torch import Tensor

from ..targets import (
    target_information,
    target_intrinsics,
    target_scores_keeping_best,
    target_subsample,
)
from .base import SelectionContext, timed
from .common import eig_scores_keeping_best

__all__ = ["objective_scores_keeping_best", "target_views"]


def target_views(ctx: SelectionContext) -> Tensor:
    """The poses whose Fisher makes T: ``config.target_views`` of the request's targets (else
    of the pool), a farthest-point subsample under the SE(3) distance of ``ctx.rot_weight``."""
    targets = ctx.targets if ctx.targets is not None else ctx.pool
    picks = target_subsample(targets, ctx.rot_weight, int(ctx.config.target_views))
    return targets[picks]


def objective_scores_keeping_best(
    ctx: SelectionContext, poses: Tensor, lat: dict[str, float], stage: str
) -> tuple[Tensor, dict[str, Tensor] | None]:
    """The objective of every pose [V, 4, 4] -> [V] (float64) and the Fisher of the best (the
    first of the largest). The ``target`` objective first sums the targets' Fisher T, timed
    as ``<stage>.targets`` (within ``stage``)."""
    if ctx.config.objective == "target":
        with timed(lat, f"{stage}.targets"):
            t_info = target_information(ctx.gmap, target_views(ctx),
                                        target_intrinsics(ctx.intrinsics, ctx.config.target_scale),
                                        fields=ctx.fields, background=ctx.background)
        return target_scores_keeping_best(ctx.gmap, ctx.h_acc, poses, ctx.intrinsics, t_info,
                                          fields=ctx.fields, background=ctx.background)
    return eig_scores_keeping_best(ctx.gmap, ctx.h_acc, poses, ctx.intrinsics,
                                   fields=ctx.fields, background=ctx.background)
