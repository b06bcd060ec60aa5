"""Small helpers the selection methods share."""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import Tensor

from ..camera import Camera, Intrinsics
from ..cancel import checkpoint
from ..gaussians import GaussianMap
from ..information import fisher_diag

__all__ = ["argmax_first", "eig_scores_keeping_best"]


def argmax_first(values: Tensor) -> int:
    """Index of the largest value, the lowest index on ties (NaN never wins)."""
    v = torch.nan_to_num(values.to(torch.float64), nan=-math.inf)
    return int(torch.argmax(v))


def _rank(value: float) -> float:
    """``value`` as :func:`argmax_first` ranks it."""
    return float(torch.nan_to_num(torch.tensor(value, dtype=torch.float64), nan=-math.inf))


def eig_scores_keeping_best(
    gmap: GaussianMap,
    h_acc: Mapping[str, Tensor],
    poses: Tensor,
    intrinsics: Intrinsics,
    *,
    fields: tuple[str, ...],
    background: Tensor | None = None,
) -> tuple[Tensor, dict[str, Tensor] | None]:
    """phi(v) = sum_q log(1 + H_v,qq / Hhat_qq) of every pose [V, 4, 4] -> [V] (float64), the
    same arithmetic as :func:`~agilegs.service.nbv.information.eig_scores`, and the diagonal
    Fisher H_v (blocks ``fields``) of the pose :func:`argmax_first` picks, kept from its pass
    (None when ``poses`` is empty): what acquiring that view adds to Hhat."""
    g = gmap.detach()
    inv = {f: h_acc[f].detach().to(g.dtype).reciprocal() for f in fields}
    out = torch.empty(poses.shape[0], dtype=torch.float64)
    best: dict[str, Tensor] | None = None
    best_rank = -math.inf
    with torch.no_grad():
        for i, pose in enumerate(poses.detach().to(g.dtype)):
            checkpoint()
            h = fisher_diag(
                g, Camera(c2w=pose, intrinsics=intrinsics), fields=fields, background=background
            )
            total = 0.0
            for f in fields:
                total += float(h[f].mul(inv[f]).log1p_().sum(dtype=torch.float64))
            out[i] = total
            rank = _rank(total)
            if best is None or rank > best_rank:
                best, best_rank = h, rank
    return out, best
