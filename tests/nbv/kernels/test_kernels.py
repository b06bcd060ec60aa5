"""The compiled CPU kernels (backend "numba") against the pure-torch reference (backend
"torch"): renders, gradients, the Fisher and its screen moments, FisherRF's Hessian, the
analytic projection Jacobian, threads, and which backend serves which call."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import camera, random_map

from agilegs.config.selection import FIELD_NAMES
from agilegs.service.nbv import GaussianMap, fisher_diag, render
from agilegs.service.nbv.information import projection_jacobians, screen_second_moments
from agilegs.service.nbv.kernels import backend
from agilegs.service.nbv.methods.fisherrf import fisherrf_hessian

F64 = torch.float64
F32 = torch.float32


def tol(dtype: torch.dtype) -> dict[str, float]:
    return {"atol": 1e-11, "rtol": 1e-10} if dtype == F64 else {"atol": 2e-5, "rtol": 2e-5}


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    scale = b.abs().max()
    assert scale > 0
    return float((a.double() - b.double()).abs().max() / scale)


# ----------------------------------------------------------------------------- render
@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize("tile", [8, 5])
def test_render_matches_torch(dtype: torch.dtype, tile: int) -> None:
    gm = random_map(60, seed=1, deg=2, dtype=dtype)
    cam = camera(dtype=dtype)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=dtype)
    feats = torch.rand(60, 2, generator=torch.Generator().manual_seed(3), dtype=F64).to(dtype)
    k = render(gm, cam, background=bg, features=feats, tile_size=tile, backend="numba")
    t = render(gm, cam, background=bg, features=feats, tile_size=tile, backend="torch")
    assert float(t.alpha.max()) > 0.9  # opaque enough to stop some pixels
    for name in ("rgb", "alpha", "depth", "features", "means2d", "depths"):
        torch.testing.assert_close(getattr(k, name), getattr(t, name), **tol(dtype))
        assert getattr(k, name).dtype == dtype
    assert torch.equal(k.radii, t.radii)


def _loss(out, feats: bool = True) -> torch.Tensor:
    """A generic scalar of every output."""
    w = torch.sin(torch.arange(out.rgb.numel(), dtype=out.rgb.dtype)).reshape(out.rgb.shape)
    total = (out.rgb * w).sum() + 0.3 * (out.alpha ** 2).sum() + 0.1 * out.depth.sum()
    if feats and out.features is not None:
        total = total + (out.features * out.features).sum()
    return total


@pytest.mark.parametrize("pose", [False, True])
def test_render_gradients_match_torch_autograd_float64(pose: bool) -> None:
    gm = random_map(50, seed=2, deg=3)
    cam0 = camera()
    feats0 = torch.rand(50, 1, generator=torch.Generator().manual_seed(4), dtype=F64)
    grads = {}
    for be, mode in (("numba", "analytic"), ("torch", "autograd")):
        g = gm.clone().requires_grad_()
        bg = torch.tensor([0.1, 0.2, 0.3], dtype=F64, requires_grad=True)
        feats = feats0.clone().requires_grad_()
        c2w = cam0.c2w.clone().requires_grad_(pose)
        out = render(g, cam0.with_pose(c2w), background=bg, features=feats, backend=be,
                     backward=mode)
        wrt = [*g.tensors().values(), bg, feats] + ([c2w] if pose else [])
        grads[be] = torch.autograd.grad(_loss(out), wrt)
    for a, b in zip(grads["numba"], grads["torch"], strict=True):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-9)


def test_screen_space_gradient_for_densification() -> None:
    gm = random_map(40, seed=6)
    cam = camera()
    got = {}
    for be in ("numba", "torch"):
        out = render(gm.clone().requires_grad_(), cam, backend=be)
        out.means2d.retain_grad()
        out.rgb.square().sum().backward()
        got[be] = out.means2d.grad
    assert got["numba"] is not None and float(got["numba"].abs().max()) > 0
    torch.testing.assert_close(got["numba"], got["torch"], atol=1e-11, rtol=1e-10)


@pytest.mark.gradcheck
@pytest.mark.parametrize("field", ["means", "log_scales", "quats", "opacity_logits", "sh"])
def test_gradcheck_kernel_path(field: str) -> None:
    gm = random_map(6, seed=7, scale=(0.1, 0.2), opaque=1)
    cam = camera(w=10, h=9)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=F64)

    def fn(x: torch.Tensor) -> torch.Tensor:
        params = gm.tensors()
        params[field] = x
        out = render(GaussianMap(**params), cam, background=bg, backend="numba")
        return torch.cat([out.rgb.flatten(), out.alpha.flatten(), out.depth.flatten()])

    x0 = getattr(gm, field).clone().requires_grad_()
    assert torch.autograd.gradcheck(fn, (x0,), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_threads_do_not_change_the_result() -> None:
    gm = random_map(80, seed=8)
    cam = camera(w=32, h=27)
    before = torch.get_num_threads()
    try:
        outs = []
        for n in (1, 3):
            torch.set_num_threads(n)
            g = gm.clone().requires_grad_()
            out = render(g, cam, backend="numba")
            _loss(out).backward()
            fd = fisher_diag(gm, cam, backend="numba")
            outs.append((out.rgb.detach(), g.means.grad, g.sh.grad, fd["means"], fd["quats"]))
    finally:
        torch.set_num_threads(before)
    for a, b in zip(*outs, strict=True):
        torch.testing.assert_close(a, b, atol=1e-13, rtol=1e-12)


def test_empty_and_invisible_maps() -> None:
    cam = camera()
    empty = GaussianMap(means=torch.zeros(0, 3, dtype=F64), log_scales=torch.zeros(0, 3, dtype=F64),
                        quats=torch.zeros(0, 4, dtype=F64), opacity_logits=torch.zeros(0, dtype=F64),
                        sh=torch.zeros(0, 1, 3, dtype=F64))
    behind = random_map(5, seed=9)
    behind.means.data[:, 2] = -5.0
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=F64)
    for gm in (empty, behind):
        g = gm.clone().requires_grad_()
        out = render(g, cam, background=bg, backend="numba")
        torch.testing.assert_close(out.rgb, bg.expand(cam.height, cam.width, 3))
        assert float(out.alpha.detach().abs().sum()) == 0.0
        out.rgb.sum().backward()
        assert all(float(t.grad.abs().sum()) == 0.0 for t in g.tensors().values())
        fd = fisher_diag(gm, cam, backend="numba")
        assert all(float(v.abs().sum()) == 0.0 for v in fd.values())


# ----------------------------------------------------------------------------- Fisher
@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize("residuals", ["channels", "pixels"])
def test_screen_second_moments_match_torch(dtype: torch.dtype, residuals: str) -> None:
    gm = random_map(50, seed=10, deg=1, dtype=dtype)
    cam = camera(dtype=dtype)
    bg = torch.tensor([0.3, 0.1, 0.7], dtype=dtype)
    k = screen_second_moments(gm, cam, background=bg, residuals=residuals, backend="numba")
    t = screen_second_moments(gm, cam, background=bg, residuals=residuals, backend="torch")
    assert k.shape == (50, 9, 9) and k.dtype == dtype
    assert rel_err(k, t) < (1e-10 if dtype == F64 else 1e-4), rel_err(k, t)


@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize("deg", [0, 3])
def test_fisher_diag_matches_torch(dtype: torch.dtype, deg: int) -> None:
    gm = random_map(50, seed=11 + deg, deg=deg, dtype=dtype)
    cam = camera(dtype=dtype)
    bg = torch.tensor([0.5, 0.2, 0.9], dtype=dtype)
    k = fisher_diag(gm, cam, background=bg, backend="numba")
    t = fisher_diag(gm, cam, background=bg, backend="torch")
    assert set(k) == set(FIELD_NAMES)
    for f in FIELD_NAMES:
        assert k[f].shape == getattr(gm, f).shape and k[f].dtype == dtype
        assert not k[f].requires_grad
        assert rel_err(k[f], t[f]) < (1e-10 if dtype == F64 else 1e-4), (f, rel_err(k[f], t[f]))
    only = fisher_diag(gm, cam, background=bg, fields=["quats", "sh"], backend="numba")
    assert set(only) == {"quats", "sh"}
    torch.testing.assert_close(only["quats"], k["quats"])


def test_fisherrf_hessian_matches_torch() -> None:
    gm = random_map(50, seed=13, deg=2)
    cam = camera()
    bg = torch.tensor([0.2, 0.2, 0.2], dtype=F64)
    k = fisherrf_hessian(gm, cam, background=bg, backend="numba")
    t = fisherrf_hessian(gm, cam, background=bg, backend="torch")
    for f in t:
        assert rel_err(k[f], t[f]) < 1e-10, f


def test_projection_jacobians_match_autograd() -> None:
    gm = random_map(40, seed=14, deg=3)
    gm.means.data[:4, :2] *= 6.0  # outside the 1.3x field of view: the Jacobian's clamp
    gm.sh.data[4:8, 0] = -3.0  # colours clamped at 0
    cam = camera()
    k = projection_jacobians(gm, cam, FIELD_NAMES, backend="numba")
    t = projection_jacobians(gm, cam, FIELD_NAMES, backend="torch")
    for f in FIELD_NAMES:
        assert k[f].shape == t[f].shape
        torch.testing.assert_close(k[f], t[f], atol=1e-12, rtol=1e-10)


# ----------------------------------------------------------------------------- which path
def test_backend_choice(monkeypatch: pytest.MonkeyPatch) -> None:
    gm = random_map(5)
    cam = camera()
    tensors = [*gm.tensors().values(), cam.c2w]
    assert backend.resolve(None, tensors)  # auto: the kernels on CPU float64
    assert not backend.resolve("torch", tensors)
    assert not backend.resolve("auto", tensors, pose_grad=True)
    with pytest.raises(ValueError, match="pose requires grad"):
        backend.resolve("numba", tensors, pose_grad=True)
    half = [gm.means.to(torch.float16)]
    assert not backend.resolve("auto", half)
    with pytest.raises(ValueError, match="float32 or float64"):
        backend.resolve("numba", half)
    with pytest.raises(ValueError, match="backend"):
        backend.resolve("cuda", tensors)  # type: ignore[arg-type]
    monkeypatch.setenv(backend.ENV_VAR, "torch")
    assert backend.default_backend() == "torch"
    assert not backend.resolve(None, tensors)
    monkeypatch.setenv(backend.ENV_VAR, "fast")
    with pytest.raises(ValueError, match=backend.ENV_VAR):
        backend.default_backend()
    monkeypatch.delenv(backend.ENV_VAR)
    backend.set_default_backend("torch")
    try:
        assert not backend.resolve(None, tensors)
    finally:
        backend.set_default_backend(None)
    # numba missing or broken: auto falls back, "numba" says why
    monkeypatch.setattr(backend, "_kernels", None)
    monkeypatch.setattr(backend, "_import_error", "ModuleNotFoundError: numba")
    assert not backend.kernels_available()
    assert not backend.resolve(None, tensors)
    with pytest.raises(ValueError, match="unavailable"):
        backend.resolve("numba", tensors)
    out = render(gm, cam)  # served by torch
    assert out.rgb.shape == (cam.height, cam.width, 3)


def test_reference_paths_stay_torch() -> None:
    gm = random_map(20, seed=15)
    cam = camera()
    with pytest.raises(ValueError, match="autograd"):
        render(gm, cam, backward="autograd", backend="numba")
    # a pose that requires grad: the exact psi's Fisher is differentiated in the pose
    c2w = cam.c2w.clone().requires_grad_()
    fd = fisher_diag(gm, cam.with_pose(c2w), fields=["means"])
    assert fd["means"].requires_grad
    (g,) = torch.autograd.grad(fd["means"].sum(), c2w)
    assert torch.isfinite(g).all() and float(g.abs().max()) > 0
    with pytest.raises(ValueError, match="pose"):
        fisher_diag(gm, cam.with_pose(c2w), backend="numba")


def test_workspace_reuses_and_aligns_its_buffers() -> None:
    ws = backend.Workspace()
    for n in (67, 55, 67, 300, 1, 299):  # smaller after larger, and a buffer grown in place
        a = ws.take("x", (n, 3), np.float32, zero=True)
        assert a.shape == (n, 3) and a.ctypes.data % 64 == 0 and float(np.abs(a).sum()) == 0.0
        a.fill(1.0)
    big = backend.Workspace(limit=1000).take("y", (1000,), np.float64)  # above the limit
    assert big.shape == (1000,)


def test_workspace_is_released() -> None:
    gm = random_map(30, seed=16)
    fisher_diag(gm, camera(), backend="numba")
    assert backend.release_workspace() > 0
    assert backend.release_workspace() == 0
    again = fisher_diag(gm, camera(), backend="numba")
    assert math.isfinite(float(again["means"].sum()))
