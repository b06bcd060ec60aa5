"""SE(3) / SO(3) maths: exp/log identities, small-angle and near-pi stability, gradients."""

from __future__ import annotations

import math

import pytest
import torch

from agilegs.service.nbv import hat, se3_exp, se3_log, vee
from agilegs.service.nbv.se3 import (
    pose_distance,
    project_to_se3,
    rotation_angle,
    se3_inverse,
    so3_exp,
    so3_hat,
    so3_log,
    so3_vee,
)

DTYPES = [torch.float32, torch.float64]
# (rtol-free) absolute tolerances for identities on O(1) quantities
TOL = {torch.float32: 5e-6, torch.float64: 1e-12}
ANGLES = [0.0, 1e-8, 1e-6, 1e-4, 1e-2, 0.09, 0.11, 0.5, 1.0, 2.0, 2.5, 3.0, math.pi - 1e-4]


def random_twists(n: int, angle: float, dtype: torch.dtype, seed: int = 0) -> torch.Tensor:
    """Twists with random translation (|rho| ~ 1) and rotation angle exactly ``angle``."""
    g = torch.Generator().manual_seed(seed)
    rho = torch.randn(n, 3, generator=g, dtype=torch.float64)
    axis = torch.randn(n, 3, generator=g, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    return torch.cat([rho, axis * angle], dim=-1).to(dtype)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("angle", ANGLES)
def test_log_of_exp_is_identity(dtype: torch.dtype, angle: float) -> None:
    xi = random_twists(200, angle, dtype)
    back = se3_log(se3_exp(xi))
    assert back.dtype == dtype
    # near pi the rotation vector is only as accurate as R allows (d omega ~ eps / sin t)
    tol = TOL[dtype] * (100 if angle > 3.0 else 1)
    torch.testing.assert_close(back, xi, atol=tol, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("angle", ANGLES + [math.pi - 1e-7, math.pi])
def test_exp_of_log_is_identity(dtype: torch.dtype, angle: float) -> None:
    t = se3_exp(random_twists(200, angle, torch.float64, seed=1)).to(dtype)
    back = se3_exp(se3_log(t))
    torch.testing.assert_close(back, t, atol=10 * TOL[dtype], rtol=0)
    # the principal log: rotation angle in [0, pi]
    ang = se3_log(t)[..., 3:].norm(dim=-1)
    assert float(ang.max()) <= math.pi + 10 * TOL[dtype]


@pytest.mark.parametrize("dtype", DTYPES)
def test_log_at_exactly_pi(dtype: torch.dtype) -> None:
    # 180 degree turns about coordinate axes and a generic axis: the antisymmetric part is 0
    axes = torch.tensor(
        [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, -2.0, 0.5]], dtype=torch.float64
    )
    axes = axes / axes.norm(dim=-1, keepdim=True)
    r = so3_exp(axes * math.pi).to(dtype)
    w = so3_log(r)
    assert torch.isfinite(w).all()
    torch.testing.assert_close(w.norm(dim=-1), torch.full((4,), math.pi, dtype=dtype))
    torch.testing.assert_close(so3_exp(w), r, atol=10 * TOL[dtype], rtol=0)
    # the axis is recovered up to sign
    assert torch.allclose((w / math.pi * axes.to(dtype)).sum(-1).abs(), torch.ones(4, dtype=dtype))


@pytest.mark.parametrize("dtype", DTYPES)
def test_hat_vee_inverse(dtype: torch.dtype) -> None:
    xi = torch.randn(5, 7, 6, dtype=dtype)
    x = hat(xi)
    assert x.shape == (5, 7, 4, 4)
    torch.testing.assert_close(vee(x), xi)
    assert (x[..., 3, :] == 0).all()
    w = xi[..., 3:]
    torch.testing.assert_close(so3_vee(so3_hat(w)), w)
    k = so3_hat(w)
    torch.testing.assert_close(k, -k.transpose(-1, -2))
    v = torch.randn(5, 7, 3, dtype=dtype)
    torch.testing.assert_close((k @ v[..., None]).squeeze(-1), torch.cross(w, v, dim=-1))


@pytest.mark.parametrize("dtype", DTYPES)
def test_exp_of_zero_is_identity(dtype: torch.dtype) -> None:
    t = se3_exp(torch.zeros(3, 6, dtype=dtype))
    assert torch.equal(t, torch.eye(4, dtype=dtype).expand(3, 4, 4))
    assert torch.equal(so3_exp(torch.zeros(3, dtype=dtype)), torch.eye(3, dtype=dtype))
    assert torch.equal(se3_log(torch.eye(4, dtype=dtype)), torch.zeros(6, dtype=dtype))
    assert torch.equal(so3_log(torch.eye(3, dtype=dtype)), torch.zeros(3, dtype=dtype))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("angle", [0.0, 1e-6, 0.05, 0.5, 1.5, 3.0])
def test_exp_matches_matrix_exp(dtype: torch.dtype, angle: float) -> None:
    xi = random_twists(100, angle, dtype, seed=2)
    ref = torch.linalg.matrix_exp(hat(xi.double())).to(dtype)
    torch.testing.assert_close(se3_exp(xi), ref, atol=2 * TOL[dtype], rtol=0)
    torch.testing.assert_close(so3_exp(xi[..., 3:]), ref[..., :3, :3], atol=2 * TOL[dtype], rtol=0)


def test_exp_is_rigid_and_batched() -> None:
    xi = torch.randn(4, 3, 6, dtype=torch.float64) * 2
    t = se3_exp(xi)
    assert t.shape == (4, 3, 4, 4)
    r = t[..., :3, :3]
    torch.testing.assert_close(
        r.transpose(-1, -2) @ r, torch.eye(3, dtype=torch.float64).expand_as(r)
    )
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(4, 3, dtype=torch.float64))
    torch.testing.assert_close(
        t[..., 3, :], torch.tensor([0.0, 0, 0, 1], dtype=torch.float64).expand(4, 3, 4)
    )
    # batching agrees with one-at-a-time evaluation
    torch.testing.assert_close(t[2, 1], se3_exp(xi[2, 1]))


