"""A view's worth on the renders of the views of interest (the ``target`` objective).

With the diagonal Fisher, the predicted variance of a target render's pixel (and channel) p
is sum_q J_pq^2 / Hhat_q (J the render's Jacobian w.r.t. the map's parameters); summed over
the pixels of the target views it is sum_q T_q / Hhat_q, T = sum over the targets of their
diagonal Fisher diag(J_t^T J_t). Acquiring a view v adds H_v to Hhat, so the targets' summed
variance falls by

    gain(v) = sum_q T_q H_v,q / (Hhat_q (Hhat_q + H_v,q)),

which counts a parameter as much as the targets' pixels depend on it: a parameter no target
sees is worth nothing, however little Hhat knows of it (the EIG sum_q log(1 + H_v,q/Hhat_q)
values every parameter alike). T is computed once per selection from a farthest-point
subsample of the targets (:func:`target_subsample`), never per candidate, on images smaller
than the candidates' (:func:`target_intrinsics`): T's scale does not change which view is best.

:func:`target_gain_bruteforce` is the reference: the targets' per-pixel Jacobians by autograd
(one backward per pixel and channel) and the variance before and after the view's brute-force
Fisher, summed pixel by pixel.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import Tensor

from .camera import Camera, Intrinsics
from .cancel import checkpoint
from .gaussians import GaussianMap
from .information import fisher_diag, fisher_diag_bruteforce
from .rasterize import render
from .spread import farthest_point_order

__all__ = [
    "target_gain",
    "target_gain_bruteforce",
    "target_information",
    "target_intrinsics",
    "target_size",
    "target_scores_keeping_best",
    "target_subsample",
]


def target_subsample(targets: Tensor, rot_weight: float, count: int) -> list[int]:
    """``count`` of the target poses [T, 4, 4] spread over them: their farthest-point order
    (SE(3) distance, ``rot_weight`` world units per radian), first target first."""
    return farthest_point_order(targets, None, rot_weight, count)


def target_size(width: int, height: int, scale: float) -> tuple[int, int]:
    """The targets' image size: ``width`` and ``height`` times ``scale``, rounded, at least
    one pixel each (the size itself at scale 1)."""
    if scale >= 1.0:
        return width, height
    return max(1, round(width * scale)), max(1, round(height * scale))


def target_intrinsics(intrinsics: Intrinsics, scale: float) -> Intrinsics:
    """The targets' images: ``intrinsics`` at :func:`target_size` (the same field of view),
    ``intrinsics`` itself at scale 1."""
    if scale >= 1.0:
        return intrinsics
    return intrinsics.scaled(*target_size(intrinsics.width, intrinsics.height, scale))


def target_information(
    gmap: GaussianMap,
    targets: Tensor,
    intrinsics: Intrinsics,
    *,
    fields: tuple[str, ...],
    background: Tensor | None = None,
) -> dict[str, Tensor]:
    """T = sum over the target poses [T, 4, 4] of their diagonal Fisher (blocks ``fields``),
    in the map's dtype: one ``fisher_diag`` pass per target."""
    g = gmap.detach()
    out = {f: torch.zeros_like(getattr(g, f)) for f in fields}
    with torch.no_grad():
        for pose in targets.detach().to(g.dtype):
            checkpoint()
            h = fisher_diag(g, Camera(c2w=pose, intrinsics=intrinsics), fields=fields,
                            background=background)
            for f in fields:
                out[f] += h[f]
    return out


def target_gain(h_view: Mapping[str, Tensor], h_acc: Mapping[str, Tensor],
                t_info: Mapping[str, Tensor]) -> float:
    """sum_q T_q H_v,q / (Hhat_q (Hhat_q + H_v,q)) over the blocks of ``t_info`` (float64
    accumulation): the fall of the targets' summed predicted variance when the view whose
    Fisher is ``h_view`` is acquired."""
    total = 0.0
    for f, t in t_info.items():
        hv = h_view[f].to(torch.float64)
        ha = h_acc[f].to(device=hv.device, dtype=torch.float64)
        total += float((t.to(torch.float64) * hv / (ha * (ha + hv))).sum())
    return total


def target_scores_keeping_best(
    gmap: GaussianMap,
    h_acc: Mapping[str, Tensor],
    poses: Tensor,
    intrinsics: Intrinsics,
    t_info: Mapping[str, Tensor],
    *,
    fields: tuple[str, ...],
    background: Tensor | None = None,
) -> tuple[Tensor, dict[str, Tensor] | None]:
    """:func:`target_gain` of every pose [V, 4, 4] -> [V] (float64), one exact Fisher pass
    each, and the Fisher of the best (the first of the largest; NaN never wins), kept from
    its pass (None when ``poses`` is empty)."""
    g = gmap.detach()
    out = torch.empty(poses.shape[0], dtype=torch.float64)
    best: dict[str, Tensor] | None = None
    best_value = -math.inf
    with torch.no_grad():
        for i, pose in enumerate(poses.detach().to(g.dtype)):
            checkpoint()
            h = fisher_diag(g, Camera(c2w=pose, intrinsics=intrinsics), fields=fields,
                            background=background)
            value = target_gain(h, h_acc, {f: t_info[f] for f in fields})
            out[i] = value
            rank = -math.inf if math.isnan(value) else value
            if best is None or rank > best_value:
                best, best_value = h, rank
    return out, best


def target_gain_bruteforce(
    gmap: GaussianMap,
    h_acc: Mapping[str, Tensor],
    view: Tensor,
    targets: Tensor,
    intrinsics: Intrinsics,
    *,
    background: Tensor | None = None,
) -> float:
    """Reference of :func:`target_gain` over every block (slow): the targets' renders
    differentiated pixel by pixel and channel by channel (rows J_p of the Jacobian), the view's
    Fisher from :func:`~agilegs.service.nbv.information.fisher_diag_bruteforce`, and
    sum_p sum_q J_pq^2 (1 / Hhat_q - 1 / (Hhat_q + H_v,q))."""
    h_view = fisher_diag_bruteforce(gmap, Camera(c2w=view, intrinsics=intrinsics),
                                    background=background)
    names = [k for k, _ in gmap.items()]
    before = {k: 1.0 / h_acc[k].detach().to(torch.float64) for k in names}
    after = {k: 1.0 / (h_acc[k].detach().to(torch.float64) + h_view[k].to(torch.float64))
             for k in names}
    total = 0.0
    for pose in targets:
        leaves = {k: v.detach().clone().requires_grad_(True) for k, v in gmap.items()}
        g = GaussianMap(**leaves)
        rgb = render(g, Camera(c2w=pose, intrinsics=intrinsics), background=background,
                     backward="autograd").rgb.reshape(-1)
        for i in range(rgb.numel()):
            if not rgb[i].requires_grad:
                continue
            grads = torch.autograd.grad(rgb[i], [leaves[k] for k in names], retain_graph=True)
            for k, gr in zip(names, grads):
                j2 = gr.detach().to(torch.float64) ** 2
                total += float((j2 * (before[k] - after[k])).sum())
    return total
