"""Exact diagonal Fisher against the brute-force per-pixel Jacobian, and the information maths."""

from __future__ import annotations

import pytest
import torch

from agilegs.config.selection import FIELD_NAMES
from agilegs.service.nbv import (
    Camera,
    GaussianMap,
    accumulate_information,
    expected_information_gain,
    fisher_diag,
    fisher_diag_bruteforce,
    init_information,
    look_at,
    trace_surrogate,
)

F64 = torch.float64


def random_map(n: int, *, seed: int = 0, deg: int = 1, dtype=F64) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    return GaussianMap(
        means=torch.rand(n, 3, generator=g, dtype=dtype) - 0.5,
        log_scales=torch.log(torch.rand(n, 3, generator=g, dtype=dtype) * 0.1 + 0.04),
        quats=torch.randn(n, 4, generator=g, dtype=dtype),
        opacity_logits=torch.randn(n, generator=g, dtype=dtype) + 0.5,
        sh=torch.randn(n, (deg + 1) ** 2, 3, generator=g, dtype=dtype) * 0.4,
    )


def camera(dtype=F64, w=16, h=14, eye=(0.3, -0.4, -2.0)) -> Camera:
    c2w = look_at(torch.tensor(eye, dtype=dtype), torch.zeros(3, dtype=dtype))
    return Camera.from_c2w(c2w, fx=0.9 * w, fy=0.9 * w, cx=w / 2, cy=h / 2 + 0.3, width=w, height=h)


@pytest.mark.parametrize("backend", ["torch", "numba"])
@pytest.mark.parametrize("deg", [0, 1, 3])
@pytest.mark.parametrize("bg", [None, (0.1, 0.5, 0.9)])
def test_fisher_matches_bruteforce_float64(deg: int, bg, backend: str) -> None:
    gm = random_map(30, seed=deg, deg=deg)
    gm.opacity_logits.data[:5] += 5.0  # some clamped at 0.99, and transmittance stops
    cam = camera()
    background = None if bg is None else torch.tensor(bg, dtype=F64)
    fast = fisher_diag(gm, cam, background=background, backend=backend)
    slow = fisher_diag_bruteforce(gm, cam, background=background)
    assert set(fast) == set(FIELD_NAMES)
    for k in FIELD_NAMES:
        assert fast[k].shape == getattr(gm, k).shape
        scale = slow[k].abs().max()
        assert scale > 0, k
        rel = ((fast[k] - slow[k]).abs().max() / scale).item()
        assert rel <= 1e-6, (k, rel)


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_fisher_float32_close_to_float64(backend: str) -> None:
    gm = random_map(40, seed=9)
    cam = camera()
    f64 = fisher_diag(gm, cam, backend=backend)
    f32 = fisher_diag(gm.to(dtype=torch.float32), cam.to(dtype=torch.float32), backend=backend)
    for k in FIELD_NAMES:
        assert f32[k].dtype == torch.float32
        rel = ((f32[k].double() - f64[k]).abs().max() / f64[k].abs().max()).item()
        assert rel < 1e-3, (k, rel)


def test_fisher_field_subset_and_bad_field() -> None:
    gm = random_map(10)
    cam = camera()
    only = fisher_diag(gm, cam, fields=["means", "sh"])
    assert set(only) == {"means", "sh"}
    full = fisher_diag(gm, cam)
    torch.testing.assert_close(only["means"], full["means"])
    with pytest.raises(ValueError, match="fields"):
        fisher_diag(gm, cam, fields=["colour"])


def test_fisher_pose_gradient_matches_finite_differences() -> None:
    gm = random_map(25, seed=4)
    cam = camera()
    h_acc = accumulate_information(
        init_information(gm, 0.3), fisher_diag(gm, camera(eye=(1.0, 0, -2)))
    )

    def psi(c2w: torch.Tensor) -> torch.Tensor:
        return trace_surrogate(fisher_diag(gm, cam.with_pose(c2w)), h_acc)

    x = cam.c2w.clone().requires_grad_()
    (g,) = torch.autograd.grad(psi(x), x)
    assert torch.isfinite(g).all()
    eps = 1e-6
    for i, j in [(0, 3), (1, 3), (2, 3), (0, 0), (1, 2), (2, 1)]:
        e = torch.zeros(4, 4, dtype=F64)
        e[i, j] = eps
        with torch.no_grad():
            fd = (psi(cam.c2w + e) - psi(cam.c2w - e)) / (2 * eps)
        assert abs(float(fd) - float(g[i, j])) <= 1e-5 * max(1.0, abs(float(fd))), (i, j)