@pytest.mark.parametrize("dtype", DTYPES)
def test_gradient_at_zero_twist_is_finite_and_correct(dtype: torch.dtype) -> None:
    xi = torch.zeros(6, dtype=dtype, requires_grad=True)
    (g,) = torch.autograd.grad(se3_exp(xi).sum(), xi)
    assert torch.isfinite(g).all()
    # central finite differences in float64
    x0 = torch.zeros(6, dtype=torch.float64)
    h = 1e-6
    fd = torch.stack(
        [
            (se3_exp(x0 + h * e).sum() - se3_exp(x0 - h * e).sum()) / (2 * h)
            for e in torch.eye(6, dtype=torch.float64)
        ]
    )
    torch.testing.assert_close(g.double(), fd, atol=1e-5, rtol=0)
    # d/dxi sum(exp(xi)) at 0 = sum(hat(e_i)): translations 1 each, rotations cancel
    torch.testing.assert_close(g, torch.tensor([1.0, 1, 1, 0, 0, 0], dtype=dtype))


@pytest.mark.parametrize("dtype", DTYPES)
def test_gradients_finite_at_identity_for_log_and_distance(dtype: torch.dtype) -> None:
    t = torch.eye(4, dtype=dtype, requires_grad=True)
    (g,) = torch.autograd.grad(se3_log(t).sum(), t)
    assert torch.isfinite(g).all()
    t1 = torch.eye(4, dtype=dtype, requires_grad=True)
    (g1,) = torch.autograd.grad(pose_distance(t1, torch.eye(4, dtype=dtype)), t1)
    assert torch.isfinite(g1).all()
    # tiny twists: the Taylor branches
    xi = torch.full((6,), 1e-7, dtype=dtype, requires_grad=True)
    (gx,) = torch.autograd.grad(se3_log(se3_exp(xi)).sum(), xi)
    torch.testing.assert_close(gx, torch.ones(6, dtype=dtype), atol=1e-4, rtol=0)


