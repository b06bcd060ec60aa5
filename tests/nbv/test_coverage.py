"""Support samples, frustum visibility, the anchor coverage matrix M and the JL projection."""

from __future__ import annotations

import math

import pytest
import torch

from agilegs.service.nbv import Intrinsics, look_at
from agilegs.service.nbv.candidates import capture_pool
from agilegs.service.nbv.coverage import (
    coverage_matrix,
    frustum_visibility,
    jl_projection,
    support_samples,
)

DTYPES = [torch.float32, torch.float64]
INTR = Intrinsics.from_fov(60.0, 32, 32)


def pose(eye: list[float], target: list[float], dtype: torch.dtype = torch.float64) -> torch.Tensor:
    return look_at(torch.tensor(eye, dtype=dtype), torch.tensor(target, dtype=dtype))


def blob(n: int = 400, dtype: torch.dtype = torch.float64, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (0.3 * torch.randn(n, 3, generator=g, dtype=torch.float64)).to(dtype)


def naive_m(x, cands, anchor, intr, sigma_p, gamma, eps, near):
    """Paper eqs. 8-10, one loop per entry."""
    d, k = cands.shape[0], x.shape[0]
    m = torch.zeros(d, k, dtype=torch.float64)
    chi = torch.zeros(d, k, dtype=torch.float64)
    for v in range(d):
        r, p = cands[v, :3, :3], cands[v, :3, 3]
        for j in range(k):
            c = r.T @ (x[j] - p)
            inside = (
                c[2] > near
                and 0 <= intr.fx * c[0] / c[2] + intr.cx < intr.width
                and 0 <= intr.fy * c[1] / c[2] + intr.cy < intr.height
            )
            chi[v, j] = float(inside)
    for v in range(d):
        r, p = cands[v, :3, :3], cands[v, :3, 3]
        dv = r[:, 2]
        pos = math.exp(-float(((p - anchor[:3, 3]) ** 2).sum()) / (2 * sigma_p**2))
        orient = max(float(dv @ anchor[:3, 2]), 0.0) ** 2
        rho = pos * orient * float(chi[v].mean())
        for j in range(k):
            rvec = x[j] - p
            dist = float(rvec.norm())
            kappa = chi[v, j] * max(float(dv @ rvec) / dist, 0.0) / (dist + eps)
            m[v, j] = rho**gamma * kappa
    return m


@pytest.mark.parametrize("dtype", DTYPES)
def test_coverage_matrix_matches_naive(dtype: torch.dtype) -> None:
    x = blob(60, dtype)
    cands = capture_pool([0.0, 0.0, 0.0], 2.0, 12, seed=3, dtype=dtype)
    anchor = cands[4].clone()
    res = coverage_matrix(x, cands, anchor, INTR, sigma_p=1.0, gamma=1.5, eps=1e-3, near=0.01)
    ref = naive_m(x.double(), cands.double(), anchor.double(), INTR, 1.0, 1.5, 1e-3, 0.01)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(res.m.double(), ref, rtol=tol, atol=tol)
    assert res.m.shape == (12, 60) and res.rho.shape == (12,)
    assert bool((res.rho >= 0).all()) and bool((res.rho <= 1).all())


def test_back_facing_candidate_gets_zero_row() -> None:
    x = blob(200)
    anchor = pose([0.0, 0.0, -2.0], [0.0, 0.0, 0.0])
    front = pose([0.3, 0.0, -2.0], [0.0, 0.0, 0.0])
    # behind the anchor's samples, looking away from them (its axis opposes the anchor's)
    back = pose([0.0, 0.0, -2.5], [0.0, 0.0, -5.0])
    # looks at the object from the far side: sees the samples but faces the anchor
    opposite = pose([0.0, 0.0, 2.0], [0.0, 0.0, 0.0])
    cands = torch.stack([front, back, opposite])
    res = coverage_matrix(x, cands, anchor, INTR, sigma_p=1.0)
    assert float(res.m[0].abs().sum()) > 0
    assert torch.equal(res.m[1], torch.zeros_like(res.m[1]))
    assert torch.equal(res.m[2], torch.zeros_like(res.m[2]))
    assert float(res.rho[1]) == 0.0 and float(res.rho[2]) == 0.0


def test_frustum_visibility() -> None:
    cam = pose([0.0, 0.0, -2.0], [0.0, 0.0, 0.0]).unsqueeze(0)
    pts = torch.tensor(
        [[0.0, 0.0, 0.0], [0.0, 0.0, -3.0], [5.0, 0.0, 0.0], [0.0, 0.0, -1.995]],
        dtype=torch.float64,
    )
    vis = frustum_visibility(pts, cam, INTR, near=0.01)
    assert vis.tolist() == [[True, False, False, False]]


def test_support_samples_lie_in_anchor_frustum_and_are_seeded() -> None:
    means = blob(500)
    anchor = pose([0.0, 0.0, -2.0], [0.0, 0.0, 0.0])
    a = support_samples(
        means, anchor, INTR, grid=16, ray_samples=2, generator=torch.Generator().manual_seed(1)
    )
    b = support_samples(
        means, anchor, INTR, grid=16, ray_samples=2, generator=torch.Generator().manual_seed(1)
    )
    assert torch.equal(a, b)
    assert a.shape[0] % 3 == 0 and a.shape[0] // 3 <= 16 * 16
    vis = frustum_visibility(a, anchor.unsqueeze(0), INTR)
    assert bool(vis.all())
    capped = support_samples(
        means, anchor, INTR, grid=16, max_samples=50, generator=torch.Generator().manual_seed(1)
    )
    assert capped.shape[0] == 50


def test_point_zbuffer_keeps_the_nearest_mean_per_cell() -> None:
    anchor = pose([0.0, 0.0, -2.0], [0.0, 0.0, 0.0])
    means = torch.tensor([[0.0, 0.0, 0.5], [0.0, 0.0, -0.5], [0.0, 0.0, 0.0]], dtype=torch.float64)
    x = support_samples(means, anchor, INTR, grid=8, ray_samples=0)
    torch.testing.assert_close(x, means[1:2])
    # a transparent mean is not a surface
    op = torch.tensor([1.0, 0.01, 1.0], dtype=torch.float64)
    x = support_samples(means, anchor, INTR, grid=8, ray_samples=0, opacities=op)
    torch.testing.assert_close(x, means[2:3])


def test_support_samples_fall_back_when_nothing_is_seen() -> None:
    means = blob(50)
    away = pose([0.0, 0.0, -2.0], [0.0, 0.0, -5.0])
    x = support_samples(means, away, INTR, grid=4, ray_samples=0)
    assert x.shape == (16, 3)
    assert bool(frustum_visibility(x, away.unsqueeze(0), INTR).all())


def test_jl_projection_is_seeded_and_scaled() -> None:
    a = jl_projection(500, 64, seed=3)
    b = jl_projection(500, 64, seed=3)
    c = jl_projection(500, 64, seed=4)
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert a.shape == (500, 64)
    # E ||x Pi||^2 = ||x||^2 for N(0, 1/d) entries
    g = torch.Generator().manual_seed(0)
    x = torch.randn(200, 500, generator=g)
    ratio = (x @ a).pow(2).sum(1) / x.pow(2).sum(1)
    assert abs(float(ratio.mean()) - 1.0) < 0.1


@pytest.mark.parametrize("dim", [64, 8, 5])
def test_jl_projection_from_a_larger_draw_equals_its_own_draw(dim: int) -> None:
    """Pi's rows cut from a larger draw are the matrix a draw of its own size gives."""
    from agilegs.service.nbv.coverage import _jl_draw, _jl_matrix, _jl_typed

    _jl_matrix.cache_clear()
    _jl_typed.cache_clear()
    for k in [1, 2, 3, 7, 100, 1920, 2048, 4097, 6016, 6144, 5000, 7]:
        assert torch.equal(jl_projection(k, dim, seed=11, dtype=torch.float64),
                           _jl_draw(k, dim, 11)), (k, dim)


def test_jl_projection_rejects_bad_sizes() -> None:
    with pytest.raises(ValueError, match="JL"):
        jl_projection(0, 4)


@pytest.mark.parametrize("dtype", DTYPES)
def test_point_zbuffer_equals_the_sorted_reference(dtype: torch.dtype) -> None:
    """The surface samples: per occupied cell in cell order, the nearest mean, the first in
    index order among equally near ones (as a stable sort by depth, then by cell)."""
    from agilegs.service.nbv.coverage import project_points

    means = blob(3000, dtype, seed=4)
    means[1500:1600] = means[:100]  # exact ties in depth and cell
    anchor = pose([0.3, 0.2, -2.0], [0.0, 0.0, 0.0], dtype)
    grid = 16
    got = support_samples(means, anchor, INTR, grid=grid, ray_samples=0, max_samples=10**6)
    u, v, z = project_points(means, anchor, INTR.scaled(grid, grid))
    idx = torch.nonzero((z > 0.01) & (u >= 0) & (u < grid) & (v >= 0) & (v < grid)).squeeze(1)
    cell = v[idx].long() * grid + u[idx].long()
    order = torch.argsort(z[idx], stable=True)
    order = order[torch.argsort(cell[order], stable=True)]
    cs = cell[order]
    first = torch.ones_like(cs, dtype=torch.bool)
    first[1:] = cs[1:] != cs[:-1]
    assert int(first.sum()) > 50
    assert torch.equal(got, means[idx[order[first]]])


@pytest.mark.parametrize("dtype", DTYPES)
def test_coverage_kernel_equals_the_torch_reference(dtype: torch.dtype) -> None:
    from agilegs.service.nbv.coverage import _coverage_terms_kernel, _coverage_terms_torch
    from agilegs.service.nbv.kernels import backend

    if not backend.kernels_available():
        pytest.skip("numba unavailable")
    means = blob(600, dtype, seed=5)
    cands = capture_pool(torch.zeros(3, dtype=torch.float64), 2.0, 40, seed=1).to(dtype)
    cands[0, :3, 3] = means[0]  # a candidate on a sample: distance 0
    samples = torch.cat([means, 3.0 * means[:50]])  # some behind the cameras or outside
    got = _coverage_terms_kernel(samples, cands, INTR, 0.01, 1e-3)
    ref = _coverage_terms_torch(samples, cands, INTR, 0.01, 1e-3)
    assert 0 < int(ref[1].sum()) < ref[1].numel()
    assert torch.equal(got[1], ref[1])
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(got[0], ref[0], rtol=tol, atol=tol)
    torch.testing.assert_close(got[2], ref[2], rtol=tol, atol=tol)
    anchor = pose([0.0, 0.5, -2.0], [0.0, 0.0, 0.0], dtype)
    full = coverage_matrix(samples, cands, anchor, INTR, sigma_p=1.0)
    try:
        backend.set_default_backend("torch")
        slow = coverage_matrix(samples, cands, anchor, INTR, sigma_p=1.0)
    finally:
        backend.set_default_backend(None)
    torch.testing.assert_close(full.m, slow.m, rtol=tol, atol=tol)
    assert torch.equal(full.chi, slow.chi)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [1, 2, 1001, 1002])
def test_scene_center_is_torch_s_per_axis_median(dtype: torch.dtype, n: int) -> None:
    from agilegs.service.nbv.candidates import scene_center

    pts = torch.randn(n, 3, generator=torch.Generator().manual_seed(n), dtype=dtype)
    pts[: n // 3, 1] = 0.25  # ties
    torch.testing.assert_close(scene_center(pts), pts.median(dim=0).values, rtol=0, atol=0)
