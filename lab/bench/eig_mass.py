"""Where a chosen view's EIG mass lies: over which Gaussians the view's
φ(v) = Σ_q log(1 + H_v,q / Ĥ_q) is summed, by their distance from the view and by how many
pool views see them (``agilegs bench run --eig-mass`` records it per event; ``agilegs bench
coverage`` tabulates it).

A Gaussian's share of φ is the sum of its parameter slots' terms. The Gaussians the view
informs (a positive share) are split at their median distance from the view's centre
(``near_share``: the share of φ from the nearer half) and at their median fraction of the
pool's cameras whose frustum holds their mean (``rare_share``: the share from the Gaussians
seen by fewer pool views than that median); ``unseen_share`` is the share from Gaussians no
acquired view informed (their opacity slot of Ĥ still at λ); ``pool_seen_weighted`` and
``pool_seen_mean`` are the fraction of pool views that see a Gaussian, weighted by the view's φ
and unweighted over the Gaussians it informs; ``depth_ratio`` is the φ-weighted mean distance
over the unweighted one.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

from agilegs.service.nbv import GaussianMap, Intrinsics
from agilegs.service.nbv.coverage import frustum_visibility

__all__ = ["eig_mass", "per_gaussian_eig"]


def per_gaussian_eig(h_view: Mapping[str, Tensor], h_acc: Mapping[str, Tensor]) -> Tensor:
    """Each Gaussian's share of φ [N] (float64): Σ over its slots of log(1 + H_v / Ĥ)."""
    out: Tensor | None = None
    for f, hv in h_view.items():
        term = torch.log1p(hv.detach().to(torch.float64) / h_acc[f].detach().to(torch.float64))
        term = term.reshape(term.shape[0], -1).sum(dim=1)
        out = term if out is None else out + term
    assert out is not None
    return out


def eig_mass(
    gmap: GaussianMap,
    h_acc: Mapping[str, Tensor],
    h_view: Mapping[str, Tensor],
    view_c2w: Tensor,
    pool_c2w: Tensor,
    intrinsics: Intrinsics,
    lam: float,
) -> dict[str, Any]:
    """The breakdown of the view's φ (see the module docstring); shares are None when the
    view informs no Gaussian."""
    e = per_gaussian_eig(h_view, h_acc)
    total = float(e.sum())
    out: dict[str, Any] = {"phi": total, "informed": 0, "near_share": None, "rare_share": None,
                           "unseen_share": None, "pool_seen_weighted": None,
                           "pool_seen_mean": None, "depth_ratio": None}
    seen = e > max(total, 0.0) * 1e-12
    if total <= 0 or not bool(seen.any()):
        return out
    means = gmap.means.detach().to(torch.float64)
    dist = (means - view_c2w.detach().to(torch.float64)[:3, 3]).norm(dim=1)
    pool = pool_c2w.detach().to(torch.float64)
    frac = frustum_visibility(means, pool, intrinsics).to(torch.float64).mean(dim=0)
    es, ds, fs = e[seen], dist[seen], frac[seen]
    near = ds <= ds.median()
    rare = fs < fs.median()
    op = h_acc.get("opacity_logits")
    unseen_share = None
    if op is not None:
        never = (op.detach().to(torch.float64) - lam) <= 1e-6 * lam
        unseen_share = float(e[never].sum()) / total
    out.update(
        informed=int(seen.sum()),
        near_share=float(es[near].sum()) / total,
        rare_share=float(es[rare].sum()) / total,
        unseen_share=unseen_share,
        pool_seen_weighted=float((es * fs).sum()) / total,
        pool_seen_mean=float(fs.mean()),
        depth_ratio=float((es * ds).sum() / total / ds.mean()),
    )
    return out