def test_fisher_without_pose_grad_is_detached() -> None:
    gm = random_map(10)
    out = fisher_diag(gm, camera())
    assert all(not v.requires_grad for v in out.values())


def test_information_maths() -> None:
    gm = random_map(12)
    h0 = init_information(gm, 0.5)
    hv = fisher_diag(gm, camera())
    h1 = accumulate_information(h0, hv)
    for k in FIELD_NAMES:
        torch.testing.assert_close(h1[k], h0[k] + hv[k])
    eig = expected_information_gain(hv, h1)
    tr = trace_surrogate(hv, h1)
    expect = sum(torch.log1p(hv[k] / h1[k]).sum() for k in FIELD_NAMES)
    torch.testing.assert_close(eig, expect)
    assert float(tr) >= float(eig)  # tr(H Ĥ⁻¹) ≥ log det(I + H Ĥ⁻¹)
    # batched over views
    hv2 = fisher_diag(gm, camera(eye=(-1.0, 0.5, -1.5)))
    batch = {k: torch.stack([hv[k], hv2[k]]) for k in FIELD_NAMES}
    eb = expected_information_gain(batch, h1)
    assert eb.shape == (2,)
    torch.testing.assert_close(eb[0], eig)
    torch.testing.assert_close(eb[1], expected_information_gain(hv2, h1))
    only = expected_information_gain(hv, h1, fields=["means"])
    torch.testing.assert_close(only, torch.log1p(hv["means"] / h1["means"]).sum())


def test_information_maths_errors() -> None:
    gm = random_map(5)
    h0 = init_information(gm, 1.0)
    with pytest.raises(ValueError, match="lam"):
        init_information(gm, 0.0)
    bad = dict(h0)
    bad["means"] = torch.ones(4, 3, dtype=F64)
    with pytest.raises(ValueError, match="means"):
        accumulate_information(h0, bad)
    with pytest.raises(ValueError, match="means"):
        expected_information_gain(bad, h0)
    with pytest.raises(ValueError, match="fields"):
        trace_surrogate(h0, h0, fields=["nope"])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_per_gaussian_sums_by_segments_equal_the_scatter(dtype: torch.dtype) -> None:
    from agilegs.service.nbv.information import per_gaussian_sums

    g = torch.Generator().manual_seed(5)
    n, q = 40, 3000
    gauss = torch.randint(0, n - 3, (q,), generator=g)  # some Gaussians have no pair
    values = torch.randn(q, 7, generator=g, dtype=dtype)
    a = per_gaussian_sums(gauss, values, n, how="index_add")
    b = per_gaussian_sums(gauss, values, n, how="segments")
    assert a.shape == b.shape == (n, 7)
    tol = 1e-12 if dtype == torch.float64 else 1e-4
    torch.testing.assert_close(b, a, atol=tol, rtol=tol)
    assert torch.equal(b[n - 3:], torch.zeros(3, 7, dtype=dtype))
    with pytest.raises(ValueError, match="how must be"):
        per_gaussian_sums(gauss, values, n, how="atomic")  # type: ignore[arg-type]


def test_the_torch_fisher_summed_by_segments_matches_bruteforce(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The reduction a GPU takes (sorted runs instead of scattered additions), here on the
    CPU: the same exact Fisher."""
    import agilegs.service.nbv.information as info

    plain = info.per_gaussian_sums
    monkeypatch.setattr(info, "per_gaussian_sums",
                        lambda g, v, n, how="auto": plain(g, v, n, how="segments"))
    gm = random_map(30, seed=4, deg=1)
    gm.opacity_logits.data[:5] += 5.0
    cam = camera()
    fast = fisher_diag(gm, cam, backend="torch")
    slow = fisher_diag_bruteforce(gm, cam)
    for k in FIELD_NAMES:
        rel = ((fast[k] - slow[k]).abs().max() / slow[k].abs().max()).item()
        assert rel <= 1e-6, (k, rel)
