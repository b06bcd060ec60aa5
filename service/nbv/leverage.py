"""Shortlists from projected coverage profiles B [D, d] (paper section 4.3).

``greedy_ridge_leverage`` is the paper's Algorithm 1 inner loop: it greedily maximises
``F(L) = log det(lambda I + sum_{v in L} b_v b_v^T)`` by picking, at every step, the row with
the largest conditional ridge-leverage score ``b^T S^-1 b`` and updating ``S^-1`` with
Sherman-Morrison. ``naive_logdet_greedy`` is the slow, obviously correct reference (one
``slogdet`` per candidate per step) that the tests compare it with.

The shortlist ablations live here too: ``topnorm_shortlist`` (the N largest ``||b_v||``) and
``online_ridge_leverage`` (online lambda-ridge leverage row sampling, Cohen, Musco and
Pachocki 2016). The K-nearest ablation needs poses, not B, and lives in ``selectors``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def _check_b(b: Tensor, budget: int, ridge: float) -> None:
    if not isinstance(b, Tensor) or b.ndim != 2:
        raise ValueError(f"B must be a 2-D tensor [D, d], got {getattr(b, 'shape', type(b))}")
    if b.shape[0] == 0:
        raise ValueError("B is empty: the candidate pool has no rows")
    if not torch.isfinite(b).all():
        raise ValueError("B contains NaN or infinite values")
    if isinstance(budget, bool) or int(budget) != budget or int(budget) < 1:
        raise ValueError(f"budget must be an integer >= 1, got {budget!r}")
    if not (float(ridge) > 0 and math.isfinite(float(ridge))):
        raise ValueError(f"ridge must be a positive finite number, got {ridge!r}")


def _prior_matrix(prior: Tensor | None, dim: int, ridge: float, x: Tensor) -> Tensor:
    """``S_0 = ridge I + P^T P`` for prior rows P [A, d] (None or A = 0: ``ridge I``)."""
    s0 = torch.eye(dim, dtype=torch.float64, device=x.device) * float(ridge)
    if prior is not None and prior.shape[0]:
        if prior.ndim != 2 or prior.shape[1] != dim:
            raise ValueError(f"prior must be rows [A, {dim}], got {list(prior.shape)}")
        if not torch.isfinite(prior).all():
            raise ValueError("prior contains NaN or infinite values")
        p = prior.detach().to(torch.float64).to(x.device)
        s0 = s0 + p.T @ p
    return s0


def greedy_ridge_leverage_gains(
    b: Tensor, budget: int, ridge: float, prior: Tensor | None = None
) -> tuple[list[int], list[float]]:
    """Greedy conditional ridge-leverage selection (paper Algorithm 1, lines 6-10).

    Starting from ``S_0 = ridge * I`` (plus ``P^T P`` for ``prior`` rows P [A, d]: the
    shortlist is then conditioned on rows already held, e.g. the acquired views), repeatedly picks
    ``argmax_{v not chosen} b_v^T S^-1 b_v`` (ties to the lowest index) and applies the
    Sherman-Morrison update ``S^-1 <- S^-1 - z z^T / (1 + b^T z)``, ``z = S^-1 b``. The
    scores of all rows are downdated in O(D d) per step, so the whole loop is O(N D d).
    By the matrix determinant lemma each pick is exactly the greedy maximiser of
    ``log det(ridge I + sum b b^T)``.

    Args:
        b: projected profiles, one row per candidate [D, d].
        budget: number of rows to pick (N >= 1); at most D are returned.
        ridge: lambda_G > 0.
        prior: rows [A, d] already in the set (None: none, the paper's plain greedy).

    Returns:
        The picked row indices, in pick order, and each pick's conditional leverage
        ``b_v^T S^-1 b_v`` at the time it was picked.
    """
    _check_b(b, budget, ridge)
    x = b.detach().to(torch.float64)
    n_rows, dim = x.shape
    if prior is None or prior.shape[0] == 0:
        s_inv = torch.eye(dim, dtype=torch.float64, device=x.device) / float(ridge)
    else:
        s_inv = torch.linalg.inv(_prior_matrix(prior, dim, ridge, x))
        s_inv = 0.5 * (s_inv + s_inv.T)
    scores = ((x @ s_inv) * x).sum(dim=1)  # b^T S0^-1 b
    taken = torch.zeros(n_rows, dtype=torch.bool, device=x.device)
    picks: list[int] = []
    gains: list[float] = []
    neg_inf = torch.tensor(-math.inf, dtype=torch.float64, device=x.device)
    for _ in range(min(int(budget), n_rows)):
        masked = torch.where(taken, neg_inf, scores)
        v = int(torch.argmax(masked))  # first maximal index on ties
        picks.append(v)
        gains.append(float(scores[v]))
        taken[v] = True
        z = s_inv @ x[v]
        denom = 1.0 + torch.dot(x[v], z)
        s_inv = s_inv - torch.outer(z, z) / denom
        scores = scores - (x @ z) ** 2 / denom
    return picks, gains


def greedy_ridge_leverage(
    b: Tensor, budget: int, ridge: float, prior: Tensor | None = None
) -> list[int]:
    """The picks of ``greedy_ridge_leverage_gains`` (see there), in pick order."""
    return greedy_ridge_leverage_gains(b, budget, ridge, prior)[0]


def naive_logdet_greedy(
    b: Tensor, budget: int, ridge: float, prior: Tensor | None = None
) -> list[int]:
    """Reference for ``greedy_ridge_leverage``: greedy on log det, one slogdet per candidate.

    O(N D d^3); for tests only. Ties (equal log det to 1e-12 relative) go to the lowest index.
    ``prior`` rows [A, d] start the sum, as in ``greedy_ridge_leverage``.
    """
    _check_b(b, budget, ridge)
    x = b.detach().to(torch.float64)
    n_rows, dim = x.shape
    s = _prior_matrix(prior, dim, ridge, x).cpu()
    picks: list[int] = []
    for _ in range(min(int(budget), n_rows)):
        best, best_val = -1, -math.inf
        for v in range(n_rows):
            if v in picks:
                continue
            val = float(torch.linalg.slogdet(s + torch.outer(x[v], x[v]))[1])
            if best < 0 or val > best_val + 1e-12 * max(1.0, abs(best_val)):
                best, best_val = v, val
        picks.append(best)
        s = s + torch.outer(x[best], x[best])
    return picks


def logdet_objective(b: Tensor, subset: list[int], ridge: float) -> float:
    """``F(L) = log det(ridge I + sum_{v in L} b_v b_v^T) - d log ridge`` (paper eq. 12)."""
    x = b.detach().to(torch.float64)
    dim = x.shape[1]
    s = torch.eye(dim, dtype=torch.float64, device=x.device) * float(ridge)
    if subset:
        rows = x[torch.as_tensor(subset, device=x.device)]
        s = s + rows.T @ rows
    return float(torch.linalg.slogdet(s)[1]) - dim * math.log(float(ridge))


def topnorm_shortlist(b: Tensor, budget: int) -> list[int]:
    """The ``budget`` rows of largest ``||b_v||`` (ablation "top independent norm").

    Ties go to the lowest index (stable sort).
    """
    _check_b(b, budget, 1.0)
    norms = b.detach().to(torch.float64).norm(dim=1)
    order = torch.sort(-norms, stable=True).indices
    return [int(i) for i in order[: min(int(budget), b.shape[0])]]


def online_ridge_leverage(
    b: Tensor,
    budget: int,
    ridge: float,
    *,
    generator: torch.Generator | None = None,
    oversample: float = 1.0,
    epsilon: float = 0.5,
    max_passes: int = 4,
) -> list[int]:
    """Online lambda-ridge leverage row sampling (Cohen, Musco, Pachocki 2016), as a shortlist.

    Rows arrive as a stream (a seeded random permutation of the pool, so that pool order
    carries no bias). Each arriving row gets the online ridge-leverage estimate
    ``l = min(1, (1 + epsilon) b^T (A^T A + ridge I)^-1 b)`` against the rows kept so far
    (``A`` holds kept rows reweighted by ``1/sqrt(p)``) and is kept with probability
    ``p = min(1, c l)``. The oversampling ``c = oversample * budget / d_ridge`` is calibrated
    with the effective dimension ``d_ridge = tr(G (G + ridge I)^-1)``, ``G = B^T B``, so that
    about ``budget`` rows are kept per pass. Sampling stops once ``budget`` rows are kept;
    if a pass ends short, further passes run over the rows not yet kept, and after
    ``max_passes`` the remainder is filled with the highest current online scores.

    Returns:
        Kept row indices in the order they were kept (the stream order).
    """
    _check_b(b, budget, ridge)
    if not (oversample > 0 and epsilon >= 0 and max_passes >= 1):
        raise ValueError("oversample must be > 0, epsilon >= 0 and max_passes >= 1")
    x = b.detach().to(torch.float64).cpu()
    n_rows, dim = x.shape
    target = min(int(budget), n_rows)
    gram = x.T @ x
    eye = torch.eye(dim, dtype=torch.float64)
    d_ridge = float(torch.trace(gram @ torch.linalg.inv(gram + float(ridge) * eye)))
    c = oversample * target / max(d_ridge, 1e-12)
    s_inv = eye / float(ridge)
    kept: list[int] = []
    taken = torch.zeros(n_rows, dtype=torch.bool)
    for _ in range(max_passes):
        order = torch.randperm(n_rows, generator=generator)
        for v in order.tolist():
            if len(kept) >= target:
                return kept
            if taken[v]:
                continue
            z = s_inv @ x[v]
            lev = min(1.0, (1.0 + epsilon) * float(torch.dot(x[v], z)))
            p = min(1.0, c * lev)
            u = float(torch.rand((), generator=generator, dtype=torch.float64))
            if p > 0 and u < p:
                kept.append(v)
                taken[v] = True
                w = x[v] / math.sqrt(p)  # reweighted row of A
                zw = s_inv @ w
                s_inv = s_inv - torch.outer(zw, zw) / (1.0 + torch.dot(w, zw))
    while len(kept) < target:  # deterministic fill: highest current online score
        scores = ((x @ s_inv) * x).sum(dim=1)
        scores[taken] = -math.inf
        v = int(torch.argmax(scores))
        kept.append(v)
        taken[v] = True
        z = s_inv @ x[v]
        s_inv = s_inv - torch.outer(z, z) / (1.0 + torch.dot(x[v], z))
    return kept
