"""Adaptive density control of 3DGS (Kerbl et al. 2023): clone small Gaussians and split
large ones whose mean screen-space gradient is high, then prune transparent and (late in
training) oversized ones. A pure function of the parameters and the gradient statistics;
the mapper applies its plan."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from agilegs.config.mapper import MapperConfig
from agilegs.service.nbv.rotations import quat_to_rotmat

__all__ = ["Densification", "plan_densification"]

log = logging.getLogger(__name__)


@dataclass
class Densification:
    """A densify-and-prune step: the new parameters, where each new Gaussian comes from
    (``src`` [N_new] into the old ones), which are old ones kept as themselves
    (``identity`` [N_new]), and the counts of clones, splits and pruned."""

    params: dict[str, Tensor]
    src: Tensor
    identity: Tensor
    counts: dict[str, int]


@torch.no_grad()
def plan_densification(
    params: dict[str, Tensor],
    grad_accum: Tensor,
    grad_count: Tensor,
    max_radii: Tensor,
    config: MapperConfig,
    *,
    extent: float,
    step: int,
    generator: torch.Generator,
) -> Densification | None:
    """The densify-and-prune plan of the current Gaussians, or None when nothing changes.

    Args:
        params: the mapper's parameters (detached), each [N, ...].
        grad_accum: summed screen-space mean-gradient norms [N].
        grad_count: steps each Gaussian was visible [N].
        max_radii: largest screen radius seen [N].
        config: the thresholds (``densify_grad_threshold``, ``percent_dense``, ...).
        extent: the scene extent the world-space thresholds are relative to.
        step: the training step (large-Gaussian pruning starts after ``prune_large_from``).
        generator: draws the split children's positions.
    """
    c = config
    ext = extent
    p = params
    n = int(p["means"].shape[0])
    dev = p["means"].device
    dtype = p["means"].dtype
    grads = torch.where(
        grad_count > 0,
        grad_accum / grad_count.clamp_min(1).to(dtype),
        torch.zeros_like(grad_accum),
    )
    max_scale = p["log_scales"].exp().amax(dim=1)
    cand = grads >= c.densify_grad_threshold
    small = max_scale <= c.percent_dense * ext
    # cap: keep the candidates with the largest gradients that fit
    if c.max_gaussians is not None and bool(cand.any()):
        idx = cand.nonzero().squeeze(1)
        order = idx[grads[idx].argsort(descending=True)]
        cost = torch.where(small[order], 1, c.split_samples - 1)
        fits = cost.cumsum(0) <= max(0, c.max_gaussians - n)
        cand = torch.zeros_like(cand)
        cand[order[fits]] = True
    clone = cand & small
    split = cand & ~small
    n_clone, n_split = int(clone.sum()), int(split.sum())

    # kept old (not split), clones, split children: in that order
    keep_idx = (~split).nonzero().squeeze(1)
    clone_idx = clone.nonzero().squeeze(1)
    split_idx = split.nonzero().squeeze(1)
    k = c.split_samples
    child_src = split_idx.repeat(k)
    parts: dict[str, list[Tensor]] = {key: [p[key][keep_idx], p[key][clone_idx]] for key in p}
    if n_split:
        stds = p["log_scales"][child_src].exp()
        z = torch.randn(stds.shape, generator=generator, device=dev, dtype=dtype)
        rot = quat_to_rotmat(p["quats"][child_src])
        new_means = (rot @ (z * stds)[..., None])[..., 0] + p["means"][child_src]
        new_ls = p["log_scales"][child_src] - math.log(c.split_scale_divisor)
    for key in p:
        if key == "means" and n_split:
            parts[key].append(new_means)
        elif key == "log_scales" and n_split:
            parts[key].append(new_ls)
        else:
            parts[key].append(p[key][child_src])
    dens = {key: torch.cat(v) for key, v in parts.items()}
    src = torch.cat([keep_idx, clone_idx, child_src])
    identity = torch.cat(
        [
            torch.ones(keep_idx.numel(), dtype=torch.bool, device=dev),
            torch.zeros(clone_idx.numel() + child_src.numel(), dtype=torch.bool, device=dev),
        ]
    )
    # prune (on the densified set; new Gaussians have no screen-radius history)
    opac = torch.sigmoid(dens["opacity_logits"])
    prune = opac < c.prune_opacity
    if c.prune_large_from is not None and step > c.prune_large_from:
        radii = torch.zeros(src.numel(), dtype=dtype, device=dev)
        radii[: keep_idx.numel()] = max_radii[keep_idx]
        big_ws = dens["log_scales"].exp().amax(dim=1) > c.max_world_scale * ext
        prune = prune | (radii > c.max_screen_radius) | big_ws
    if bool(prune.all()) and prune.numel():
        log.warning("pruning would remove every Gaussian; keeping the most opaque one")
        prune[opac.argmax()] = False
    n_pruned = int(prune.sum())
    if n_clone == 0 and n_split == 0 and n_pruned == 0:
        return None
    keep = ~prune
    return Densification(
        params={key: v[keep] for key, v in dens.items()},
        src=src[keep],
        identity=identity[keep],
        counts={"cloned": n_clone, "split": n_split, "pruned": n_pruned},
    )
