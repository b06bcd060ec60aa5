"""Unexplored space as information: the Gaussians a map does not have yet.

The diagonal EIG counts the parameters of the Gaussians the map holds. A region no acquired
view has seen holds none, so a view of it is worth nothing to the EIG, although it is where
the map will grow (the mapper adds Gaussians where a new view's depth finds no surface, and
densifies where its image disagrees). :func:`unexplored_space` adds that region to the
proxy's sum as virtual Gaussians with the map's own density:

- a ``cells``³ grid of points spans the map's robust extent (its centre and 98% radius,
  widened by ``margin``);
- a point is *observed* when some acquired view sees it, inside its frustum and in front of
  the map's surfaces (the proxy's smooth in-frustum test times the transmittance from the
  view); its unexplored fraction is ``1 - max over the acquired views``;
- the points that are mostly unexplored stand for Gaussians the map lacks: each is a virtual
  Gaussian of the map's median size, never observed (Hhat = lambda: the model's prior rate),
  expected to hold as many Gaussians as an observed cell of the grid does (the Gaussians whose
  centres fall in observed cells over the number of observed cells).

Two refinements are options, off by default (they measured worse on the benchmark's scenes):
``shells`` > 1 takes that density per radial shell, from the observed cells at the point's
distance from the map's centre (none in a shell with no observed cell), so that a corner of
the grid beyond the map is worth nothing; ``count_inside=False`` leaves out the points the
map's occupied cells enclose on all six axis directions (:func:`enclosed`).

A candidate that sees unexplored points through the map (the transmittance, so that the
inside of a seen object stays hidden) gains what a view of as many new Gaussians would; the
anchor's ascent and the pool's ranking see it like the rest of the proxy's sum.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..cancel import checkpoint
from ..candidates import scene_center_radius
from ..gaussians import GaussianMap
from .proxy import ProxyPsi

__all__ = ["UnexploredSpace", "enclosed", "radial_shells", "shell_densities", "unexplored_space"]


@dataclass
class UnexploredSpace:
    """Virtual Gaussians for the unexplored part of the map's extent.

    Attributes:
        means: the unexplored grid points kept [U, 3].
        cov: their covariance, isotropic at the map's median scale [U, 3, 3].
        weight: expected Gaussians each stands for, times its unexplored fraction [U].
        unexplored_fraction: the unexplored share of the grid's points (0 to 1).
        density: Gaussians per observed cell, over the whole grid.
        shell_density: Gaussians per observed cell of each radial shell [shells] (what an
            unexplored point of that shell is expected to hold).
    """

    means: Tensor
    cov: Tensor
    weight: Tensor
    unexplored_fraction: float
    density: float
    shell_density: Tensor


@torch.no_grad()
def unexplored_space(
    gmap: GaussianMap,
    acquired: Tensor,
    seer: ProxyPsi,
    *,
    cells: int = 16,
    margin: float = 0.1,
    threshold: float = 0.5,
    max_points: int = 1024,
    chunk: int = 16,
    shells: int = 1,
    count_inside: bool = True,
    generator: torch.Generator | None = None,
    share: float = 1.0,
    extent: tuple[Tensor, float] | None = None,
) -> UnexploredSpace:
    """The unexplored part of ``gmap``'s extent seen from the acquired poses [A, 4, 4].

    Args:
        gmap: the map.
        acquired: the acquired views' poses [A, 4, 4].
        seer: a proxy whose in-frustum test and visibility (camera, near plane, edge,
            transmittance) judge what a pose sees; its samples are not used.
        cells: grid points per axis.
        margin: the grid spans the map's 98% radius times ``1 + margin``.
        threshold: a point counts as unexplored above this unexplored fraction.
        max_points: at most this many points are kept (drawn in proportion to their
            weight, seeded, and reweighted: the sum's expectation is unchanged).
        chunk: acquired poses evaluated at once.
        shells: radial shells of the expected density (1: one density for the whole grid).
        count_inside: also count the points the map encloses (:func:`enclosed`: the inside of its
            surfaces, which no view will see).
        generator: seeds the subsample.
        share: how many of the map's Gaussians each of ``gmap``'s stands for (``gmap`` a
            uniform sample of the map: its counts per cell are scaled by it).
        extent: the map's centre [3] and 98% radius when known
            (:func:`~agilegs.service.nbv.candidates.scene_center_radius` of its means).
    """
    dt = gmap.dtype
    dev = gmap.means.device
    means = gmap.means.detach().to(dt)
    centre, radius = scene_center_radius(means) if extent is None else extent
    half = radius * (1.0 + margin)
    axis = torch.linspace(-half, half, cells, dtype=dt, device=dev)
    gx, gy, gz = torch.meshgrid(axis, axis, axis, indexing="ij")
    points = torch.stack([gx, gy, gz], dim=-1).reshape(-1, 3) + centre.to(dt)
    probe = ProxyPsi(means=points, cov=torch.zeros(points.shape[0], 3, 3, dtype=dt, device=dev),
                     weight=torch.ones(points.shape[0], dtype=dt, device=dev),
                     intrinsics=seer.intrinsics, near=seer.near, edge=seer.edge,
                     occluders=seer.occluders, occ_grid=seer.occ_grid,
                     occ_tests=seer.occ_tests, grid=seer.grid)
    observed = torch.zeros(points.shape[0], dtype=dt, device=dev)
    poses = acquired.detach().to(dt)
    for i in range(0, poses.shape[0], chunk):
        checkpoint()
        observed = torch.maximum(observed, probe.seen(poses[i : i + chunk]).amax(0))
    unexplored = (1.0 - observed).clamp(0, 1)
    # the map's density: Gaussians whose centres fall in observed cells, per observed cell
    step = 2.0 * half / max(cells - 1, 1)
    ijk = torch.round((means - (centre.to(dt) - half)) / step).long()
    inside = ((ijk >= 0) & (ijk < cells)).all(1)
    flat = (ijk[inside, 0] * cells + ijk[inside, 1]) * cells + ijk[inside, 2]
    per_cell = torch.zeros(points.shape[0], dtype=dt, device=dev).index_add_(
        0, flat, torch.full((flat.shape[0],), float(share), dtype=dt, device=dev))
    seen_cells = unexplored <= threshold
    n_seen = int(seen_cells.sum())
    density = float(per_cell[seen_cells].sum()) / n_seen if n_seen else 0.0
    shell = radial_shells(points, centre.to(dt), half, shells)
    shell_density = shell_densities(shell, seen_cells, per_cell, shells)
    candidates = unexplored > threshold
    if not count_inside:
        candidates &= ~enclosed(per_cell.reshape(cells, cells, cells) > 0).reshape(-1)
    keep = torch.nonzero(candidates).squeeze(1)
    weight = shell_density[shell[keep]] * unexplored[keep]
    if keep.numel() > max_points and float(weight.sum()) > 0:
        total = float(weight.sum())
        draws = torch.multinomial(weight.cpu().double(), max_points, replacement=True,
                                  generator=generator)
        uniq, counts = torch.unique(draws, return_counts=True)
        keep = keep[uniq.to(dev)]
        weight = counts.to(device=dev, dtype=dt) * (total / max_points)
    nonzero = weight > 0
    keep, weight = keep[nonzero], weight[nonzero]
    scale = torch.exp(gmap.log_scales.detach().to(dt)).median()
    cov = (scale * scale) * torch.eye(3, dtype=dt, device=dev).expand(keep.numel(), 3, 3)
    return UnexploredSpace(means=points[keep], cov=cov.clone(), weight=weight,
                           unexplored_fraction=float(unexplored.gt(threshold).to(dt).mean()),
                           density=density, shell_density=shell_density)


def enclosed(occupied: Tensor) -> Tensor:
    """The empty cells of a 3D occupancy grid [X, Y, Z] (bool) that occupied cells bound on
    all six axis directions -> [X, Y, Z] (bool): the inside of a closed surface. A map seen
    from one side only is open towards the other, so nothing behind it is enclosed."""
    o = occupied.to(torch.int32)
    bounded = ~occupied
    for dim in range(3):
        before = o.cumsum(dim) - o  # occupied cells strictly before, along this axis
        after = o.flip(dim).cumsum(dim).flip(dim) - o
        bounded &= (before > 0) & (after > 0)
    return bounded


def radial_shells(points: Tensor, centre: Tensor, half: float, shells: int) -> Tensor:
    """The radial shell of each grid point [P, 3] -> [P] (long, 0 to ``shells`` - 1): equal
    widths from ``centre`` out to the grid's corner (``half`` * sqrt(3))."""
    r = (points - centre).norm(dim=1) / (half * 3.0**0.5)
    return (r * shells).floor().long().clamp(0, max(shells, 1) - 1)


def shell_densities(shell: Tensor, seen: Tensor, per_cell: Tensor, shells: int) -> Tensor:
    """Gaussians per observed cell of each shell [shells]: ``per_cell`` [P] summed over the
    observed points (``seen`` [P], bool) of each ``shell`` [P], over their number; 0 for a
    shell without an observed point (no view found matter at that distance: the inside of a
    seen object, the grid's corners beyond the views)."""
    n = max(int(shells), 1)
    dt = per_cell.dtype
    dev = per_cell.device
    count = torch.zeros(n, dtype=dt, device=dev).index_add_(
        0, shell[seen], torch.ones(int(seen.sum()), dtype=dt, device=dev))
    mass = torch.zeros(n, dtype=dt, device=dev).index_add_(0, shell[seen], per_cell[seen])
    return mass / count.clamp_min(1)
