"""COVER (coverage-based view selection), the geometric baseline, as its code does it.

Every Gaussian keeps 128 direction bins (a Fibonacci sphere). A bin is filled when some
acquired camera sees the Gaussian (its mean lies in the camera's frustum) from a direction
whose nearest bin it is; directions point from the Gaussian to the camera centre. For a
candidate, each Gaussian's coverage is ``c_i = max over filled bins g of (cos(d_i, b_g) + 1)/2``
with d_i the direction from the Gaussian to the candidate (0 where no bin is filled: never
seen). c is composited as an extra image channel of the candidate's render, and the
candidate's score is the mean of that channel over pixels with alpha > 0: the lowest score
(the view that sees the least-covered surface) wins.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..camera import Camera, Intrinsics
from ..coverage import frustum_visibility
from ..gaussians import GaussianMap
from ..rasterize import render
from .base import MethodResult, SelectionContext, register, timed
from .common import argmax_first


def fibonacci_sphere(
    num: int = 128, *, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
) -> Tensor:
    """``num`` nearly uniform unit directions on the sphere [num, 3] (Fibonacci lattice)."""
    if num < 1:
        raise ValueError(f"num must be >= 1, got {num}")
    i = torch.arange(num, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / num
    r = torch.sqrt((1.0 - z * z).clamp_min(0.0))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    out = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=1)
    return out.to(dtype=dtype, device=device)


def _unit(x: Tensor) -> Tensor:
    return x / x.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def filled_bins(
    means: Tensor,
    acquired: Tensor,
    intrinsics: Intrinsics,
    bins: Tensor,
    *,
    near: float = 0.01,
) -> Tensor:
    """Which direction bins of each Gaussian the acquired cameras filled.

    Args:
        means: Gaussian centres [N, 3].
        acquired: acquired camera poses [A, 4, 4].
        intrinsics: their intrinsics (frustum test).
        bins: unit bin directions [G, 3].

    Returns:
        Bool [N, G].
    """
    n = means.shape[0]
    filled = torch.zeros(n, bins.shape[0], dtype=torch.bool, device=means.device)
    if acquired.shape[0] == 0:
        return filled
    vis = frustum_visibility(means, acquired.to(means.dtype), intrinsics, near=near)  # [A, N]
    for a in range(acquired.shape[0]):
        idx = torch.nonzero(vis[a]).squeeze(1)
        if idx.numel() == 0:
            continue
        d = _unit(acquired[a, :3, 3].to(means.dtype) - means[idx])
        g = torch.argmax(d @ bins.T, dim=1)
        filled[idx, g] = True
    return filled


def gaussian_coverage(means: Tensor, cam_pos: Tensor, bins: Tensor, filled: Tensor) -> Tensor:
    """c_i = max over filled bins of (cos(d_i, b_g) + 1) / 2, 0 without filled bins [N].

    Args:
        means: [N, 3]; cam_pos: candidate centre [3]; bins: [G, 3]; filled: [N, G] bool.
    """
    d = _unit(cam_pos.to(means.dtype) - means)
    score = (d @ bins.T + 1.0) * 0.5
    score = torch.where(filled, score, torch.full_like(score, -1.0))
    return score.amax(dim=1).clamp_min(0.0)


def cover_scores(
    gmap: GaussianMap,
    candidates: Tensor,
    intrinsics: Intrinsics,
    acquired: Tensor,
    *,
    num_bins: int = 128,
    resolution: int | None = None,
    near: float = 0.01,
) -> Tensor:
    """COVER's score of each candidate [D] (lower = less covered = better).

    Args:
        gmap: the current map.
        candidates: candidate poses [D, 4, 4].
        intrinsics: the candidates' intrinsics.
        acquired: acquired poses [A, 4, 4] (A may be 0: every score is then 0).
        num_bins: direction bins per Gaussian (128, as COVER's code).
        resolution: render width in pixels (None: the candidates' own).
    """
    means = gmap.means.detach()
    bins = fibonacci_sphere(num_bins, dtype=means.dtype, device=means.device)
    filled = filled_bins(means, acquired.detach(), intrinsics, bins, near=near)
    intr = intrinsics
    if resolution is not None:
        intr = intrinsics.scaled(
            resolution, max(1, round(resolution * intrinsics.height / intrinsics.width))
        )
    g = gmap.detach()
    scores = []
    with torch.no_grad():
        for pose in candidates.detach().to(means.dtype):
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
            )
        scores = {v: float(s) for v, s in zip(ctx.eligible, cs)}
        return MethodResult(index=ctx.eligible[argmax_first(-cs)], scores=scores, latency_ms=lat)


register(CoverMethod())
