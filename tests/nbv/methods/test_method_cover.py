"""COVER: Fibonacci bins, filled bins from acquired frustums, per-Gaussian coverage, score."""

from __future__ import annotations

import math

import torch

from agilegs.service.nbv import Camera, GaussianMap, Intrinsics, look_at, render
from agilegs.service.nbv.methods.cover import (
    cover_scores,
    fibonacci_sphere,
    filled_bins,
    gaussian_coverage,
    kept_by_projection,
)

INTR = Intrinsics.from_fov(60.0, 32, 32)


def pose(eye: list[float], target: list[float] | None = None) -> torch.Tensor:
    t = (
        torch.zeros(3, dtype=torch.float64)
        if target is None
        else torch.tensor(target, dtype=torch.float64)
    )
    return look_at(torch.tensor(eye, dtype=torch.float64), t)


def tiny_map(n: int = 200, seed: int = 0) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    pts = 0.3 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    cols = torch.rand(n, 3, generator=g, dtype=torch.float64)
    return GaussianMap.from_points(pts, cols, scale=0.06, opacity=0.8)


def test_fibonacci_sphere_is_unit_and_spread() -> None:
    b = fibonacci_sphere(128, dtype=torch.float64)
    assert b.shape == (128, 3)
    torch.testing.assert_close(b.norm(dim=1), torch.ones(128, dtype=torch.float64))
    assert float(b.mean(0).norm()) < 0.02
    # nearly uniform: every direction has a bin within ~15 degrees
    g = torch.Generator().manual_seed(0)
    probe = torch.randn(1000, 3, generator=g, dtype=torch.float64)
    probe = probe / probe.norm(dim=1, keepdim=True)
    worst = float((probe @ b.T).amax(dim=1).min())
    assert worst > math.cos(math.radians(15))


def test_fibonacci_sphere_is_covers_lattice() -> None:
    b = fibonacci_sphere(128, dtype=torch.float64)
    golden = (1 + math.sqrt(5)) / 2
    for i in (0, 1, 77, 127):
        z = 1 - 2 * (i + 0.5) / 128
        theta = 2 * math.pi * ((i / golden) % 1.0)
        r = math.sqrt(1 - z * z)
        ref = torch.tensor([r * math.cos(theta), r * math.sin(theta), z], dtype=torch.float64)
        torch.testing.assert_close(b[i], ref)


def _points(means: list[list[float]], scale: float) -> GaussianMap:
    pts = torch.tensor(means, dtype=torch.float64)
    return GaussianMap.from_points(pts, torch.full_like(pts, 0.5), scale=scale, opacity=0.8)


def test_filled_bins_follow_acquired_frustums() -> None:
    bins = fibonacci_sphere(128, dtype=torch.float64)
    gmap = _points([[0.0, 0.0, 0.0], [0.0, 0.0, -10.0]], scale=0.2)
    cam = pose([0.0, 0.0, -2.0])
    filled = filled_bins(gmap, cam.unsqueeze(0), INTR, bins)
    # Gaussian 0 is seen: exactly the bin of the direction camera -> Gaussian (+z) is filled
    assert int(filled[0].sum()) == 1
    g = int(torch.nonzero(filled[0])[0])
    assert g == int(torch.argmax(bins @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)))
    # Gaussian 1 is behind the camera: nothing filled
    assert int(filled[1].sum()) == 0


def test_gaussians_of_small_projected_radius_fill_no_bin() -> None:
    bins = fibonacci_sphere(128, dtype=torch.float64)
    cam = pose([0.0, 0.0, -2.0])
    # at 32 px and 60 degrees, f ~ 27.7 px: sigma 0.02 at depth 2 is ~0.28 px (radius
    # ceil(3.33 sqrt(0.28^2 + 0.3)) = 3, clipped); sigma 0.2 is ~2.8 px (radius 10, kept)
    small = _points([[0.0, 0.0, 0.0]], scale=0.02)
    big = _points([[0.0, 0.0, 0.0]], scale=0.2)
    assert not bool(kept_by_projection(small, Camera(c2w=cam, intrinsics=INTR))[0])
    assert int(filled_bins(small, cam.unsqueeze(0), INTR, bins).sum()) == 0
    assert int(filled_bins(big, cam.unsqueeze(0), INTR, bins).sum()) == 1
    # without the clip, the small one counts too
    assert int(filled_bins(small, cam.unsqueeze(0), INTR, bins, radius_clip=0.0).sum()) == 1


def test_gaussian_coverage_values() -> None:
    bins = fibonacci_sphere(128, dtype=torch.float64)
    means = torch.zeros(2, 3, dtype=torch.float64)
    filled = torch.zeros(2, 128, dtype=torch.bool)
    filled[0, 5] = True
    cam_pos = -3.0 * bins[5]  # looking along bins[5] at the Gaussian
    c = gaussian_coverage(means, cam_pos, bins, filled)
    assert abs(float(c[0]) - 1.0) < 1e-9  # the same direction as the filled bin
    assert float(c[1]) == 0.0  # no filled bin: never seen
    opposite = gaussian_coverage(means, -cam_pos, bins, filled)
    assert abs(float(opposite[0])) < 1e-9  # (cos + 1) / 2 with cos = -1


def test_cover_prefers_the_unseen_side() -> None:
    gmap = tiny_map()
    seen = pose([0.0, 0.0, -2.0])
    same_side = pose([0.2, 0.0, -2.0])
    far_side = pose([0.0, 0.0, 2.0])
    scores = cover_scores(gmap, torch.stack([same_side, far_side]), INTR, seen.unsqueeze(0))
    assert float(scores[1]) < float(scores[0])


def test_cover_score_is_mean_of_composited_channel_over_alpha() -> None:
    gmap = tiny_map(120, seed=2)
    acq = torch.stack([pose([0.0, 0.0, -2.0]), pose([2.0, 0.0, 0.0])])
    cand = pose([1.2, -0.8, -1.2])
    score = cover_scores(gmap, cand.unsqueeze(0), INTR, acq)
    bins = fibonacci_sphere(128, dtype=torch.float64)
    filled = filled_bins(gmap, acq, INTR, bins)
    c = gaussian_coverage(gmap.means, cand[:3, 3], bins, filled)
    out = render(gmap, Camera(c2w=cand, intrinsics=INTR), features=c[:, None])
    assert out.features is not None
    ref = out.features[..., 0][out.alpha > 0].mean()
    torch.testing.assert_close(score[0], ref)


def test_cover_without_acquired_views_scores_zero() -> None:
    gmap = tiny_map(50)
    scores = cover_scores(
        gmap, pose([0.0, 0.0, -2.0]).unsqueeze(0), INTR, torch.zeros(0, 4, 4, dtype=torch.float64)
    )
    assert float(scores[0]) == 0.0
