"""Pinhole camera, look_at and pose validation (OpenCV axes: x right, y down, z forward)."""

from __future__ import annotations

import math

import pytest
import torch

from agilegs.service.nbv import Camera, Intrinsics, check_pose, look_at, se3_exp

DTYPES = [torch.float32, torch.float64]
WORLD_UP = torch.tensor([0.0, -1.0, 0.0])  # Inria / COLMAP convention: up is -y


def _random_eyes(n: int, dtype: torch.dtype, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    # keep away from the poles, where "away from up" is ill defined
    d = d[(d @ WORLD_UP.double()).abs() < 0.95]
    return (2.5 * d).to(dtype)


@pytest.mark.parametrize("dtype", DTYPES)
def test_look_at_is_a_rotation_pointing_at_the_target(dtype: torch.dtype) -> None:
    eyes = _random_eyes(64, dtype)
    target = torch.tensor([0.1, -0.2, 0.3], dtype=dtype)
    c2w = look_at(eyes, target)
    n = eyes.shape[0]
    assert c2w.shape == (n, 4, 4) and c2w.dtype == dtype
    r = c2w[:, :3, :3]
    eye3 = torch.eye(3, dtype=dtype).expand(n, 3, 3)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(r.transpose(-1, -2) @ r, eye3, atol=tol, rtol=0)
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(n, dtype=dtype), atol=tol, rtol=0)
    # +z (third column) points from the eye at the target
    to_target = target - eyes
    to_target = to_target / to_target.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(r[:, :, 2], to_target, atol=tol, rtol=0)
    # +y (image down) points away from world up; +x is horizontal (no roll)
    up = WORLD_UP.to(dtype)
    assert ((r[:, :, 1] @ up) < 0).all()
    torch.testing.assert_close(r[:, :, 0] @ up, torch.zeros(n, dtype=dtype), atol=tol, rtol=0)
    # centre at the eye, proper last row
    torch.testing.assert_close(c2w[:, :3, 3], eyes)
    assert torch.equal(c2w[:, 3, :], torch.tensor([0, 0, 0, 1], dtype=dtype).expand(n, 4))
    check_pose(c2w)


def test_look_at_projects_the_target_to_the_principal_point() -> None:
    c2w = look_at(torch.tensor([1.0, -0.5, 2.0]), torch.zeros(3))
    cam = Camera.from_c2w(c2w, fx=100, fy=100, cx=32, cy=24, width=64, height=48)
    p = cam.w2c @ torch.tensor([0.0, 0.0, 0.0, 1.0])
    assert float(p[2]) > 0  # in front of the camera
    u = cam.fx * p[0] / p[2] + cam.cx
    v = cam.fy * p[1] / p[2] + cam.cy
    torch.testing.assert_close(torch.stack([u, v]), torch.tensor([32.0, 24.0]))
    # a point above the target (world up = -y) lands in the upper half of the image (v < cy)
    q = cam.w2c @ torch.tensor([0.0, -0.3, 0.0, 1.0])
    assert float(cam.fy * q[1] / q[2] + cam.cy) < 24.0


def test_look_at_custom_up_and_degenerate_direction() -> None:
    up = torch.tensor([0.0, 0.0, 1.0])  # z-up world
    c2w = look_at(torch.tensor([3.0, 0.0, 0.5]), torch.zeros(3), up=up)
    assert float(c2w[:3, 1] @ up) < 0
    check_pose(c2w)
    # looking straight along up: still a valid, finite rotation
    c2w = look_at(torch.tensor([0.0, 2.0, 0.0]), torch.zeros(3))
    assert torch.isfinite(c2w).all()
    check_pose(c2w)
    torch.testing.assert_close(c2w[:3, 2], torch.tensor([0.0, -1.0, 0.0]))


@pytest.mark.parametrize("dtype", DTYPES)
def test_w2c_is_the_inverse_of_c2w(dtype: torch.dtype) -> None:
    c2w = look_at(torch.tensor([0.3, -1.2, 2.0], dtype=dtype), torch.zeros(3, dtype=dtype))
    cam = Camera.from_intrinsics(c2w, Intrinsics.from_fov(60.0, 64, 48))
    w2c = cam.w2c
    assert w2c.dtype == dtype
    eye4 = torch.eye(4, dtype=dtype)
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(w2c @ c2w, eye4, atol=tol, rtol=0)
    torch.testing.assert_close(c2w @ w2c, eye4, atol=tol, rtol=0)
    torch.testing.assert_close(w2c, torch.linalg.inv(c2w), atol=tol, rtol=0)
    # accessors
    torch.testing.assert_close(cam.position, c2w[:3, 3])
    torch.testing.assert_close(cam.forward, c2w[:3, 2])
    torch.testing.assert_close(cam.rotation, c2w[:3, :3])


