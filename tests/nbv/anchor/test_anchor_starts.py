"""The anchor's cheap parts against their references: the pool ranked by a coarse psi before
the full one (:mod:`agilegs.service.nbv.anchor.starts`), and the model fitted over a sample
of the map of fixed size (``AnchorConfig.fit_gaussians``)."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from conftest import TINY_INTR as INTR
from conftest import tiny_scene

from agilegs.config.selection import AnchorConfig
from agilegs.service.nbv.anchor.ascent import distinct_best, optimize_anchor
from agilegs.service.nbv.anchor.assembly import assemble_proxy
from agilegs.service.nbv.anchor.records import AnchorInputs
from agilegs.service.nbv.anchor.starts import (
    coarse_proxy,
    sample_shares,
    two_pass_pool_psi,
)
from agilegs.service.nbv.candidates import pool_radius


def _proxy(dtype: torch.dtype = torch.float64, n: int = 600, **changes):
    gmap, pool, acq, h = tiny_scene(n=n, dtype=dtype)
    cfg = AnchorConfig(**{"num_gaussians": 400, **changes})
    inputs = AnchorInputs(gmap, h, pool, INTR, cfg, acquired=acq, lam=1e-6,
                          generator=torch.Generator().manual_seed(0))
    built = assemble_proxy(inputs, inputs.radius, lambda stage: None)
    return built, pool, inputs


def _values(proxy, poses):
    with torch.no_grad():
        return proxy(poses)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_coarse_psi_estimates_the_full_one(dtype: torch.dtype) -> None:
    built, pool, _ = _proxy(dtype)
    proxy, typical = built.proxy, built.model.typical_term
    full = _values(proxy, pool.to(dtype)).double()
    n = int(proxy.means.shape[0])
    assert coarse_proxy(proxy, 0, typical) is None
    assert coarse_proxy(proxy, n, typical) is None
    coarse = coarse_proxy(proxy, n // 3, typical)
    assert coarse is not None and coarse.means.shape[0] <= n // 3
    rough = _values(coarse, pool.to(dtype)).double()
    # unbiased in expectation; a third of the samples, drawn by share: within a few percent
    # and ranking the pool alike
    assert float(((rough - full) / full).abs().mean()) < 0.05
    ra, rb = rough.argsort().argsort().double(), full.argsort().argsort().double()
    assert float(torch.corrcoef(torch.stack([ra, rb]))[0, 1]) > 0.95
    # the estimator's weights: the sum of the shares is kept exactly
    share_full = sample_shares(proxy, typical)
    share_coarse = sample_shares(coarse, typical)
    torch.testing.assert_close(share_coarse.sum(), share_full.sum(), rtol=1e-6 if
                               dtype == torch.float32 else 1e-12, atol=0)


def test_the_two_pass_pool_psi_is_the_full_one_where_refined() -> None:
    built, pool, _ = _proxy()
    proxy, typical = built.proxy, built.model.typical_term
    full = _values(proxy, pool)
    one, none = two_pass_pool_psi(proxy, pool, samples=0, refined=5, typical=typical,
                                  values=_values)
    assert none is None
    torch.testing.assert_close(one, full, rtol=0, atol=0)
    n = int(proxy.means.shape[0])
    psi, refined = two_pass_pool_psi(proxy, pool, samples=n // 3, refined=5,
                                     typical=typical, values=_values,
                                     also=lambda rough: torch.tensor([0, 1]))
    assert refined is not None and {0, 1} <= set(refined.tolist())
    assert 5 <= refined.numel() <= 7
    torch.testing.assert_close(psi[refined], full[refined], rtol=1e-12, atol=0)
    # the full pass's best is among the coarse pass's best
    assert int(torch.argmax(full)) in refined.tolist()


@pytest.mark.parametrize("anchors", [1, 3])
def test_the_starts_are_the_best_refined_candidates(anchors: int) -> None:
    gmap, pool, acq, h = tiny_scene(n=600)
    cfg = AnchorConfig(iterations=0, num_starts=3, anchors=anchors, num_gaussians=400,
                       start_samples=120, start_refined=6)
    res = optimize_anchor(gmap, h, pool, INTR, config=cfg, acquired=acq, lam=1e-6,
                          generator=torch.Generator().manual_seed(0))
    assert res.pool_psi is not None and res.pool_refined is not None
    among = res.pool_refined
    local = res.pool_psi[among]
    if anchors == 1:
        best = among[torch.topk(local, 3).indices].tolist()
    else:
        r = pool_radius(pool)
        best = among[distinct_best(pool[among], local, 3, cfg.mode_separation * r, r)].tolist()
    assert res.diagnostics.start_indices == best
    assert res.psi == pytest.approx(float(local.max()), rel=1e-9)
    # the same anchor as the full pass over the pool where its best is refined
    ref = optimize_anchor(gmap, h, pool, INTR, config=dataclasses.replace(cfg, start_samples=0),
                          acquired=acq, lam=1e-6, generator=torch.Generator().manual_seed(0))
    assert ref.pool_refined is None
    if ref.diagnostics.start_indices[0] in among.tolist():
        assert res.diagnostics.start_indices[0] == ref.diagnostics.start_indices[0]


def test_the_fit_sample_estimates_the_whole_map() -> None:
    # the model fitted over half of the map: the same proxy psi up to the sample's error
    whole, pool, _ = _proxy(n=1200, fit_gaussians=0, num_gaussians=0)
    half, _, _ = _proxy(n=1200, fit_gaussians=600, num_gaussians=0)
    same, _, _ = _proxy(n=1200, fit_gaussians=1200, num_gaussians=0)
    a = _values(whole.proxy, pool)
    b = _values(half.proxy, pool)
    torch.testing.assert_close(_values(same.proxy, pool), a, rtol=0, atol=0)
    assert half.proxy.means.shape[0] < whole.proxy.means.shape[0]
    rel = ((b - a) / a).abs()  # half of 1200 Gaussians: a few percent, at most a fifth
    assert float(rel.mean()) < 0.08 and float(rel.max()) < 0.25
    ra, rb = a.argsort().argsort().double(), b.argsort().argsort().double()
    assert float(torch.corrcoef(torch.stack([ra, rb]))[0, 1]) > 0.9


def test_the_fit_sample_is_a_uniform_subset() -> None:
    from agilegs.service.nbv.anchor.assembly import uniform_subset

    gen = torch.Generator().manual_seed(0)
    counts = torch.zeros(40)
    for _ in range(4000):
        idx = uniform_subset(40, 8, gen)  # the draws' path
        assert idx.numel() == 8 and bool((idx[1:] > idx[:-1]).all())
        counts[idx] += 1
    # every index drawn with probability 8 / 40: 800 times each, binomial sd ~25
    assert float((counts - 800).abs().max()) < 125
    assert uniform_subset(10, 7, gen).unique().numel() == 7  # the permutation's path


def test_carried_rates_equal_a_refit() -> None:
    from agilegs.config.selection import FIELD_NAMES
    from agilegs.service.nbv.anchor.fitting import directional_rates

    gmap, pool, acq, h = tiny_scene(n=600)
    kw = dict(near=0.1, edge=2.0, lam=1e-6)
    acq4 = torch.cat([acq, pool[[14]]])
    first = directional_rates(gmap, h, acq4[:2], INTR, FIELD_NAMES, refit_every=3, **kw)
    assert not first.carried and first.carry is not None
    # a view more: its terms added to the carried ones
    nxt = directional_rates(gmap, h, acq4[:3], INTR, FIELD_NAMES, refit_every=3,
                            carried=first.carry, **kw)
    ref = directional_rates(gmap, h, acq4[:3], INTR, FIELD_NAMES, **kw)
    assert nxt.carried and ref.carry is None
    torch.testing.assert_close(nxt.accumulated, ref.accumulated, rtol=1e-12, atol=1e-300)
    assert nxt.typical == pytest.approx(ref.typical, rel=0.02)  # from the views' quantiles
    # every third event refits (the first, then carried twice); other views than the
    # carried ones refit too, and so does another map
    third = directional_rates(gmap, h, acq4, INTR, FIELD_NAMES, refit_every=3,
                              carried=nxt.carry, **kw)
    assert third.carried
    fourth = directional_rates(gmap, h, acq4, INTR, FIELD_NAMES, refit_every=3,
                               carried=third.carry, **kw)
    assert not fourth.carried and fourth.carry is not None and fourth.carry["age"] == 0
    other = directional_rates(gmap, h, acq4[[1, 0, 2]], INTR, FIELD_NAMES, refit_every=3,
                              carried=first.carry, **kw)
    assert not other.carried
    fewer = directional_rates(gmap, h, acq4[:3], INTR, FIELD_NAMES, refit_every=3,
                              carried={**first.carry, "count": 5}, **kw)
    assert not fewer.carried


def test_agile_carries_the_rates_in_its_warm_state() -> None:
    from agilegs.config.selection import SelectConfig
    from agilegs.service.nbv import select

    gmap, pool, acq, h = tiny_scene(n=600)
    cfg = SelectConfig(shortlist_size=4, anchor=AnchorConfig(refit_every=3))
    first = select("agile", gmap, h, pool, INTR, config=cfg, acquired=acq, lam=1e-6)
    assert first.details["rates_carried"] is False
    assert {"anchor_rates_w_sum", "anchor_rates_meta"} <= set(first.state)
    assert all(isinstance(v, torch.Tensor) for k, v in first.state.items()
               if k.startswith("anchor_rates_"))
    more = torch.cat([acq, pool[[first.index]]])
    nxt = select("agile", gmap, h, pool, INTR, config=cfg, acquired=more, lam=1e-6,
                 state=first.state)
    assert nxt.details["rates_carried"] is True
    # without the warm state, or with refit_every=1, a refit
    cold = select("agile", gmap, h, pool, INTR, config=cfg, acquired=more, lam=1e-6)
    assert cold.details["rates_carried"] is False
    every = SelectConfig(shortlist_size=4, anchor=AnchorConfig(refit_every=1))
    again = select("agile", gmap, h, pool, INTR, config=every, acquired=more, lam=1e-6,
                   state=first.state)
    assert "rates_carried" not in again.details
    assert not any(k.startswith("anchor_rates_") for k in again.state)
