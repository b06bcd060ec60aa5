"""Farthest-point sampling over camera poses, under the SE(3) distance of
:func:`~agilegs.service.nbv.se3.pose_distance` (camera-centre distance plus ``rot_weight``
world units per radian of rotation): the distance of every pose to its nearest reference pose,
and the max-min order in which a set of poses covers itself. No map and no information: poses
in, indices out.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .se3 import pose_distance

__all__ = ["farthest_point_order", "nearest_distances"]

_CHUNK = 4096
"""Poses per block of the distance computations (bounds their memory: [chunk, 4, 4] at once)."""


def nearest_distances(poses: Tensor, reference: Tensor | None, rot_weight: float) -> Tensor:
    """Distance of each pose [P, 4, 4] to its nearest reference pose [R, 4, 4], float64 [P];
    +inf for every pose when there is no reference (None or R = 0)."""
    p = poses.detach().to(torch.float64)
    out = torch.full((p.shape[0],), math.inf, dtype=torch.float64, device=p.device)
    if reference is None or reference.shape[0] == 0 or p.shape[0] == 0:
        return out
    ref = reference.detach().to(device=p.device, dtype=torch.float64)
    for r in ref:
        for start in range(0, p.shape[0], _CHUNK):
            block = p[start:start + _CHUNK]
            d = pose_distance(block, r.expand_as(block), rot_weight)
            torch.minimum(out[start:start + _CHUNK], d, out=out[start:start + _CHUNK])
    return out


def farthest_point_order(
    poses: Tensor,
    reference: Tensor | None,
    rot_weight: float,
    count: int,
) -> list[int]:
    """``count`` indices into ``poses`` [P, 4, 4] by greedy farthest-point sampling: each pick
    is the pose farthest from every reference pose [R, 4, 4] and every earlier pick (max over
    the poses of the min distance), the lowest index on ties (so with no reference, the first
    pick is pose 0). Picks are distinct; ``count`` is capped at P."""
    n = int(poses.shape[0])
    count = max(0, min(int(count), n))
    if count == 0:
        return []
    dist = nearest_distances(poses, reference, rot_weight)
    p = poses.detach().to(device=dist.device, dtype=torch.float64)
    taken = torch.zeros(n, dtype=torch.bool, device=dist.device)
    picks: list[int] = []
    for _ in range(count):
        score = torch.where(taken, torch.full_like(dist, -math.inf), dist)
        i = int(torch.argmax(score))  # the first of the largest: lowest index on ties
        picks.append(i)
        taken[i] = True
        d = pose_distance(p, p[i].expand_as(p), rot_weight)
        torch.minimum(dist, d, out=dist)
    return picks