def test_gradient_flows_through_w2c_to_c2w() -> None:
    eye = torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64, requires_grad=True)
    c2w = look_at(eye, torch.zeros(3, dtype=torch.float64))
    cam = Camera.from_c2w(c2w, fx=50, fy=50, cx=16, cy=16, width=32, height=32)
    point = torch.tensor([0.1, 0.2, -0.1, 1.0], dtype=torch.float64)
    depth = (cam.w2c @ point)[2]
    (g_eye,) = torch.autograd.grad(depth, eye)
    assert torch.isfinite(g_eye).all() and float(g_eye.abs().sum()) > 0

    leaf = c2w.detach().clone().requires_grad_(True)
    cam2 = cam.with_pose(leaf)
    (g,) = torch.autograd.grad((cam2.w2c @ point).sum(), leaf)
    assert torch.isfinite(g).all()
    assert float(g[:3, :3].abs().sum()) > 0 and float(g[:3, 3].abs().sum()) > 0

    # along the manifold (pose perturbed by a twist) it matches an explicit matrix inverse;
    # off the manifold R^T and R^-1 differ, so the raw 4x4 gradients need not agree
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    moved = c2w.detach() @ se3_exp(xi)
    (g_xi,) = torch.autograd.grad((cam.with_pose(moved).w2c @ point).sum(), xi)
    xi2 = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    moved2 = c2w.detach() @ se3_exp(xi2)
    (g_ref,) = torch.autograd.grad((torch.linalg.inv(moved2) @ point).sum(), xi2)
    torch.testing.assert_close(g_xi, g_ref)
    assert float(g_xi.abs().sum()) > 0


def test_gradcheck_w2c() -> None:
    c2w = look_at(torch.tensor([1.0, -0.5, 2.0], dtype=torch.float64), torch.zeros(3).double())
    intr = Intrinsics.from_fov(50.0, 32, 32)

    def f(m: torch.Tensor) -> torch.Tensor:
        return Camera(c2w=m, intrinsics=intr).w2c

    assert torch.autograd.gradcheck(f, (c2w.clone().requires_grad_(True),))


def test_check_pose_accepts_rigid_and_rejects_bad_poses() -> None:
    good = look_at(torch.tensor([1.0, -1.0, 2.0]), torch.zeros(3))
    check_pose(good)
    check_pose(torch.stack([good, torch.eye(4)]))  # batched

    nan = good.clone()
    nan[0, 3] = float("nan")
    with pytest.raises(ValueError, match=r"candidate_pose contains NaN"):
        check_pose(nan, name="candidate_pose")
    inf = good.clone()
    inf[1, 1] = float("inf")
    with pytest.raises(ValueError, match="c2w contains NaN or infinite"):
        check_pose(inf)

    skew = good.clone()
    skew[:3, 0] *= 1.5
    with pytest.raises(ValueError, match=r"pose\[3\] rotation is not orthonormal"):
        check_pose(skew, name="pose[3]")

    mirror = torch.diag(torch.tensor([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match="current.*determinant -1"):
        check_pose(mirror, name="current")

    row = torch.eye(4)
    row[3, 0] = 0.5
    with pytest.raises(ValueError, match="acquired last row"):
        check_pose(row, name="acquired")

    with pytest.raises(ValueError, match=r"c2w must have shape \[\.\.\., 4, 4\]"):
        check_pose(torch.eye(3))

    # Camera validates its pose unless told not to
    with pytest.raises(ValueError, match="c2w"):
        Camera.from_c2w(mirror, fx=1, fy=1, cx=0, cy=0, width=2, height=2)
    Camera.from_c2w(mirror, fx=1, fy=1, cx=0, cy=0, width=2, height=2, validate=False)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("fx", 0.0),
        ("fx", -10.0),
        ("fy", float("nan")),
        ("fy", float("inf")),
        ("cx", float("nan")),
        ("cy", float("-inf")),
        ("width", 0),
        ("width", 10.5),
        ("height", -3),
    ],
)
def test_intrinsics_reject_bad_values_naming_the_field(field: str, value: float) -> None:
    kwargs: dict[str, float] = dict(fx=100.0, fy=100.0, cx=32.0, cy=24.0, width=64, height=48)
    kwargs[field] = value
    with pytest.raises(ValueError, match=rf"^{field} must be"):
        Intrinsics(**kwargs)  # type: ignore[arg-type]


def test_intrinsics_from_fov_and_scaled() -> None:
    k = Intrinsics.from_fov(90.0, 200, 100)
    assert math.isclose(k.fx, 100.0) and k.fx == k.fy
    assert (k.cx, k.cy) == (100.0, 50.0)
    half = k.scaled(100, 50)
    assert (half.width, half.height) == (100, 50)
    for got, want in [(half.fx, 50.0), (half.fy, 50.0), (half.cx, 50.0), (half.cy, 25.0)]:
        assert math.isclose(got, want)
    # same field of view
    assert math.isclose(half.width / half.fx, k.width / k.fx)


def test_camera_to_and_resolution() -> None:
    c2w = look_at(torch.tensor([1.0, -1.0, 2.0]), torch.zeros(3))
    cam = Camera.from_intrinsics(c2w, Intrinsics.from_fov(60.0, 64, 48))
    c64 = cam.to(dtype=torch.float64)
    assert c64.c2w.dtype == torch.float64 and c64.w2c.dtype == torch.float64
    small = cam.with_resolution(32, 24)
    assert (small.width, small.height) == (32, 24)
    assert math.isclose(small.fx, cam.fx / 2)
