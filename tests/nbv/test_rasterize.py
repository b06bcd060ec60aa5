"""Rasterizer: closed forms, a naive per-pixel reference, analytic vs autograd backward, gradcheck."""

from __future__ import annotations

import math

import pytest
import torch

from agilegs.service.nbv import Camera, GaussianMap, look_at, project_gaussians, render
from agilegs.service.nbv.rasterize import ALPHA_MAX, ALPHA_MIN, T_MIN
from agilegs.service.nbv.rotations import quat_to_rotmat
from agilegs.service.nbv.sh import eval_sh_colors

F64 = torch.float64


def random_map(n: int, *, seed: int = 0, deg: int = 1, dtype=F64, scale=(0.03, 0.1)) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    lo, hi = scale
    return GaussianMap(
        means=torch.rand(n, 3, generator=g, dtype=dtype) - 0.5,
        log_scales=torch.log(torch.rand(n, 3, generator=g, dtype=dtype) * (hi - lo) + lo),
        quats=torch.randn(n, 4, generator=g, dtype=dtype),
        opacity_logits=torch.randn(n, generator=g, dtype=dtype),
        sh=torch.randn(n, (deg + 1) ** 2, 3, generator=g, dtype=dtype) * 0.3,
    )


def make_camera(w=16, h=15, dtype=F64, eye=(0.3, -0.4, -2.0)) -> Camera:
    c2w = look_at(torch.tensor(eye, dtype=dtype), torch.zeros(3, dtype=dtype))
    return Camera.from_c2w(
        c2w, fx=0.9 * w, fy=0.95 * w, cx=w / 2 + 0.3, cy=h / 2 - 0.2, width=w, height=h
    )


def naive_render(gmap: GaussianMap, cam: Camera, bg: torch.Tensor) -> torch.Tensor:
    """Per-pixel loop over depth-sorted Gaussians with the reference rules (slow, obvious)."""
    proj = project_gaussians(
        gmap.means, gmap.log_scales, gmap.quats, gmap.opacity_logits, gmap.sh, cam
    )
    order = torch.argsort(proj.depths, stable=True).tolist()
    img = torch.zeros(cam.height, cam.width, 3, dtype=gmap.dtype)
    for py in range(cam.height):
        for px in range(cam.width):
            t = 1.0
            c = torch.zeros(3, dtype=gmap.dtype)
            for i in order:
                r = int(proj.radii[i])
                if r == 0:
                    continue
                mx, my = proj.means2d[i].tolist()
                # the binning rule: the pixel's 8x8 tile lies in the (clamped) tile range
                # that the 3σ square [m - r, m + r] covers
                nx, ny = (cam.width + 7) // 8, (cam.height + 7) // 8
                x0 = min(max(math.floor((mx - r) / 8), 0), nx - 1)
                x1 = min(max(math.floor((mx + r) / 8), 0), nx - 1)
                y0 = min(max(math.floor((my - r) / 8), 0), ny - 1)
                y1 = min(max(math.floor((my + r) / 8), 0), ny - 1)
                if not (x0 <= px // 8 <= x1 and y0 <= py // 8 <= y1):
                    continue
                a, b, cc = proj.conics[i].tolist()
                dx, dy = px + 0.5 - mx, py + 0.5 - my
                sigma = 0.5 * (a * dx * dx + cc * dy * dy) + b * dx * dy
                if sigma < 0:
                    continue
                alpha = min(ALPHA_MAX, float(proj.opacities[i]) * math.exp(-sigma))
                if alpha < ALPHA_MIN:
                    continue
                if t * (1 - alpha) < T_MIN:
                    break
                c += t * alpha * proj.colors[i]
                t *= 1 - alpha
            img[py, px] = c + t * bg
    return img


def test_quat_to_rotmat_is_rotation() -> None:
    q = torch.randn(50, 4, dtype=F64)
    r = quat_to_rotmat(q)
    eye = torch.eye(3, dtype=F64).expand(50, 3, 3)
    torch.testing.assert_close(r @ r.transpose(-1, -2), eye)
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(50, dtype=F64))


BACKENDS = ["torch", "numba"]
"""The pure-torch reference and the compiled kernels, each against the closed forms and the
per-pixel loop below (tests/nbv/test_kernels.py compares the two directly)."""


