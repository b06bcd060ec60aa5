"""COVER (coverage-based view selection), the geometric baseline, as its code does it
(chengine/nbv_gym: ``nbv_gym/util/coverage.py``, ``nbv_gym/view_selector.py``).

- Every Gaussian keeps G = 128 direction bins, the Fibonacci lattice of ``fibonacci_sphere``
  (z = 1 - 2(i + 0.5)/G, azimuth 2π·frac(i/φ), φ the golden ratio).
- The bins are recomputed at every selection from all acquired views
  (``update_view_coverage_for_frustum``): a view fills, for each Gaussian its gsplat
  projection keeps (``fully_fused_projection`` with ``eps2d=0.3``, ``near_plane=0.01``,
  ``far_plane=1e10``, ``radius_clip=3.0``, no opacity), the bin nearest the direction from the
  camera centre to the Gaussian's mean. That projection keeps a Gaussian when its 2D
  covariance (with the 0.3 low-pass) is positive definite, its depth lies within the near
  and far planes, its per-axis radius ``ceil(3.33 sqrt(Σ_aa))`` exceeds ``radius_clip`` on at
  least one axis, and that box overlaps the image. So Gaussians of projected radius ≤ 3 px
  fill no bin: at low resolution most small Gaussians never count as covered.
- A candidate's coverage of Gaussian i (``compute_coverage_per_gaussian``) is the largest
  (cos(d_i, b_g) + 1)/2 over its filled bins g, d_i the direction from the candidate's
  centre to the mean (0 when no bin is filled). It is composited as an extra image channel of
  the candidate's render, and the candidate's score is that channel's mean over the pixels
  with alpha > 0; the lowest score (the view that sees the least-covered surface) wins.
- Embodied mode: COVER restricts the choice to the K = 5 remaining frames whose camera
  centres are nearest the last acquired view's (a KD-tree query): ``SelectConfig``'s
  ``embodied_metric="position"``, the default, does the same for every method.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..camera import Camera, Intrinsics
from ..cancel import checkpoint
from ..gaussians import GaussianMap
from ..projection import project_map
from ..rasterize import render
from .base import MethodResult, SelectionContext, register, timed
from .common import argmax_first

#: gsplat's fixed box extent (3.33 standard deviations) when no opacity is given
BOX_EXTENT = 3.33
#: the far plane of COVER's projection
FAR_PLANE = 1e10


def fibonacci_sphere(
    num: int = 128, *, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
) -> Tensor:
    """``num`` nearly uniform unit directions on the sphere [num, 3]: COVER's Fibonacci
    lattice, z_i = 1 - 2(i + 0.5)/num and azimuth 2π·frac(i/φ)."""
    if num < 1:
        raise ValueError(f"num must be >= 1, got {num}")
    i = torch.arange(num, dtype=torch.float64)
    golden = (1.0 + math.sqrt(5.0)) / 2.0
    z = 1.0 - 2.0 * (i + 0.5) / num
    r = torch.sqrt((1.0 - z * z).clamp_min(0.0))
    theta = 2.0 * math.pi * torch.remainder(i / golden, 1.0)
    out = torch.stack([r * torch.cos(theta), r * torch.sin(theta), z], dim=1)
    return out.to(dtype=dtype, device=device)


def _unit(x: Tensor) -> Tensor:
    return x / (x.norm(dim=-1, keepdim=True) + 1e-10)


@torch.no_grad()
def kept_by_projection(
    gmap: GaussianMap, camera: Camera, *, near: float = 0.01, radius_clip: float = 3.0
) -> Tensor:
    """Which Gaussians COVER's gsplat projection keeps in ``camera`` [N] (bool): positive
    definite 2D covariance, depth in (near, far), per-axis radius ceil(3.33 sqrt(Σ_aa)) above
    ``radius_clip`` on some axis, and the box overlapping the image."""
    p = project_map(gmap.detach(), camera, near=near)
    c00, c01, c11 = p.cov2d.unbind(-1)
    det = c00 * c11 - c01 * c01
    z = p.depths
    rx = torch.ceil(BOX_EXTENT * torch.sqrt(c00.clamp_min(0)))
    ry = torch.ceil(BOX_EXTENT * torch.sqrt(c11.clamp_min(0)))
    u, v = p.means2d[:, 0], p.means2d[:, 1]
    on_image = (u + rx > 0) & (u - rx < camera.width) & (v + ry > 0) & (v - ry < camera.height)
    big = (rx > radius_clip) | (ry > radius_clip)
    return (z > near) & (z < FAR_PLANE) & (det > 0) & big & on_image


def filled_bins(
    gmap: GaussianMap,
    acquired: Tensor,
    intrinsics: Intrinsics,
    bins: Tensor,
    *,
    near: float = 0.01,
    radius_clip: float = 3.0,
) -> Tensor:
    """Which direction bins of each Gaussian the acquired cameras filled [N, G] (bool).

    Args:
        gmap: the map (N Gaussians).
        acquired: acquired camera poses [A, 4, 4].
        intrinsics: their intrinsics.
        bins: unit bin directions [G, 3].
    """
    means = gmap.means.detach()
    filled = torch.zeros(means.shape[0], bins.shape[0], dtype=torch.bool, device=means.device)
    for pose in acquired.detach().to(means.dtype):
        cam = Camera(c2w=pose, intrinsics=intrinsics)
        idx = torch.nonzero(kept_by_projection(gmap, cam, near=near,
                                               radius_clip=radius_clip)).squeeze(1)
        if idx.numel() == 0:
            continue
        d = _unit(means[idx] - pose[:3, 3])  # camera centre -> Gaussian
        filled[idx, torch.argmax(d @ _unit(bins).T, dim=1)] = True
    return filled


def gaussian_coverage(means: Tensor, cam_pos: Tensor, bins: Tensor, filled: Tensor,
                      chunk: int = 1 << 16) -> Tensor:
    """c_i = max over filled bins of (cos(d_i, b_g) + 1) / 2, 0 without filled bins [N];
    d_i the direction from the candidate's centre to the mean.

    Args:
        means: [N, 3]; cam_pos: candidate centre [3]; bins: [G, 3]; filled: [N, G] bool.
        chunk: Gaussians per block (the [block, G] scores are the memory: a block at a time).
    """
    out = torch.empty(means.shape[0], dtype=means.dtype, device=means.device)
    pos = cam_pos.to(means.dtype)
    for s in range(0, means.shape[0], chunk):
        d = _unit(means[s:s + chunk] - pos)
        score = (d @ bins.T + 1.0) * 0.5
        score.masked_fill_(~filled[s:s + chunk], -1.0)
        out[s:s + chunk] = score.amax(dim=1).clamp_min(0.0)
    return out


def cover_scores(
    gmap: GaussianMap,
    candidates: Tensor,
    intrinsics: Intrinsics,
    acquired: Tensor,
    *,
    num_bins: int = 128,
    resolution: int | None = None,
    near: float = 0.01,
    radius_clip: float = 3.0,
) -> Tensor:
    """COVER's score of each candidate [D] (lower = less covered = better).

    Args:
        gmap: the current map.
        candidates: candidate poses [D, 4, 4].
        intrinsics: the candidates' intrinsics.
        acquired: acquired poses [A, 4, 4] (A may be 0: every score is then 0).
        num_bins: direction bins per Gaussian (128, as COVER's code).
        resolution: render width in pixels (None: the candidates' own).
        radius_clip: the projection's radius clip in pixels of the acquired views.
    """
    means = gmap.means.detach()
    bins = fibonacci_sphere(num_bins, dtype=means.dtype, device=means.device)
    filled = filled_bins(gmap, acquired.detach(), intrinsics, bins, near=near,
                         radius_clip=radius_clip)
    intr = intrinsics
    if resolution is not None:
        intr = intrinsics.scaled(
            resolution, max(1, round(resolution * intrinsics.height / intrinsics.width))
        )
    g = gmap.detach()
    scores = []
    with torch.no_grad():
        for pose in candidates.detach().to(means.dtype):
            checkpoint()
            c = gaussian_coverage(means, pose[:3, 3], bins, filled)
            out = render(g, Camera(c2w=pose, intrinsics=intr), features=c[:, None], near=near)
            assert out.features is not None
            hit = out.alpha > 0
            if bool(hit.any()):
                scores.append(out.features[..., 0][hit].mean())
            else:  # sees nothing: nothing to cover, never preferred
                scores.append(torch.tensor(math.inf, dtype=means.dtype, device=means.device))
    return torch.stack(scores)


class CoverMethod:
    name = "cover"
    uses_information = False

    def __call__(self, ctx: SelectionContext) -> MethodResult:
        dt = ctx.gmap.dtype
        lat: dict[str, float] = {}
        with timed(lat, "scoring"):
            acq = ctx.acquired if ctx.acquired is not None else torch.zeros(0, 4, 4, dtype=dt)
            cs = cover_scores(
                ctx.gmap,
                ctx.eligible_poses,
                ctx.intrinsics,
                acq.to(dt),
                num_bins=ctx.config.cover_bins,
                resolution=ctx.config.cover_resolution,
                near=ctx.config.scoring.near,
                radius_clip=ctx.config.cover_radius_clip,
            )
        scores = {v: float(s) for v, s in zip(ctx.eligible, cs)}
        return MethodResult(index=ctx.eligible[argmax_first(-cs)], scores=scores, latency_ms=lat)


register(CoverMethod())
