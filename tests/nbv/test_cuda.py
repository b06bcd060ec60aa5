"""The same maths on CUDA as on the CPU (skipped without a GPU)."""

from __future__ import annotations

import pytest
import torch

from agilegs.config.selection import FIELD_NAMES
from agilegs.service.nbv import (
    Camera,
    GaussianMap,
    fisher_diag,
    init_information,
    look_at,
    render,
    select,
)
from agilegs.service.nbv.candidates import capture_pool
from agilegs.service.nbv.methods.fisherrf import fisherrf_hessian

pytestmark = [pytest.mark.cuda,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]
F64 = torch.float64


def _world(device: str):
    g = torch.Generator().manual_seed(0)
    n = 300
    gm = GaussianMap(
        means=0.4 * torch.randn(n, 3, generator=g, dtype=F64),
        log_scales=torch.log(torch.rand(n, 3, generator=g, dtype=F64) * 0.05 + 0.02),
        quats=torch.randn(n, 4, generator=g, dtype=F64),
        opacity_logits=torch.randn(n, generator=g, dtype=F64),
        sh=torch.randn(n, 4, 3, generator=g, dtype=F64) * 0.3,
    )
    c2w = look_at(torch.tensor([0.3, -0.4, -2.0], dtype=F64), torch.zeros(3, dtype=F64))
    cam = Camera.from_c2w(c2w, fx=30.0, fy=30.0, cx=16.0, cy=15.0, width=32, height=30)
    return gm.to(device=device), cam.to(device=device)


def test_render_backward_and_fisher_match_the_cpu() -> None:
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=F64)
    out = {}
    for dev in ("cpu", "cuda"):
        gm, cam = _world(dev)
        g = gm.clone().requires_grad_()
        r = render(g, cam, background=bg.to(dev))
        grads = torch.autograd.grad(r.rgb.square().sum(), list(g.tensors().values()))
        out[dev] = (r.rgb, grads, fisher_diag(gm, cam, background=bg.to(dev)),
                    fisherrf_hessian(gm, cam, background=bg.to(dev)))
    (rgb_c, gr_c, f_c, h_c), (rgb_g, gr_g, f_g, h_g) = out["cpu"], out["cuda"]
    assert rgb_g.is_cuda
    torch.testing.assert_close(rgb_g.cpu(), rgb_c, atol=1e-10, rtol=0)
    for a, b in zip(gr_g, gr_c):
        torch.testing.assert_close(a.cpu(), b, atol=1e-9, rtol=1e-7)
    for k in FIELD_NAMES:
        torch.testing.assert_close(f_g[k].cpu(), f_c[k], atol=1e-9, rtol=1e-7)
    for k in h_c:
        torch.testing.assert_close(h_g[k].cpu(), h_c[k], atol=1e-9, rtol=1e-7)


@pytest.mark.parametrize("method", ["full_eig", "fisherrf", "cover", "agile", "agile_plus"])
def test_select_on_cuda(method: str) -> None:
    gm, cam = _world("cuda")
    pool = capture_pool([0.0, 0.0, 0.0], 2.0, 16, seed=0, dtype=F64).cuda()
    h = init_information(gm, 1e-3)
    sel = select(method, gm, h, pool, cam.intrinsics, acquired=pool[:2], lam=1e-3)
    ref = select(method, gm.to(device="cpu"), {k: v.cpu() for k, v in h.items()}, pool.cpu(),
                 cam.intrinsics, acquired=pool[:2].cpu(), lam=1e-3)
    assert sel.index == ref.index
