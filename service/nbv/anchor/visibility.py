"""Visibility by transmittance: how much of a Gaussian a virtual camera sees through the map.

The renderer composites front to back: a Gaussian's pixels carry the transmittance T of
everything in front of it (its Fisher information scales with T²; the proxy uses T, see
notebook/2026-11-23-transmittance-visibility.md). The anchor needs T for a few thousand
Gaussians at hundreds of poses per selection, so it does not rasterize: :class:`OpacityMaps`
builds, per pose, a coarse *deep opacity map* (a frustum grid
of ``cells`` x ``cells`` screen cells by ``bins`` depth slices) of the map's optical depth,
and reads each Gaussian's transmittance from it:

- every occluder j (the map's Gaussians, or a seeded subset drawn in proportion to their
  mass and reweighted) carries the optical depth τ_j = -log(1 - min(o_j, 0.99)) of a ray
  through its centre over its projected area, a mass m_j = τ_j · 2π A_j (f/z_j)² in
  pixels² (A_j the mean of its scales' pairwise products: its mean cross-section); the mass
  divided by a cell's area is that cell's coverage-weighted optical depth, deposited in the
  cell and depth slice of the occluder's centre and spread by a [1, 2, 1]² blur in the screen;
- the optical depth in front of Gaussian i is the cumulated depth of its cell (bilinear in
  the screen, linear within a slice) up to one slice in front of its centre (its own slab,
  and so its own mass, is not in front of it); T_i = exp(-τ).

The depth slices span the map's robust extent around the pose (1.1 times its 98% radius on
either side of its centre's depth); occluders nearer fall in the first slice, farther ones in
the last. Building the maps is a few scatter-adds per pose (no marching), batched over every
pose of a call; the read is differentiable in the pose (through the Gaussian's screen
position and depth), the deposit is not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..camera import Intrinsics
from ..gaussians import GaussianMap

__all__ = ["OpacityMaps"]


@dataclass
class OpacityMaps:
    """The occluders of a map, ready to be splatted into per-pose deep opacity maps.

    Attributes:
        means: occluder centres [M, 3].
        mass: τ_j · 2π A_j · fx · fy, the pixel mass at unit depth [M] (already reweighted
            when the occluders are a subset).
        intrinsics: the virtual camera.
        center: the map's robust centre [3]; half_depth: the slices' half range (1.1 r98).
        cells: screen cells per image side; bins: depth slices.
    """

    means: Tensor
    mass: Tensor
    intrinsics: Intrinsics
    center: Tensor
    half_depth: float
    cells: int = 16
    bins: int = 32

    @classmethod
    @torch.no_grad()
    def build(
        cls,
        gmap: GaussianMap,
        intrinsics: Intrinsics,
        center: Tensor,
        radius: float,
        *,
        cells: int = 16,
        bins: int = 32,
        max_occluders: int = 0,
        generator: torch.Generator | None = None,
    ) -> OpacityMaps:
        """The occluders of ``gmap`` (all, or ``max_occluders`` drawn in proportion to their
        mass and reweighted, unbiased); ``center`` [3] and ``radius`` (the map's robust centre
        and 98% radius) set the depth slices."""
        g = gmap.detach()
        op = g.opacities.clamp(max=0.99)
        s = torch.exp(g.log_scales)
        area = (s[:, 0] * s[:, 1] + s[:, 0] * s[:, 2] + s[:, 1] * s[:, 2]) / 3.0
        mass = -torch.log1p(-op) * 2.0 * math.pi * area * (intrinsics.fx * intrinsics.fy)
        means = g.means
        n = mass.shape[0]
        total = float(mass.sum())
        if 0 < max_occluders < n and total > 0:
            draws = torch.multinomial(mass.cpu().double(), max_occluders, replacement=True,
                                      generator=generator)
            idx, counts = torch.unique(draws, return_counts=True)
            idx = idx.to(means.device)
            means = means[idx]
            mass = counts.to(mass) * (total / max_occluders)
        return cls(means=means, mass=mass, intrinsics=intrinsics, center=center.detach(),
                   half_depth=1.1 * float(radius), cells=int(cells), bins=int(bins))

    def transmittance(self, c2w: Tensor, points: Tensor,
                      cam_points: tuple[Tensor, Tensor, Tensor] | None = None) -> Tensor:
        """T of each point seen from each pose: poses [B, 4, 4], points [P, 3] -> [B, P].

        ``cam_points``: the points' camera coordinates (x, y, z), each [B, P], when the caller
        has them (differentiable in the poses through them).
        """
        b = c2w.shape[0]
        dt, dev = c2w.dtype, c2w.device
        k = self.intrinsics
        g, nb = self.cells, self.bins
        rot = c2w[:, :3, :3]
        t = c2w[:, :3, 3]
        # depth slices around the map's centre, per pose
        zc = ((self.center.to(dt) - t.detach()) * rot.detach()[:, :, 2]).sum(-1)  # [B]
        z0 = zc - self.half_depth
        dz = 2.0 * self.half_depth / nb
        with torch.no_grad():
            ox, oy, oz = _to_camera(self.means.to(dt), rot.detach(), t.detach())  # [B, M]
            ozs = oz.clamp_min(1e-6)
            cu = ((k.fx * ox / ozs + k.cx) / k.width * g).floor()  # the occluder's cell
            cv = ((k.fy * oy / ozs + k.cy) / k.height * g).floor()
            cell_px = (k.width / g) * (k.height / g)
            val = self.mass.to(dt)[None, :] / (ozs * ozs) / cell_px  # optical depth per cell
            slab = ((oz - z0[:, None]) / dz).floor().clamp(0, nb - 1).long()
            ok = (oz > 1e-6) & (cu >= 0) & (cu < g) & (cv >= 0) & (cv < g)
            val = torch.where(ok, val, torch.zeros_like(val))
            idx = ((torch.arange(b, device=dev)[:, None] * nb + slab) * g
                   + cv.clamp(0, g - 1).long()) * g + cu.clamp(0, g - 1).long()
            grid = torch.zeros(b * nb * g * g, dtype=dt, device=dev)
            grid.index_add_(0, idx.reshape(-1), val.reshape(-1))
            # a [1, 2, 1]² blur within each slice stands for the bilinear spread of the mass
            grid = _blur(_blur(grid.reshape(b * nb, g, g), 1), 2)
            # optical depth at the far end of each slice, a zero slice in front: [B, nb + 1]
            cum = grid.reshape(b, nb, g, g).cumsum(1)
            cum = torch.cat([torch.zeros_like(cum[:, :1]), cum], dim=1)[:, None]
        if cam_points is None:
            cam_points = _to_camera(points.to(dt), rot, t)
        x, y, z = cam_points
        zs = z.clamp_min(1e-6)
        # cell-centre coordinates in [-1, 1] (align_corners): cell i's centre is i
        su = ((k.fx * x / zs + k.cx) / k.width * g - 0.5) / max(g - 1, 1) * 2.0 - 1.0
        sv = ((k.fy * y / zs + k.cy) / k.height * g - 0.5) / max(g - 1, 1) * 2.0 - 1.0
        # one slice in front of the point: its own slab is not in front of it
        depth = ((z - z0[:, None]) / dz - 1.0).clamp(0.0, float(nb)) / nb * 2.0 - 1.0
        coords = torch.stack([su.clamp(-1, 1), sv.clamp(-1, 1), depth], dim=-1)
        tau = torch.nn.functional.grid_sample(
            cum, coords[:, None, None], mode="bilinear", padding_mode="border",
            align_corners=True,
        ).reshape(b, -1)
        return torch.exp(-tau)


def _blur(x: Tensor, dim: int) -> Tensor:
    """A [1, 2, 1] / 4 blur along ``dim`` (zero outside)."""
    out = 0.5 * x
    n = x.shape[dim]
    out.narrow(dim, 1, n - 1).add_(0.25 * x.narrow(dim, 0, n - 1))
    out.narrow(dim, 0, n - 1).add_(0.25 * x.narrow(dim, 1, n - 1))
    return out


def _to_camera(points: Tensor, rot: Tensor, t: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Camera coordinates x, y, z (each [B, P]) of world points [P, 3] for c2w rotations
    [B, 3, 3] and centres [B, 3]."""
    b = rot.shape[0]
    rt = rot.transpose(1, 2)
    cam = torch.matmul(rt.reshape(3 * b, 3), points.T.contiguous()).reshape(b, 3, -1)
    cam = cam - torch.matmul(rt, t.unsqueeze(-1))
    return cam[:, 0], cam[:, 1], cam[:, 2]
