"""The pool's psi, from which the anchor's starts are drawn, in two passes.

The full proxy psi of every candidate costs one kernel pose per candidate over all the
proxy's samples (2-3k). The pool is first ranked by a coarse psi over ``start_samples`` of
those samples (:func:`coarse_proxy`: a systematic subsample drawn in proportion to each
sample's share of psi, ``weight * sum_q log(1 + rate_q * f)`` with f the model's typical
term, reweighted so that the coarse psi is an unbiased estimate of the full one); the full
psi is then evaluated only on the ``start_refined`` best under the coarse one (and on the
coarse pass's best of distinct modes, with several anchors), among which the starts are
chosen. ``start_samples=0`` evaluates the full psi over the whole pool (the reference).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import torch
from torch import Tensor

from .proxy import ProxyPsi

__all__ = ["coarse_proxy", "sample_shares", "two_pass_pool_psi"]


def sample_shares(proxy: ProxyPsi, typical: float | None) -> Tensor:
    """Each sample's share of psi [S] (not normalised): ``weight * sum_q log(1 + rate_q *
    typical)`` for the log forms (per-sample rate [S] or per slot [S, Q]), ``weight`` for the
    linear form or without a typical term."""
    w = proxy.weight.detach().to(torch.float64).clamp_min(0)
    if proxy.rate is None or typical is None or not typical > 0:
        return w
    rate = proxy.rate.detach().to(torch.float64).clamp_min(0)
    c = torch.log1p(rate * typical)
    return w * (c.sum(1) if c.ndim == 2 else c)


def coarse_proxy(proxy: ProxyPsi, samples: int, typical: float | None) -> ProxyPsi | None:
    """``proxy`` over about ``samples`` of its samples, drawn systematically (a fixed offset:
    no random numbers) in proportion to :func:`sample_shares` and reweighted by
    ``count / (samples * p_s)``: an unbiased estimate of the proxy's psi at every pose. None
    when ``samples`` is 0 or at least the proxy's samples (or no sample has a share)."""
    n = int(proxy.means.shape[0])
    if samples <= 0 or samples >= n:
        return None
    share = sample_shares(proxy, typical)
    total = float(share.sum())
    if not total > 0:
        return None
    p = share / total
    u = (torch.arange(samples, dtype=torch.float64, device=p.device) + 0.5) / samples
    idx = torch.searchsorted(torch.cumsum(p, 0), u).clamp_max(n - 1)
    uniq, counts = torch.unique(idx, return_counts=True)
    uniq = uniq[p[uniq] > 0]
    counts = torch.bincount(idx, minlength=n)[uniq]
    dev = proxy.means.device
    scale = counts.to(torch.float64) / (samples * p[uniq])
    keep = uniq.to(dev)
    weight = proxy.weight[keep] * scale.to(device=dev, dtype=proxy.weight.dtype)
    return dataclasses.replace(
        proxy,
        means=proxy.means[keep],
        cov=proxy.cov[keep],
        weight=weight,
        rate=None if proxy.rate is None else proxy.rate[keep],
        axes=None if proxy.axes is None else proxy.axes[keep],
    )


def two_pass_pool_psi(
    proxy: ProxyPsi,
    placed: Tensor,
    *,
    samples: int,
    refined: int,
    typical: float | None,
    values: Callable[[ProxyPsi, Tensor], Tensor],
    also: Callable[[Tensor], Tensor] | None = None,
) -> tuple[Tensor, Tensor | None]:
    """psi of the pool's poses ``placed`` [D, 4, 4] -> ([D], the refined indices [K] or None).

    With a coarse proxy (:func:`coarse_proxy` of ``samples``) and ``refined`` < D: the coarse
    psi of every pose, then the full psi of the ``refined`` best under it and of the indices
    ``also(coarse psi)`` gives (the coarse pass's best of distinct modes); the returned psi
    is the full one there and the coarse one elsewhere. Else the full psi of every pose and
    None. ``values(proxy, poses)`` evaluates a proxy (in parts, with cancellation checks).
    """
    d = int(placed.shape[0])
    coarse = coarse_proxy(proxy, samples, typical) if 0 < refined < d else None
    if coarse is None:
        return values(proxy, placed), None
    rough = values(coarse, placed)
    top = torch.topk(rough, refined).indices
    if also is not None:
        top = torch.cat([top, also(rough).to(top.device)])
    chosen = torch.unique(top)  # sorted, each once
    out = rough.clone()
    out[chosen] = values(proxy, placed[chosen])
    return out, chosen
