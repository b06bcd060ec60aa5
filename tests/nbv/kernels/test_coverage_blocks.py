"""The pool scored in one pass (:func:`agilegs.service.nbv.coverage.coverage_blocks`): every
anchor's coverage matrix through one compiled call, against the reference (one
:func:`~agilegs.service.nbv.coverage.coverage_matrix` per anchor, its blocks scaled and put
side by side), bit for bit, and against the pure-torch path."""

from __future__ import annotations

import math

import pytest
import torch

from agilegs.service.nbv import Intrinsics, look_at
from agilegs.service.nbv.candidates import capture_pool
from agilegs.service.nbv.coverage import (
    _coverage_blocks_reference,
    coverage_blocks,
    support_samples,
)
from agilegs.service.nbv.kernels import backend

INTR = Intrinsics.from_fov(60.0, 48, 40)
DTYPES = [torch.float32, torch.float64]


def _scene(dtype: torch.dtype, weights: list[float]
           ) -> tuple[list[torch.Tensor], torch.Tensor, list[tuple[torch.Tensor, float]]]:
    """Support samples of anchors on an orbit, a pool around the same object (some
    candidates facing away from an anchor: rows of weight zero) and the anchors."""
    g = torch.Generator().manual_seed(7)
    means = (0.4 * torch.randn(3000, 3, generator=g, dtype=torch.float64)).to(dtype)
    pool = capture_pool(torch.zeros(3, dtype=torch.float64), 2.5, 60, seed=2).to(dtype)
    pool[0, :3, 3] = means[0]  # a candidate on a sample: distance 0
    eyes = [[0.0, 0.3, -2.2], [2.0, 0.1, 0.4], [-0.5, -1.8, 1.2]]
    anchors = [(look_at(torch.tensor(e, dtype=dtype), torch.zeros(3, dtype=dtype)), w)
               for e, w in zip(eyes, weights)]
    samples = [support_samples(means, pose, INTR, grid=24, max_samples=300 + 50 * a,
                               generator=torch.Generator().manual_seed(a))
               for a, (pose, _) in enumerate(anchors)]
    samples[-1] = torch.cat([samples[-1], 3.0 * means[:40]])  # some behind or outside
    return samples, pool, anchors


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("weights", [[1.0], [1.0, 0.6, 0.25], [1.0, 0.0, 0.8]])
@pytest.mark.parametrize("gamma", [1.0, 1.5])
def test_one_pass_equals_the_per_anchor_reference(dtype: torch.dtype, weights: list[float],
                                                   gamma: float) -> None:
    if not backend.kernels_available():
        pytest.skip("numba unavailable")
    samples, pool, anchors = _scene(dtype, weights)
    kw = {"sigma_p": 1.2, "gamma": gamma, "eps": 2e-3, "near": 0.01}
    m, rho = coverage_blocks(samples, pool, anchors, INTR, **kw)
    ref_m, ref_rho = _coverage_blocks_reference(samples, pool, anchors, INTR, **kw)
    assert m.dtype == dtype and rho.dtype == dtype
    assert m.shape == (60, sum(x.shape[0] for x in samples))
    # the reference's rows of weight zero are skipped here: some must be, some not
    zero_rows = int((ref_m[:, :samples[0].shape[0]] == 0).all(1).sum())
    assert 0 < zero_rows < 60
    assert torch.equal(m, ref_m)
    assert torch.equal(rho, ref_rho)


@pytest.mark.parametrize("dtype", DTYPES)
def test_one_pass_equals_the_torch_path(dtype: torch.dtype) -> None:
    samples, pool, anchors = _scene(dtype, [1.0, 0.5, 0.3])
    kw = {"sigma_p": 1.2, "gamma": 1.0, "eps": 1e-3, "near": 0.01}
    m, rho = coverage_blocks(samples, pool, anchors, INTR, **kw)
    try:
        backend.set_default_backend("torch")
        slow_m, slow_rho = coverage_blocks(samples, pool, anchors, INTR, **kw)
    finally:
        backend.set_default_backend(None)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(m, slow_m, rtol=tol, atol=tol)
    torch.testing.assert_close(rho, slow_rho, rtol=tol, atol=tol)


def test_one_pass_checks_its_arguments() -> None:
    samples, pool, anchors = _scene(torch.float64, [1.0, 0.5])
    with pytest.raises(ValueError):
        coverage_blocks(samples[:1], pool, anchors[:2], INTR, sigma_p=1.0)
    with pytest.raises(ValueError):
        coverage_blocks(samples[:1], pool, anchors[:1], INTR, sigma_p=0.0)
    assert math.isfinite(float(coverage_blocks(samples[:1], pool, anchors[:1], INTR,
                                               sigma_p=1.0)[0].sum()))
