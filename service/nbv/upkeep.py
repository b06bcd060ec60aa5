"""The upkeep of Hhat = lambda I + sum over the acquired views of their diagonal Fisher H_v:
one view's H_v, and Hhat of a set of views on a map.

The one place both are computed: a session's acquisitions and map changes
(:mod:`agilegs.service.sessions.transitions`) and the benchmark's protocol
(:mod:`agilegs.lab.bench.protocol`) go through these functions.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch
from torch import Tensor

from .camera import Camera, Intrinsics
from .gaussians import GaussianMap
from .information import accumulate_information, fisher_diag, init_information

__all__ = ["information_of_views", "view_information"]


def view_information(gmap: GaussianMap, c2w: Tensor, intrinsics: Intrinsics,
                     background: Tensor | None = None) -> dict[str, Tensor]:
    """H_v, the exact diagonal Fisher of the view ``c2w`` [4, 4] of ``gmap`` rendered on
    ``background`` [3] (None: black), every block; zeros for an empty map."""
    if gmap.num_gaussians == 0:
        return {k: torch.zeros_like(v) for k, v in gmap.items()}
    with torch.no_grad():
        c2w = c2w.to(device=gmap.means.device, dtype=gmap.dtype)
        return fisher_diag(gmap.detach(), Camera(c2w=c2w, intrinsics=intrinsics),
                           background=background)


def information_of_views(gmap: GaussianMap, poses: Iterable[Tensor], intrinsics: Intrinsics,
                         lam: float, background: Tensor | None = None) -> dict[str, Tensor]:
    """Hhat = lambda I + sum_v H_v over the views at ``poses`` (each [4, 4], camera-to-world),
    accumulated in order."""
    h = init_information(gmap, lam)
    for c2w in poses:
        h = accumulate_information(h, view_information(gmap, c2w, intrinsics, background))
    return h
