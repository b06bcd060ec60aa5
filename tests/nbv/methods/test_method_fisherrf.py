"""FisherRF's Hessian against a brute-force evaluation of the same formula, and the method."""

from __future__ import annotations

import pytest
import torch

from agilegs.config.selection import FISHERRF_FIELDS, FisherRFConfig, SelectConfig
from agilegs.service.nbv import (
    Camera,
    GaussianMap,
    Intrinsics,
    fisher_diag,
    init_information,
    look_at,
    select,
)
from agilegs.service.nbv.methods.fisherrf import fisherrf_hessian, fisherrf_hessian_bruteforce
from agilegs.service.nbv.projection import project_map
from agilegs.service.nbv.rasterize import ALPHA_MIN

F64 = torch.float64


def random_map(n: int, *, seed: int = 0, deg: int = 1) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    return GaussianMap(
        means=torch.rand(n, 3, generator=g, dtype=F64) - 0.5,
        log_scales=torch.log(torch.rand(n, 3, generator=g, dtype=F64) * 0.1 + 0.04),
        quats=torch.randn(n, 4, generator=g, dtype=F64),
        # opacities below 0.99: the brute force's autograd passes nothing through the clamp
        opacity_logits=(torch.randn(n, generator=g, dtype=F64) + 0.5).clamp(max=3.0),
        sh=torch.randn(n, (deg + 1) ** 2, 3, generator=g, dtype=F64) * 0.4,
    )


def camera(w: int = 16, h: int = 14, eye: tuple[float, ...] = (0.3, -0.4, -2.0)) -> Camera:
    c2w = look_at(torch.tensor(eye, dtype=F64), torch.zeros(3, dtype=F64))
    return Camera.from_c2w(c2w, fx=0.9 * w, fy=0.9 * w, cx=w / 2, cy=h / 2 + 0.3, width=w,
                           height=h)


@pytest.mark.parametrize("backend", ["torch", "numba"])
@pytest.mark.parametrize("deg", [0, 1, 3])
@pytest.mark.parametrize("bg", [None, (0.1, 0.5, 0.9)])
def test_fisherrf_hessian_matches_bruteforce_float64(deg: int, bg, backend: str) -> None:
    gm = random_map(30, seed=deg, deg=deg)
    cam = camera()
    background = None if bg is None else torch.tensor(bg, dtype=F64)
    fast = fisherrf_hessian(gm, cam, background=background, backend=backend)
    slow = fisherrf_hessian_bruteforce(gm, cam, background=background)
    assert set(fast) == set(FISHERRF_FIELDS)
    for k in FISHERRF_FIELDS:
        assert fast[k].shape == getattr(gm, k).shape
        scale = slow[k].abs().max()
        assert scale > 0, k
        rel = ((fast[k] - slow[k]).abs().max() / scale).item()
        assert rel <= 1e-6, (k, rel)


def test_fisherrf_hessian_differs_from_the_exact_fisher() -> None:
    # channels summed before squaring, activations chained linearly: not diag(J^T J)
    gm = random_map(30, seed=5)
    cam = camera()
    h = fisherrf_hessian(gm, cam)
    f = fisher_diag(gm, cam)
    for k in ("means", "log_scales", "opacity_logits"):
        assert not torch.allclose(h[k], f[k], rtol=1e-3), k
    # the SH block: per channel, the channel sum's gradient is the channel's own (w), so the
    # colour part agrees with the exact Fisher
    torch.testing.assert_close(h["sh"], f["sh"])


def test_fisherrf_opacity_derivative_ignores_the_alpha_clamp() -> None:
    # one Gaussian of opacity ~0.9997 on black: C_pc = alpha_p c_c, and FisherRF's kernel
    # takes d(sum_c C_pc)/d(sigma) = G_p sum_c c_c even where alpha_p is clamped at 0.99
    gm = GaussianMap(
        means=torch.zeros(1, 3, dtype=F64),
        log_scales=torch.log(torch.full((1, 3), 1.0, dtype=F64)),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64),
        opacity_logits=torch.tensor([8.0], dtype=F64),
        sh=torch.tensor([[[0.5, 0.2, -0.1]]], dtype=F64),
    )
    cam = camera(eye=(0.0, 0.0, -2.0))
    h = fisherrf_hessian(gm, cam, fields=["opacity_logits"])["opacity_logits"]
    p = project_map(gm, cam)
    ys, xs = torch.meshgrid(torch.arange(cam.height, dtype=F64) + 0.5,
                            torch.arange(cam.width, dtype=F64) + 0.5, indexing="ij")
    dx, dy = xs - p.means2d[0, 0], ys - p.means2d[0, 1]
    a, b, c = p.conics[0]
    gauss = torch.exp(-(0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy))
    sig = torch.sigmoid(gm.opacity_logits[0])
    composited = sig * gauss >= ALPHA_MIN
    assert bool((sig * gauss > 0.99).any())  # some pixels are clamped
    csum = p.colors[0].sum()
    expect = ((gauss * csum) ** 2)[composited].sum() * sig * (1 - sig)
    torch.testing.assert_close(h[0], expect)


def test_fisherrf_hessian_rejects_rotation() -> None:
    with pytest.raises(ValueError, match="fields"):
        fisherrf_hessian(random_map(4), camera(), fields=["quats"])
    with pytest.raises(ValueError):
        FisherRFConfig(fields=("quats",))  # type: ignore[arg-type]


def test_fisherrf_selects_the_argmax_of_its_trace_score() -> None:
    gm = random_map(40, seed=3)
    intr = Intrinsics(fx=14.4, fy=14.4, cx=8.0, cy=7.3, width=16, height=14)
    eyes = [(0.3, -0.4, -2.0), (2.0, 0.1, 0.2), (-1.5, 1.0, 1.0), (0.0, 2.0, 0.5),
            (0.1, -2.0, 0.3), (-2.0, -0.3, -0.5)]
    poses = torch.stack([look_at(torch.tensor(e, dtype=F64), torch.zeros(3, dtype=F64))
                         for e in eyes])
    acquired, pool = poses[:2], poses[2:]
    bg = (0.2, 0.3, 0.4)
    cfg = SelectConfig(fisher_background=bg)
    # Hhat is ignored: FisherRF rebuilds its own H_train from the acquired poses
    sel = select("fisherrf", gm, init_information(gm, 1.0), pool, intr, config=cfg,
                 acquired=acquired)
    background = torch.tensor(bg, dtype=F64)
    h_train = {f: torch.zeros_like(getattr(gm, f)) for f in FISHERRF_FIELDS}
    for a in acquired:
        hv = fisherrf_hessian(gm, Camera(c2w=a, intrinsics=intr), background=background)
        for f in FISHERRF_FIELDS:
            h_train[f] += hv[f]
    expect = []
    for pose in pool:
        hv = fisherrf_hessian(gm, Camera(c2w=pose, intrinsics=intr), background=background)
        expect.append(sum(float((hv[f] / (h_train[f] + 1e-6)).sum()) for f in FISHERRF_FIELDS))
    assert sel.index == max(range(len(expect)), key=lambda i: expect[i])
    for i, e in enumerate(expect):
        assert abs(sel.scores[i] - e) <= 1e-9 * abs(e)
    assert sel.latency_ms["information"] > 0 and sel.latency_ms["scoring"] > 0
    assert sel.details["training_views"] == 2