@pytest.mark.parametrize("backend", BACKENDS)
def test_single_gaussian_matches_closed_form(backend: str) -> None:
    # one isotropic Gaussian straight ahead: its image is an isotropic 2D Gaussian whose
    # variance is f²s²/z² + 0.3 (the low-pass), centred on the principal point
    s, z, f, o = 0.05, 2.0, 40.0, 0.8
    gm = GaussianMap(
        means=torch.tensor([[0.0, 0.0, z]], dtype=F64),
        log_scales=torch.full((1, 3), math.log(s), dtype=F64),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64),
        opacity_logits=torch.tensor([math.log(o / (1 - o))], dtype=F64),
        sh=torch.tensor([[[0.7, -0.2, 0.1]]], dtype=F64),
    )
    cam = Camera.from_c2w(
        torch.eye(4, dtype=F64), fx=f, fy=f, cx=16.0, cy=16.0, width=32, height=32
    )
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=F64)
    out = render(gm, cam, background=bg, backend=backend)
    var = (f * s / z) ** 2 + 0.3
    ys, xs = torch.meshgrid(torch.arange(32, dtype=F64), torch.arange(32, dtype=F64), indexing="ij")
    d2 = (xs + 0.5 - 16.0) ** 2 + (ys + 0.5 - 16.0) ** 2
    alpha = torch.clamp(o * torch.exp(-0.5 * d2 / var), max=0.99)
    radius = math.ceil(3 * math.sqrt(var))
    inside = (xs + 0.5 - 16).abs() < radius + 8  # within the binned tiles
    alpha = torch.where((alpha >= 1 / 255) & inside, alpha, torch.zeros_like(alpha))
    color = 0.5 + 0.28209479177387814 * torch.tensor([0.7, -0.2, 0.1], dtype=F64)
    color = color.clamp_min(0)
    expect = alpha[..., None] * color + (1 - alpha[..., None]) * bg
    torch.testing.assert_close(out.rgb, expect, atol=1e-12, rtol=0)
    torch.testing.assert_close(out.alpha, alpha, atol=1e-12, rtol=0)
    expect_depth = torch.where(alpha > 0, torch.full_like(alpha, z), torch.zeros_like(alpha))
    torch.testing.assert_close(out.depth, expect_depth, atol=1e-12, rtol=0)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("seed", [0, 1])
def test_matches_naive_per_pixel_reference(seed: int, backend: str) -> None:
    gm = random_map(40, seed=seed, scale=(0.05, 0.2))
    gm.opacity_logits.data += 3.0  # opaque: exercises the transmittance stop and 0.99 clamp
    cam = make_camera(w=20, h=18)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=F64)
    out = render(gm, cam, background=bg, tile_size=8, backend=backend)
    ref = naive_render(gm, cam, bg)
    torch.testing.assert_close(out.rgb, ref, atol=1e-12, rtol=0)


def test_tile_size_and_chunking_do_not_change_the_image() -> None:
    gm = random_map(80, seed=3)
    cam = make_camera(w=24, h=20)
    a = render(gm, cam, tile_size=8, backend="torch").rgb
    b = render(gm, cam, tile_size=8, max_elements=500, backend="torch").rgb
    torch.testing.assert_close(a, b, atol=1e-12, rtol=0)


def test_sh_colour_is_view_dependent_and_clamped() -> None:
    sh = torch.zeros(2, 4, 3, dtype=F64)
    sh[:, 0] = -5.0  # DC far below: clamped to 0
    sh[1, 0] = 0.0
    sh[1, 3] = 1.0  # -C1 * x
    dirs = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]], dtype=F64)
    col = eval_sh_colors(sh, dirs)
    assert torch.all(col[0] == 0)
    torch.testing.assert_close(col[1], torch.full((3,), 0.5 + 0.4886025119029199, dtype=F64))


def _loss(out) -> torch.Tensor:  # a generic scalar of every output
    wts = torch.sin(torch.arange(out.rgb.numel(), dtype=out.rgb.dtype)).reshape(out.rgb.shape)
    return (out.rgb * wts).sum() + 0.3 * (out.alpha**2).sum() + 0.1 * out.depth.sum()


