"""Greedy ridge leverage against the naive log-det greedy, ties, ablation shortlists."""

from __future__ import annotations

import math

import pytest
import torch

from agilegs.service.nbv import greedy_ridge_leverage
from agilegs.service.nbv.leverage import (
    logdet_objective,
    naive_logdet_greedy,
    online_ridge_leverage,
    topnorm_shortlist,
)

DTYPES = [torch.float32, torch.float64]


def rows_with_near_duplicates(seed: int, dtype: torch.dtype, d: int = 8) -> torch.Tensor:
    """24 rows: 12 random ones, each followed by a near-duplicate (1e-2 perturbation)."""
    g = torch.Generator().manual_seed(seed)
    base = torch.randn(12, d, generator=g, dtype=torch.float64)
    base = base * torch.rand(12, 1, generator=g, dtype=torch.float64).add(0.2)
    dup = base + 1e-2 * torch.randn(12, d, generator=g, dtype=torch.float64)
    out = torch.stack([base, dup], dim=1).reshape(24, d)
    return out.to(dtype)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("ridge", [1e-2, 1.0])
def test_greedy_matches_naive_logdet(dtype: torch.dtype, seed: int, ridge: float) -> None:
    b = rows_with_near_duplicates(seed, dtype)
    fast = greedy_ridge_leverage(b, 10, ridge)
    slow = naive_logdet_greedy(b, 10, ridge)
    assert fast == slow
    assert len(set(fast)) == 10


def test_greedy_gain_is_log1p_of_leverage() -> None:
    b = rows_with_near_duplicates(3, torch.float64)
    ridge = 0.1
    picks = greedy_ridge_leverage(b, 6, ridge)
    s = torch.eye(b.shape[1], dtype=torch.float64) * ridge
    for q, v in enumerate(picks):
        lev = float(b[v] @ torch.linalg.solve(s, b[v]))
        gain = logdet_objective(b, picks[: q + 1], ridge) - logdet_objective(b, picks[:q], ridge)
        assert gain == pytest.approx(math.log1p(lev), rel=1e-9)
        s = s + torch.outer(b[v], b[v])


def test_near_duplicates_are_passed_over() -> None:
    # row 0 is the largest, row 1 its near-duplicate, row 2 a smaller distinct direction
    b = torch.tensor([[3.0, 0.0], [2.99, 0.01], [0.0, 1.0]], dtype=torch.float64)
    assert greedy_ridge_leverage(b, 2, 1e-2) == [0, 2]
    assert topnorm_shortlist(b, 2) == [0, 1]  # the naive ablation keeps the duplicate


def test_ties_go_to_lowest_index() -> None:
    b = torch.tensor([[0.0, 0.0], [1.0, 1.0], [1.0, 1.0], [0.0, 0.0], [1.0, -1.0]])
    assert greedy_ridge_leverage(b, 5, 0.5) == naive_logdet_greedy(b, 5, 0.5)
    picks = greedy_ridge_leverage(b, 5, 0.5)
    assert picks[0] == 1 and picks.index(1) < picks.index(2)
    assert picks.index(0) < picks.index(3)  # zero rows: lowest index first


def test_budget_larger_than_pool_returns_all() -> None:
    b = torch.randn(4, 3)
    assert sorted(greedy_ridge_leverage(b, 10, 1.0)) == [0, 1, 2, 3]


@pytest.mark.parametrize(
    ("args", "word"),
    [
        ((torch.zeros(0, 3), 2, 1.0), "empty"),
        ((torch.ones(3, 3), 0, 1.0), "budget"),
        ((torch.ones(3, 3), -1, 1.0), "budget"),
        ((torch.ones(3, 3), 2, 0.0), "ridge"),
        ((torch.tensor([[float("nan"), 1.0]]), 1, 1.0), "NaN"),
        ((torch.ones(3), 1, 1.0), "B"),
    ],
)
def test_bad_arguments_raise(args: tuple, word: str) -> None:
    for fn in (greedy_ridge_leverage, naive_logdet_greedy):
        with pytest.raises(ValueError, match=word):
            fn(*args)


