"""The benchmark's straightforward baselines agree with the rasterizer and the exact Fisher."""

from __future__ import annotations

import pytest
import torch

from agilegs.config.selection import FIELD_NAMES
from agilegs.lab.bench.render_reference import baseline_fisher_diag, baseline_render
from agilegs.service.nbv import Camera, GaussianMap, fisher_diag, look_at, render

F64 = torch.float64


@pytest.mark.heavy
def test_baselines_match_the_fast_paths_float64() -> None:
    g = torch.Generator().manual_seed(3)
    n = 60
    gm = GaussianMap(
        means=torch.rand(n, 3, generator=g, dtype=F64) - 0.5,
        log_scales=torch.log(torch.rand(n, 3, generator=g, dtype=F64) * 0.1 + 0.04),
        quats=torch.randn(n, 4, generator=g, dtype=F64),
        opacity_logits=torch.randn(n, generator=g, dtype=F64) + 1.0,
        sh=torch.randn(n, 4, 3, generator=g, dtype=F64) * 0.4,
    )
    c2w = look_at(torch.tensor([0.3, -0.4, -2.0], dtype=F64), torch.zeros(3, dtype=F64))
    cam = Camera.from_c2w(c2w, fx=22.0, fy=22.0, cx=12.0, cy=11.0, width=24, height=22)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=F64)
    torch.testing.assert_close(baseline_render(gm, cam, bg), render(gm, cam, background=bg).rgb,
                               atol=1e-12, rtol=0)
    slow = baseline_fisher_diag(gm, cam, bg, max_elements=4000)
    fast = fisher_diag(gm, cam, background=bg)
    for k in FIELD_NAMES:
        torch.testing.assert_close(slow[k], fast[k], rtol=1e-8, atol=1e-12 * float(
            fast[k].abs().max()))