@pytest.mark.parametrize("backend", BACKENDS)
def test_analytic_backward_matches_autograd(backend: str) -> None:
    gm = random_map(60, seed=5, deg=2)
    cam0 = make_camera(w=24, h=20)
    grads = {}
    for mode in ("analytic", "autograd"):
        g = gm.clone().requires_grad_()
        c2w = cam0.c2w.clone().requires_grad_()
        out = render(g, cam0.with_pose(c2w), background=torch.tensor([0.1, 0.2, 0.3], dtype=F64),
                     backward=mode, max_elements=3000,
                     backend=backend if mode == "analytic" else "torch")  # fmt: skip
        grads[mode] = torch.autograd.grad(_loss(out), [*g.tensors().values(), c2w])
    for a, b in zip(grads["analytic"], grads["autograd"], strict=True):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-9)


@pytest.mark.gradcheck
@pytest.mark.parametrize("field", ["means", "log_scales", "quats", "opacity_logits", "sh", "pose"])
def test_gradcheck_every_field_and_pose(field: str) -> None:
    """The reference path (the kernels': tests/nbv/test_kernels.py)."""
    gm = random_map(6, seed=7, scale=(0.1, 0.2))
    cam = make_camera(w=10, h=9)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=F64)

    def fn(x: torch.Tensor) -> torch.Tensor:
        if field == "pose":
            out = render(gm, cam.with_pose(x), background=bg, backend="torch")
        else:
            params = gm.tensors()
            params[field] = x
            out = render(GaussianMap(**params), cam, background=bg, backend="torch")
        return torch.cat([out.rgb.flatten(), out.alpha.flatten(), out.depth.flatten()])

    x0 = (cam.c2w if field == "pose" else getattr(gm, field)).clone().requires_grad_()
    assert torch.autograd.gradcheck(fn, (x0,), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_pose_gradient_matches_finite_differences_float32_scene() -> None:
    gm = random_map(50, seed=11, dtype=torch.float32)
    cam = make_camera(w=16, h=16, dtype=torch.float32)
    c2w64 = cam.c2w.double()

    def loss(c2w: torch.Tensor) -> torch.Tensor:
        return render(gm.to(dtype=F64), cam.to(dtype=F64).with_pose(c2w)).rgb.square().sum()

    x = c2w64.clone().requires_grad_()
    (g,) = torch.autograd.grad(loss(x), x)
    eps = 1e-6
    for i, j in [(0, 3), (1, 3), (2, 3), (0, 1), (2, 0)]:
        e = torch.zeros(4, 4, dtype=F64)
        e[i, j] = eps
        fd = (loss(c2w64 + e) - loss(c2w64 - e)) / (2 * eps)
        assert abs(float(fd) - float(g[i, j])) <= 1e-4 * max(1.0, abs(float(fd)))


def test_features_are_composited_like_colour() -> None:
    gm = random_map(30, seed=2, deg=0)
    cam = make_camera()
    feats = torch.rand(30, 2, dtype=F64)
    out = render(gm, cam, features=feats)
    assert out.features is not None and out.features.shape == (cam.height, cam.width, 2)
    # a constant feature composites to alpha (zero background)
    ones = render(gm, cam, features=torch.ones(30, dtype=F64))
    assert ones.features is not None
    torch.testing.assert_close(ones.features[..., 0], ones.alpha, atol=1e-12, rtol=0)


def test_culls_behind_camera_and_empty_scene() -> None:
    gm = random_map(10, seed=1)
    gm.means.data[:, 2] = -10.0  # all far behind a camera at the origin looking along +z
    cam = Camera.from_c2w(torch.eye(4, dtype=F64), fx=10, fy=10, cx=8, cy=8, width=16, height=16)
    out = render(gm, cam, background=torch.tensor([0.5, 0.5, 0.5], dtype=F64))
    assert int(out.radii.sum()) == 0
    torch.testing.assert_close(out.rgb, torch.full((16, 16, 3), 0.5, dtype=F64))
    assert torch.isfinite(out.depth).all()


def test_bad_arguments() -> None:
    gm = random_map(5)
    cam = make_camera()
    with pytest.raises(TypeError, match="gmap"):
        render("not a map", cam)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="features"):
        render(gm, cam, features=torch.ones(4, 2, dtype=F64))
    with pytest.raises(ValueError, match="backward"):
        render(gm, cam, backward="nope")  # type: ignore[arg-type]