@pytest.mark.gradcheck
@pytest.mark.parametrize("angle", [0.0, 1e-3, 0.05, 0.3, 1.3, 2.9])
def test_gradcheck_se3_exp(angle: float) -> None:
    xi = random_twists(3, angle, torch.float64, seed=3).requires_grad_(True)
    assert torch.autograd.gradcheck(se3_exp, (xi,))
    assert torch.autograd.gradgradcheck(se3_exp, (xi,))


@pytest.mark.gradcheck
@pytest.mark.parametrize("angle", [1e-3, 0.05, 0.3, 1.3, 2.9])
def test_gradcheck_se3_log(angle: float) -> None:
    t = se3_exp(random_twists(3, angle, torch.float64, seed=4)).requires_grad_(True)
    assert torch.autograd.gradcheck(se3_log, (t,))


@pytest.mark.gradcheck
def test_gradcheck_pose_distance() -> None:
    t1 = se3_exp(random_twists(4, 0.7, torch.float64, seed=5)).requires_grad_(True)
    t2 = se3_exp(random_twists(4, 2.0, torch.float64, seed=6))
    assert torch.autograd.gradcheck(lambda a: pose_distance(a, t2, rot_weight=0.3), (t1,))


@pytest.mark.parametrize("dtype", DTYPES)
def test_se3_inverse(dtype: torch.dtype) -> None:
    t = se3_exp(random_twists(10, 1.2, dtype, seed=7))
    inv = se3_inverse(t)
    eye = torch.eye(4, dtype=dtype).expand_as(t)
    torch.testing.assert_close(inv @ t, eye, atol=10 * TOL[dtype], rtol=0)
    torch.testing.assert_close(t @ inv, eye, atol=10 * TOL[dtype], rtol=0)
    torch.testing.assert_close(inv, torch.linalg.inv(t), atol=10 * TOL[dtype], rtol=0)
    # exp(-xi) = exp(xi)^-1
    xi = random_twists(10, 0.8, dtype, seed=8)
    torch.testing.assert_close(se3_exp(-xi), se3_inverse(se3_exp(xi)), atol=10 * TOL[dtype], rtol=0)


def test_pose_distance_metric() -> None:
    dt = torch.float64
    a = se3_exp(random_twists(6, 0.9, dt, seed=9))
    b = se3_exp(random_twists(6, 2.2, dt, seed=10))
    c = se3_exp(random_twists(6, 1.5, dt, seed=11))
    dab = pose_distance(a, b, rot_weight=0.5)
    assert dab.shape == (6,)
    torch.testing.assert_close(dab, pose_distance(b, a, rot_weight=0.5))
    torch.testing.assert_close(pose_distance(a, a), torch.zeros(6, dtype=dt), atol=1e-7, rtol=0)
    tri = pose_distance(a, c, 0.5) + pose_distance(c, b, 0.5) - dab
    assert (tri >= -1e-12).all()
    # definition: translation distance + weight * geodesic angle
    ang = so3_log(a[..., :3, :3].transpose(-1, -2) @ b[..., :3, :3]).norm(dim=-1)
    ref = (a[..., :3, 3] - b[..., :3, 3]).norm(dim=-1) + 0.5 * ang
    torch.testing.assert_close(dab, ref)
    # pure rotation about z by 90 degrees at the same place: distance = weight * pi/2
    rz = se3_exp(torch.tensor([0.0, 0, 0, 0, 0, math.pi / 2], dtype=dt))
    torch.testing.assert_close(
        pose_distance(torch.eye(4, dtype=dt), rz, rot_weight=2.0),
        torch.tensor(math.pi, dtype=dt),
    )
    # broadcasting: one pose against a pool
    pool = se3_exp(random_twists(8, 1.0, dt, seed=12))
    d = pose_distance(a[0], pool)
    assert d.shape == (8,)
    torch.testing.assert_close(d[3], pose_distance(a[0], pool[3]))
    with pytest.raises(ValueError, match="rot_weight"):
        pose_distance(a, b, rot_weight=-1.0)


