"""Spread: farthest-point sampling over the pool. Each pick is the eligible candidate farthest
from every acquired view (max over the candidates of the distance to the nearest acquired
view), under the SE(3) distance of embodied mode's ``"se3"`` metric and the anchor's K-nearest
shortlist: camera-centre distance plus ``context.rot_weight`` (``scoring.rot_weight``, by
default the pool's median camera distance from the map's centre) times the rotation angle.
Ties go to the lowest pool index; with no acquired view every candidate is at +inf and the
first eligible one is chosen. It reads neither the map's Gaussians nor Hhat."""

from __future__ import annotations

from ..spread import nearest_distances
from .base import MethodResult, SelectionContext, register, timed
from .common import argmax_first


class SpreadMethod:
    name = "spread"
    uses_information = False
    uses_map = False

    def __call__(self, ctx: SelectionContext) -> MethodResult:
        lat: dict[str, float] = {}
        with timed(lat, "scoring"):
            dist = nearest_distances(ctx.eligible_poses, ctx.acquired, ctx.rot_weight)
        scores = {v: float(d) for v, d in zip(ctx.eligible, dist)}
        return MethodResult(index=ctx.eligible[argmax_first(dist)], scores=scores,
                            latency_ms=lat)


register(SpreadMethod())