def test_topnorm_orders_by_norm_stably() -> None:
    b = torch.tensor([[1.0, 0.0], [0.0, 2.0], [2.0, 0.0], [0.5, 0.0]])
    assert topnorm_shortlist(b, 3) == [1, 2, 0]


def test_online_sampling_is_seeded_and_distinct() -> None:
    b = rows_with_near_duplicates(1, torch.float64)
    a = online_ridge_leverage(b, 8, 0.1, generator=torch.Generator().manual_seed(5))
    c = online_ridge_leverage(b, 8, 0.1, generator=torch.Generator().manual_seed(5))
    assert a == c
    assert len(a) == 8 and len(set(a)) == 8
    assert all(0 <= i < b.shape[0] for i in a)


def test_online_sampling_keeps_high_leverage_rows() -> None:
    # 20 small copies of one direction (ridge leverage ~0.01 each) and 4 orthogonal unit
    # rows (~0.5 each): the sampler keeps rows in proportion to leverage, so the shortlist
    # of 4 is mostly the orthogonal rows, whatever the stream order
    d = 5
    same = torch.zeros(20, d, dtype=torch.float64)
    same[:, 0] = 0.1
    b = torch.cat([same, torch.eye(d, dtype=torch.float64)[1:]])
    hits = 0
    for seed in range(10):
        picks = online_ridge_leverage(b, 4, 1.0, generator=torch.Generator().manual_seed(seed))
        hits += sum(1 for i in picks if i >= 20)
    assert hits >= 30  # of 40 slots; a uniform sampler would average 40 * 4 / 24 ~ 7


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_greedy_with_prior_rows_matches_naive_logdet(dtype: torch.dtype) -> None:
    g = torch.Generator().manual_seed(5)
    b = torch.randn(40, 6, generator=g, dtype=torch.float64).to(dtype)
    prior = torch.randn(3, 6, generator=g, dtype=torch.float64).to(dtype) * 2.0
    fast = greedy_ridge_leverage(b, 8, 0.3, prior)
    assert fast == naive_logdet_greedy(b, 8, 0.3, prior)
    # an empty prior is the plain greedy
    assert greedy_ridge_leverage(b, 8, 0.3, prior[:0]) == greedy_ridge_leverage(b, 8, 0.3)


def test_prior_rows_push_the_first_pick_away_from_what_is_held() -> None:
    b = torch.tensor([[3.0, 0.0], [2.9, 0.1], [0.0, 1.0]], dtype=torch.float64)
    assert greedy_ridge_leverage(b, 1, 1e-2) == [0]
    held = torch.tensor([[3.0, 0.0]], dtype=torch.float64)  # row 0 is already acquired
    assert greedy_ridge_leverage(b, 1, 1e-2, held) == [2]
    with pytest.raises(ValueError, match="prior"):
        greedy_ridge_leverage(b, 1, 1e-2, torch.zeros(1, 3, dtype=torch.float64))


def test_gains_are_the_conditional_leverages_at_pick_time() -> None:
    from agilegs.service.nbv.leverage import greedy_ridge_leverage_gains

    g = torch.Generator().manual_seed(9)
    b = torch.randn(30, 5, generator=g, dtype=torch.float64)
    prior = torch.randn(2, 5, generator=g, dtype=torch.float64)
    picks, gains = greedy_ridge_leverage_gains(b, 6, 0.2, prior)
    assert picks == greedy_ridge_leverage(b, 6, 0.2, prior)
    s = 0.2 * torch.eye(5, dtype=torch.float64) + prior.T @ prior
    for v, gain in zip(picks, gains):  # direct solve, no Sherman-Morrison
        assert gain == pytest.approx(float(b[v] @ torch.linalg.solve(s, b[v])), rel=1e-9)
        s = s + torch.outer(b[v], b[v])