def test_rotation_angle_range() -> None:
    angles = torch.tensor([0.0, 1e-9, 0.5, 3.0, math.pi], dtype=torch.float64)
    z = torch.zeros(5, dtype=torch.float64)
    r = so3_exp(torch.stack([z, z, angles], -1))
    torch.testing.assert_close(rotation_angle(r), angles, atol=1e-12, rtol=0)
    # an angle beyond pi folds back: the geodesic distance is the shorter way round
    r_far = so3_exp(torch.tensor([0.0, 0.0, 4.0], dtype=torch.float64))
    torch.testing.assert_close(
        rotation_angle(r_far), torch.tensor(2 * math.pi - 4.0, dtype=torch.float64)
    )


def test_shape_errors_name_the_argument() -> None:
    with pytest.raises(ValueError, match="xi"):
        se3_exp(torch.zeros(5))
    with pytest.raises(ValueError, match="T"):
        se3_log(torch.zeros(3, 3))
    with pytest.raises(ValueError, match="omega"):
        so3_exp(torch.zeros(4))


def test_no_device_or_dtype_change() -> None:
    for dtype in DTYPES:
        xi = torch.randn(2, 6, dtype=dtype)
        t = se3_exp(xi)
        assert t.dtype == dtype and t.device == xi.device
        assert se3_log(t).dtype == dtype


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu() -> None:
    xi = random_twists(50, 1.0, torch.float32, seed=13)
    t_cpu = se3_exp(xi)
    t_gpu = se3_exp(xi.cuda())
    assert t_gpu.is_cuda
    torch.testing.assert_close(t_gpu.cpu(), t_cpu, atol=1e-5, rtol=0)
    torch.testing.assert_close(se3_log(t_gpu).cpu(), se3_log(t_cpu), atol=1e-5, rtol=0)


def test_project_to_se3_is_the_nearest_rotation_and_keeps_rigid_poses() -> None:
    g = torch.Generator().manual_seed(3)
    xi = torch.randn(16, 6, generator=g, dtype=torch.float64)
    rigid = se3_exp(xi)
    assert torch.allclose(project_to_se3(rigid), rigid, atol=1e-12)
    noisy = rigid.clone()
    noisy[:, :3, :3] += 1e-3 * torch.randn(16, 3, 3, generator=g, dtype=torch.float64)
    out = project_to_se3(noisy)
    r = out[:, :3, :3]
    eye = torch.eye(3, dtype=torch.float64)
    assert torch.allclose(r.transpose(-1, -2) @ r, eye.expand(16, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(r), torch.ones(16, dtype=torch.float64))
    assert torch.equal(out[:, :3, 3], noisy[:, :3, 3])
    assert torch.equal(out[:, 3], torch.tensor([0.0, 0, 0, 1], dtype=torch.float64).expand(16, 4))
    # nearest in the Frobenius norm: no random rotation near it is nearer
    for _ in range(20):
        other = r @ so3_exp(1e-3 * torch.randn(16, 3, generator=g, dtype=torch.float64))
        assert bool(((noisy[:, :3, :3] - r).square().sum((-1, -2))
                     <= (noisy[:, :3, :3] - other).square().sum((-1, -2)) + 1e-15).all())
    # a reflection is turned into a proper rotation
    refl = rigid.clone()
    refl[:, :3, 2] *= -1
    assert torch.allclose(torch.linalg.det(project_to_se3(refl)[:, :3, :3]),
                          torch.ones(16, dtype=torch.float64))
