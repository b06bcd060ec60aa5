"""Candidate pools that look like a human capture, and the pool's and the scene's extent.

``capture_pool`` lays cameras on orbits at a few elevations around an object, in capture
order (ring after ring, azimuth increasing), with irregular spacing, a fraction of
near-duplicate frames (the person paused), and small jitter in position, aim and roll. It is
seeded, so a seed gives the same pool on every run. The benchmark, the tests and the demo
use it. (Distances between poses: ``agilegs.service.nbv.se3.pose_distance``.)
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from .camera import look_at
from .rotations import rotate_about_axis


def orbit_frame(
    center: Sequence[float] | Tensor, up: Sequence[float] | Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The orbit frame (float64): centre [3], unit up [3] and an orthonormal basis e1, e2
    (each [3]) of the plane perpendicular to up, with e2 = up x e1."""
    f64 = torch.float64
    c = torch.as_tensor(center, dtype=f64).reshape(3)
    upv = torch.as_tensor(up, dtype=f64).reshape(3)
    upv = upv / upv.norm()
    helper = torch.tensor([1.0, 0.0, 0.0], dtype=f64)
    if abs(float(helper @ upv)) > 0.9:
        helper = torch.tensor([0.0, 0.0, 1.0], dtype=f64)
    e1 = helper - (helper @ upv) * upv
    e1 = e1 / e1.norm()
    return c, upv, e1, torch.linalg.cross(upv, e1)


def capture_pool(
    center: Sequence[float] | Tensor,
    radius: float,
    num: int,
    *,
    elevations_deg: Sequence[float] = (10.0, 30.0, 50.0),
    up: Sequence[float] = (0.0, -1.0, 0.0),
    duplicate_fraction: float = 0.25,
    radius_jitter: float = 0.04,
    aim_jitter: float = 0.04,
    roll_jitter_deg: float = 2.0,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """A seeded pool of ``num`` camera-to-world poses [num, 4, 4] (OpenCV axes), capture order.

    Args:
        center: the point the capture circles [3].
        radius: nominal distance of the cameras from ``center``.
        num: number of cameras (>= 1).
        elevations_deg: elevation of each orbit above the plane through ``center``
            perpendicular to ``up``; frames are split over orbits in proportion to their
            circumference.
        up: world up direction (default -y, the Inria convention).
        duplicate_fraction: probability that a frame is a near-duplicate of the previous one
            (azimuth step of 3% of the nominal one).
        radius_jitter: relative standard deviation of each camera's distance.
        aim_jitter: standard deviation of the aim point around ``center``, relative to
            ``radius``.
        roll_jitter_deg: standard deviation of the roll about the optical axis, degrees.
        seed: seed of the generator.
    """
    if num < 1:
        raise ValueError(f"num must be >= 1, got {num}")
    if not radius > 0:
        raise ValueError(f"radius must be positive, got {radius}")
    if len(elevations_deg) < 1:
        raise ValueError("elevations_deg must name at least one orbit")
    g = torch.Generator().manual_seed(int(seed))
    f64 = torch.float64
    c, upv, e1, e2 = orbit_frame(center, up)

    elev = torch.tensor([math.radians(e) for e in elevations_deg], dtype=f64)
    weights = torch.cos(elev).clamp_min(0.2)
    counts = torch.floor(weights / weights.sum() * num).long()
    for i in range(int(num - counts.sum())):
        counts[i % len(counts)] += 1
    eyes, targets, rolls = [], [], []
    for ring, n in enumerate(counts.tolist()):
        if n == 0:
            continue
        dup = torch.rand(n, generator=g, dtype=f64) < duplicate_fraction
        step = torch.empty(n, dtype=f64).uniform_(0.5, 1.5, generator=g)
        step = torch.where(dup, 0.03 * torch.ones_like(step), step)
        step[0] = 0.0
        az = torch.cumsum(step, 0)
        span = 2 * math.pi * (1 - 1.0 / max(n, 1))
        az = az / az[-1].clamp_min(1e-9) * span if n > 1 else az
        az = az + float(torch.rand((), generator=g, dtype=f64)) * 2 * math.pi + ring * 0.7
        r = radius * (1 + radius_jitter * torch.randn(n, generator=g, dtype=f64))
        e = elev[ring] + math.radians(2.0) * torch.randn(n, generator=g, dtype=f64)
        aim = aim_jitter * radius * torch.randn(n, 3, generator=g, dtype=f64)
        roll = math.radians(roll_jitter_deg) * torch.randn(n, generator=g, dtype=f64)
        for i in range(1, n):  # a near-duplicate keeps the previous frame's jitter, +10%
            if dup[i]:
                r[i] = r[i - 1] + 0.1 * (r[i] - radius)
                e[i] = e[i - 1] + 0.1 * (e[i] - elev[ring])
                aim[i] = aim[i - 1] + 0.1 * aim[i]
                roll[i] = roll[i - 1] + 0.1 * roll[i]
        horiz = torch.cos(az)[:, None] * e1 + torch.sin(az)[:, None] * e2
        direction = torch.cos(e)[:, None] * horiz + torch.sin(e)[:, None] * upv
        eyes.append(c + r[:, None] * direction)
        targets.append(c + aim)
        rolls.append(roll)
    eye = torch.cat(eyes)
    target = torch.cat(targets)
    roll = torch.cat(rolls)
    c2w = look_at(eye, target, up=upv)
    z = c2w[:, :3, 2]
    c2w[:, :3, 0] = rotate_about_axis(c2w[:, :3, 0], z, roll)
    c2w[:, :3, 1] = rotate_about_axis(c2w[:, :3, 1], z, roll)
    return c2w.to(dtype)


def scene_center(means: Tensor) -> Tensor:
    """Robust centre of points [N, 3] (N > 0): the per-axis median [3] (the lower of the two
    middle values, as ``median(dim=0)``), by a selection on the CPU (numpy's introselect on
    each axis) instead of torch's; other devices and dtypes go to torch."""
    m = means.detach()
    if m.device.type != "cpu" or m.dtype not in (torch.float32, torch.float64) or (
            m.shape[0] == 0 or bool(torch.isnan(m).any())):
        return m.median(dim=0).values
    a = m.T.contiguous().numpy()
    k = (a.shape[1] - 1) // 2
    return torch.from_numpy(np.partition(a, k, axis=1)[:, k].copy())


def scene_center_radius(means: Tensor, quantile: float = 0.98) -> tuple[Tensor, float]:
    """Robust centre (per-axis median, :func:`scene_center`) [3] and radius (``quantile`` of
    distances) of [N, 3]."""
    m = means.detach()
    center = scene_center(m)
    dist = (m - center).norm(dim=1)
    k = max(1, min(dist.numel(), int(round(quantile * dist.numel()))))
    radius = float(dist.kthvalue(k).values) if dist.numel() else 1.0
    return center, max(radius, 1e-6)


def pool_radius(poses: Tensor, centre: Tensor | None = None) -> float:
    """Median distance of the pool's camera centres from ``centre`` [3] (default: their mean),
    at least 1e-6: the unit of the twist metric and of the scoring tolerances.

    Args:
        poses: camera-to-world poses [D, 4, 4].
    """
    p = poses[:, :3, 3].detach()
    c = p.mean(0) if centre is None else centre.to(p.dtype)
    return max(float((p - c).norm(dim=1).median()), 1e-6)
