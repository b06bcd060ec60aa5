"""The proxy's observation models, fitted to Hhat: how much a view at T adds to each Gaussian.

``fitted`` (:func:`observation_rates`): a view at T adds ``g_iq * w_i(T)`` to Gaussian i's
information in slot q; the acquired views give Hhat_iq - lambda_q = g_iq * W_i, so that
H_T,iq / Hhat_iq = r_iq w_i(T) / W_i and psi(T) ~ sum_i P log(1 + a_i w_i(T)), the diagonal
log-det EIG of the model (P parameter slots per Gaussian).

``typical``: one typical single-view Fisher value m_q per parameter slot, c_i = sum_q
log(1 + m_q / Hhat_iq) (:func:`information_weights`) and psi(T) ~ sum_i c_i w_i(T).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..camera import Intrinsics
from ..cancel import checkpoint
from ..gaussians import GaussianMap
from .proxy import DIRECTION_KINDS, ProxyPsi, local_axes
from .visibility import OpacityMaps

__all__ = [
    "FIELD_KINDS",
    "lower_median",
    "slot_medians",
    "DirectionalRates",
    "FittedRates",
    "directional_rates",
    "information_weights",
    "observation_rates",
    "prior_floor",
    "slot_kinds",
    "terms_from_state",
    "terms_to_state",
    "typical_fisher_from_h_acc",
    "typical_fisher_from_views",
]


def lower_median(x: Tensor) -> Tensor:
    """``x.median()`` of a non-empty tensor (the lower of the two middle values), by a
    selection (numpy's introselect) on the CPU instead of a sort; NaNs and other devices go
    to torch."""
    if x.device.type != "cpu" or x.dtype not in (torch.float32, torch.float64):
        return x.median()
    a = x.detach().reshape(-1).numpy()
    if np.isnan(a).any():
        return x.median()
    k = (a.size - 1) // 2
    return torch.as_tensor(np.partition(a, k)[k], dtype=x.dtype)


def slot_medians(g: Tensor, seen: Tensor) -> Tensor:
    """Each column's :func:`lower_median` of ``g`` [N, Q] over its ``seen`` [N, Q] (bool)
    rows, 0 where none is seen -> [Q]; on the CPU the columns are cut by numpy (the same
    elements, so the same medians, at a fraction of torch's boolean indexing)."""
    dt, dev = g.dtype, g.device
    cols = g.detach().T.contiguous()
    mask = seen.T.contiguous()
    if dev.type != "cpu" or dt not in (torch.float32, torch.float64):
        return torch.stack([lower_median(cols[q][mask[q]]) if bool(mask[q].any())
                            else torch.zeros((), dtype=dt, device=dev)
                            for q in range(cols.shape[0])])
    a, m = cols.numpy(), mask.numpy()
    out = []
    for q in range(a.shape[0]):
        x = a[q][m[q]]
        if x.size == 0:
            out.append(torch.zeros((), dtype=dt))
        elif np.isnan(x).any():
            out.append(torch.from_numpy(x).median())
        else:
            k = (x.size - 1) // 2
            out.append(torch.as_tensor(np.partition(x, k)[k], dtype=dt))
    return torch.stack(out)


def prior_floor(flat: Tensor, lam: float | None) -> Tensor:
    """lambda per parameter slot [1, P] of Hhat rows [N, P]: ``lam`` when known, else each
    slot's minimum over Gaussians (exact when some Gaussian is seen by no acquired view)."""
    if lam is not None:
        return torch.full_like(flat[:1], float(lam))
    return flat.amin(dim=0, keepdim=True)


def typical_fisher_from_h_acc(
    h_acc: dict[str, Tensor], num_views: int, fields: tuple[str, ...], max_rows: int = 4096,
    lam: float | None = None,
) -> dict[str, Tensor]:
    """m_q per parameter slot from Hhat alone: median over Gaussians of (Hhat - lambda) / A.

    ``lam``: the lambda in Hhat (None: each slot's minimum over Gaussians, see
    :func:`prior_floor`); only Gaussians with Hhat above lambda enter the median, taken over
    at most ``max_rows`` Gaussians (a fixed stride). ``num_views`` A >= 1 is the number of
    acquired views.
    """
    out: dict[str, Tensor] = {}
    a = max(int(num_views), 1)
    for name in fields:
        h = h_acc[name].detach()
        flat = h.reshape(h.shape[0], -1)
        base = prior_floor(flat, lam)
        if flat.shape[0] > max_rows:  # a fixed stride subsample: the median hardly moves
            flat = flat[:: -(-flat.shape[0] // max_rows)]
        excess = flat - base
        excess = torch.where(
            excess > 1e-6 * base.abs().clamp_min(1e-30),
            excess,
            torch.full_like(excess, float("nan")),
        )
        med = torch.nanmedian(excess, dim=0).values / a
        med = torch.where(torch.isfinite(med), med, flat.mean(dim=0))
        out[name] = med.reshape(h.shape[1:])
    return out


@dataclass
class FittedRates:
    """The fitted observation model of the proxy (``observation_rates``).

    Attributes:
        rate: a_i, per Gaussian [N]: a view at T gives Gaussian i the information ratio
            ``H_T,iq / Hhat_iq ~ a_i * w_i(T)``.
        accumulated: W_i, the proxy terms summed over the acquired poses [N].
        typical: f, the median proxy term of the (Gaussian, acquired view) pairs that see it.
        slots: parameter slots per Gaussian in the fields used (P).
        prior_rate: the rate of a Gaussian no view has seen (Hhat = lambda), with the seen
            Gaussians' median information per unit of footprint.
    """

    rate: Tensor
    accumulated: Tensor
    typical: float
    slots: int
    prior_rate: float = 0.0


@torch.no_grad()
def observation_rates(
    gmap: GaussianMap,
    h_acc: dict[str, Tensor],
    acquired: Tensor,
    intrinsics: Intrinsics,
    fields: tuple[str, ...],
    *,
    near: float,
    edge: float,
    num_occluders: int = 0,
    occ_grid: int = 64,
    occ_tests: tuple[tuple[int, float], ...] = ((1, 0.02),),
    generator: torch.Generator | None = None,
    occluders: Tensor | None = None,
    grid: OpacityMaps | None = None,
    chunk: int = 16,
    lam: float | None = None,
    unseen: str = "quarter_view",
) -> FittedRates:
    """Fit the proxy's observation model to Hhat over the acquired poses [A, 4, 4].

    Model: a view at T adds ``g_iq * w_i(T)`` to Gaussian i's information in slot q, with
    ``w_i(T)`` the proxy's footprint x inside x visible term (``ProxyPsi(per_sample=True)``)
    and ``g_iq`` that Gaussian's information per pixel of footprint. The acquired views give
    ``Hhat_iq - lambda_q = g_iq * W_i``, ``W_i = sum_a w_i(T_a)``, so that

        H_T,iq / Hhat_iq = r_iq * w_i(T) / W_i,   r_iq = (Hhat_iq - lambda_q) / Hhat_iq,

    and ``a_i = mean_q(r_iq) / W_i``. The fit is self-consistent: wherever the proxy's point
    z-buffer lets a hidden Gaussian through, it does so at the acquired poses too, so W_i is
    large and the leak costs little; and a Gaussian that Hhat says no view constrains although
    the proxy saw it (r ~ 0: hidden inside the surface, or too faint) gains nothing. A
    Gaussian the proxy did not see from any acquired pose (W_i below a quarter of the typical
    term f) is modelled by ``unseen``: ``"quarter_view"`` counts it as seen by a quarter of a
    typical view, ``a_i = 4 / f`` (new, but bounded: the exact ``log(1 + H / lambda)`` of such
    a Gaussian depends on lambda); ``"prior"`` gives it the seen Gaussians' median
    information per unit of footprint g_q and its own Hhat, ``a_i = mean_q(g_q / Hhat_iq)``,
    as the exact EIG does.
    ``lam``: lambda_q, the prior in Hhat (None: each slot's minimum over Gaussians,
    :func:`prior_floor`). ``grid`` (the transmittance visibility) or ``occluders`` (the
    z-buffer's occluder means): the same visibility as the proxy it serves.
    """
    n = gmap.num_gaussians
    dt = gmap.dtype
    dev = gmap.means.device
    full = ProxyPsi.build(
        gmap,
        torch.ones(n, dtype=dt, device=dev),
        intrinsics,
        num_samples=0,
        near=near,
        edge=edge,
        generator=generator,
        num_occluders=num_occluders,
        occ_grid=occ_grid,
        occ_tests=occ_tests,
        occluders=occluders,
        grid=grid,
    )
    poses = acquired.detach().to(dt)
    w_sum = torch.zeros(n, dtype=dt, device=dev)
    seen: list[Tensor] = []
    for i in range(0, poses.shape[0], chunk):
        checkpoint()
        w = full(poses[i : i + chunk], per_sample=True)  # [B, N]
        w_sum += w.sum(0)
        seen.append(w[w > 1e-6])
    pos = torch.cat(seen) if seen else torch.zeros(0, dtype=dt, device=dev)
    f_typ = float(pos.median()) if pos.numel() else 1.0
    floor = 0.25 * f_typ
    seen_mask = w_sum >= floor
    r_sum = torch.zeros(n, dtype=dt, device=dev)
    new_sum = torch.zeros(n, dtype=dt, device=dev)
    prior_sum = 0.0
    slots = 0
    for name in fields:
        flat = h_acc[name].detach().to(dt).reshape(n, -1)
        prior = prior_floor(flat, lam)
        excess = (flat - prior).clamp_min(0)
        r_sum += (excess / flat.clamp_min(1e-30)).clamp(0, 1).sum(1)
        if bool(seen_mask.any()):
            g_med = (excess[seen_mask] / w_sum[seen_mask, None]).median(dim=0).values  # [P]
            new_sum += (g_med[None, :] / flat.clamp_min(1e-30)).sum(1)
            prior_sum += float((g_med / prior[0].clamp_min(1e-30)).sum())
        slots += flat.shape[1]
    r = r_sum / max(slots, 1)
    if unseen == "prior" and bool(seen_mask.any()):
        fresh = new_sum / max(slots, 1)
    else:
        fresh = torch.full_like(r, 1 / floor)
    rate = torch.where(seen_mask, r / w_sum.clamp_min(floor), fresh)
    return FittedRates(rate=rate, accumulated=w_sum, typical=f_typ, slots=slots,
                       prior_rate=prior_sum / max(slots, 1))


FIELD_KINDS: dict[str, tuple[int, ...] | None] = {
    "means": (1, 2, 3),
    "log_scales": (4, 5, 6),
}
"""Each parameter block's direction factors (indices into
:data:`~agilegs.service.nbv.anchor.proxy.DIRECTION_KINDS`): a mean's world axes, a scale's
local axes; every other block is isotropic."""


def slot_kinds(h_acc: dict[str, Tensor], fields: tuple[str, ...]) -> Tensor:
    """The direction factor of every parameter slot of ``fields`` [Q], in the order of the
    blocks' flattened rows (``h_acc[name].reshape(N, -1)``, blocks in ``fields`` order)."""
    kinds: list[int] = []
    for name in fields:
        per = int(h_acc[name][0].numel())
        fixed = FIELD_KINDS.get(name)
        kinds += list(fixed) if fixed is not None and len(fixed) == per else [0] * per
    return torch.tensor(kinds, dtype=torch.long)


@dataclass
class DirectionalRates:
    """The directional observation model of the proxy (:func:`directional_rates`).

    Attributes:
        rate: a_iq per Gaussian and parameter slot [N, Q]: a view at T gives slot q of
            Gaussian i the information ratio ``H_T,iq / Hhat_iq ~ a_iq w_i(T) f_q(d_i(T))``.
        kinds: the direction factor of each slot [Q].
        accumulated: W_ik, the proxy terms times each direction factor, summed over the
            acquired poses [N, 7].
        typical: f, the median proxy term of the (Gaussian, acquired view) pairs that see it.
        prior_rate: the rates of a Gaussian no view has seen (Hhat = lambda) [Q]: g_q / lambda_q.
        carry: the accumulated terms to carry to the next event (:func:`directional_rates`).
        carried: whether the terms of earlier views were carried, not recomputed.
    """

    rate: Tensor
    kinds: Tensor
    accumulated: Tensor
    typical: float
    prior_rate: Tensor
    carry: dict[str, Any] | None = None
    carried: bool = False


@torch.no_grad()
def directional_rates(
    gmap: GaussianMap,
    h_acc: dict[str, Tensor],
    acquired: Tensor,
    intrinsics: Intrinsics,
    fields: tuple[str, ...],
    *,
    near: float,
    edge: float,
    grid: OpacityMaps | None = None,
    generator: torch.Generator | None = None,
    chunk: int = 16,
    lam: float | None = None,
    carried: Any = None,
    refit_every: int = 1,
) -> DirectionalRates:
    """Fit the directional observation model to Hhat over the acquired poses [A, 4, 4].

    Model: a view at T adds ``g_iq w_i(T) f_q(d_i(T))`` to slot q of Gaussian i, with
    ``w_i(T)`` the proxy's footprint x inside x visible term, ``d_i(T)`` the ray from T's
    centre to the Gaussian and ``f_q`` the slot's direction factor
    (:func:`~agilegs.service.nbv.anchor.proxy.direction_factors`: 1 for opacity, colour and
    rotation; ``1 - d_k^2`` for a mean's world axis k; ``1 - (d . u_k)^2`` for a scale's
    local axis u_k). The acquired views give ``Hhat_iq - lambda_q = g_iq W_iq`` with
    ``W_iq = sum_a w_i(T_a) f_q(d_i(T_a))``, so ``g_iq = (Hhat_iq - lambda_q) / W_iq`` where
    the acquired views saw that slot (W_iq at least a quarter of the typical term f times
    the factor's typical value), and elsewhere (a Gaussian no acquired view saw, or a mean
    seen only along one axis) the median g_q of the slots that were seen: the information a
    typical view would give it. Then ``a_iq = g_iq / Hhat_iq``: the model's diagonal EIG of a
    view at T is ``sum_iq log(1 + a_iq w_i(T) f_q)``, and a slot that the acquired views left
    unconstrained (Hhat_iq ~ lambda_q) is worth a view that sees it across.

    The accumulated terms W_ik over the acquired views are returned in ``carry`` (tensors
    and numbers, for the warm state); given back as ``carried`` at a later event they are
    extended by the new views' terms instead of recomputed over all views (the typical term
    f then from each view's quantiles), while :func:`_carried_terms` allows: a refit every
    ``refit_every`` events (1: every event).
    """
    n = gmap.num_gaussians
    dt = gmap.dtype
    dev = gmap.means.device
    full = ProxyPsi.build(gmap, torch.ones(n, dtype=dt, device=dev), intrinsics,
                          num_samples=0, near=near, edge=edge, generator=generator, grid=grid)
    axes = local_axes(gmap.quats.detach().to(dt))
    poses = acquired.detach().to(dt)
    kept = _carried_terms(carried, poses, n, refit_every)
    start = 0 if kept is None else int(kept["views"])
    w_sum = (torch.zeros(n, len(DIRECTION_KINDS), dtype=dt, device=dev) if kept is None
             else kept["w_sum"].to(device=dev, dtype=dt).clone())
    seen: list[Tensor] = []
    quant: list[Tensor] = []
    npos: list[Tensor] = []
    for i in range(start, poses.shape[0], chunk):
        checkpoint()
        w, wf = full.terms_and_factors(poses[i : i + min(chunk, poses.shape[0] - i)], axes)
        w_sum += wf  # [N, 7]
        seen.append(w[w > 1e-6])  # w: [B, N]
        for row in w if refit_every > 1 else ():
            q, c = view_quantiles(row)
            quant.append(q)
            npos.append(c)
    quantiles = torch.stack(quant) if quant else torch.zeros(0, QUANTILES, dtype=torch.float64)
    counts = torch.stack(npos) if npos else torch.zeros(0, dtype=torch.float64)
    if kept is None:
        pos = torch.cat(seen) if seen else torch.zeros(0, dtype=dt, device=dev)
        f_typ = float(lower_median(pos)) if pos.numel() else 1.0
        age = 0
    else:  # the views' terms from their quantiles: the carried views' and the new ones'
        quantiles = torch.cat([kept["quantiles"].to(torch.float64), quantiles])
        counts = torch.cat([kept["counts"].to(torch.float64), counts])
        f_typ = weighted_lower_median(quantiles, counts)
        age = int(kept["age"]) + 1
    carry = None if refit_every <= 1 else {
        "count": n, "views": int(poses.shape[0]), "poses": poses.detach().cpu().clone(),
        "w_sum": w_sum.detach().clone(), "quantiles": quantiles, "counts": counts, "age": age}
    # the floor of each factor: a quarter of a typical view, at the factor's mean over a
    # uniform direction (2/3 for 1 - c^2)
    floor = 0.25 * f_typ * torch.tensor([1.0] + [2.0 / 3.0] * 6, dtype=dt, device=dev)
    kinds = slot_kinds(h_acc, fields).to(dev)
    flat = torch.cat([h_acc[name].detach().to(dt).reshape(n, -1) for name in fields], dim=1)
    prior = torch.cat([prior_floor(h_acc[name].detach().to(dt).reshape(n, -1), lam)
                       for name in fields], dim=1)  # [1, Q]
    excess = (flat - prior).clamp_min(0)
    w_slot = w_sum[:, kinds]  # [N, Q]
    seen_slot = w_slot >= floor[kinds]
    g = excess / w_slot.clamp_min(1e-30)
    g_med = slot_medians(g, seen_slot)
    g = torch.where(seen_slot, g, g_med.unsqueeze(0))
    rate = g / flat.clamp_min(1e-30)
    return DirectionalRates(rate=rate, kinds=kinds, accumulated=w_sum, typical=f_typ,
                            prior_rate=g_med / prior[0].clamp_min(1e-30), carry=carry,
                            carried=kept is not None)


QUANTILES = 256
"""Quantiles of each acquired view's positive terms kept with the carried terms (the typical
term f of later events is their weighted median)."""


def view_quantiles(w: Tensor) -> tuple[Tensor, Tensor]:
    """One view's positive terms [N] (above 1e-6) in brief: their :data:`QUANTILES` quantiles
    at the midpoints of equal shares (float64; zeros without any) and their count []."""
    pos = w[w > 1e-6].detach().to(torch.float64).cpu()
    if pos.numel() == 0:
        return torch.zeros(QUANTILES, dtype=torch.float64), torch.zeros((), dtype=torch.float64)
    srt = torch.from_numpy(np.sort(pos.numpy()))
    at = ((torch.arange(QUANTILES, dtype=torch.float64) + 0.5) * (pos.numel() / QUANTILES))
    return srt[at.long().clamp_max(pos.numel() - 1)], torch.tensor(float(pos.numel()),
                                                                  dtype=torch.float64)


def weighted_lower_median(quantiles: Tensor, counts: Tensor) -> float:
    """The lower median of the views' positive terms from their quantiles [V, Q] and counts
    [V] (each quantile standing for count / Q terms); 1 without any term."""
    total = float(counts.sum())
    if not total > 0:
        return 1.0
    vals = quantiles.reshape(-1)
    wts = (counts / quantiles.shape[1]).unsqueeze(1).expand_as(quantiles).reshape(-1)
    order = torch.argsort(vals, stable=True)
    cum = torch.cumsum(wts[order], 0)
    k = int(torch.searchsorted(cum, torch.tensor(0.5 * total, dtype=cum.dtype)))
    return float(vals[order[min(k, vals.numel() - 1)]])


_STATE_PARTS = ("w_sum", "poses", "quantiles", "counts")


def terms_to_state(carry: dict[str, Any]) -> dict[str, Tensor]:
    """:func:`directional_rates`' ``carry`` as flat warm-state entries, tensors only
    (``rates_<part>``, and ``rates_meta``: the Gaussians' count, the views, the age)."""
    out = {f"rates_{k}": carry[k] for k in _STATE_PARTS}
    out["rates_meta"] = torch.tensor([int(carry["count"]), int(carry["views"]),
                                      int(carry["age"])], dtype=torch.long)
    return out


def terms_from_state(state: Any) -> dict[str, Any] | None:
    """The ``carry`` :func:`terms_to_state` flattened into ``state`` (a warm state), or None
    when an entry is missing."""
    if not hasattr(state, "get"):
        return None
    parts = {k: state.get(f"rates_{k}") for k in _STATE_PARTS}
    meta = state.get("rates_meta")
    if not isinstance(meta, Tensor) or meta.numel() != 3 or any(
            not isinstance(v, Tensor) for v in parts.values()):
        return None
    count, views, age = (int(v) for v in meta.tolist())
    return {**parts, "count": count, "views": views, "age": age}


def _carried_terms(carried: Any, poses: Tensor, n: int, refit_every: int
                   ) -> dict[str, Any] | None:
    """The carried accumulated terms (:func:`directional_rates`' ``carry`` of an earlier
    event) when they may serve: fewer than ``refit_every`` - 1 events since the refit, the
    same count of Gaussians ``n``, and the acquired poses [A, 4, 4] the carried ones followed
    by new ones; else None (refit)."""
    if refit_every <= 1 or not isinstance(carried, dict):
        return None
    try:
        views, age = int(carried["views"]), int(carried["age"])
        old = carried["poses"]
        ok = (int(carried["count"]) == n and age + 1 < refit_every
              and 0 < views <= poses.shape[0] and isinstance(old, Tensor)
              and old.shape == (views, 4, 4)
              and carried["w_sum"].shape == (n, len(DIRECTION_KINDS))
              and carried["quantiles"].shape == (views, QUANTILES)
              and bool(torch.allclose(old.to(torch.float64),
                                      poses[:views].detach().cpu().to(torch.float64),
                                      rtol=0, atol=1e-6)))
    except (KeyError, AttributeError, TypeError, ValueError):
        return None
    return carried if ok else None


def typical_fisher_from_views(
    h_views: list[dict[str, Tensor]], fields: tuple[str, ...]
) -> dict[str, Tensor]:
    """m_q per parameter slot: the median nonzero value over Gaussians and the given views."""
    out: dict[str, Tensor] = {}
    for name in fields:
        stack = torch.cat([h[name].detach().reshape(h[name].shape[0], -1) for h in h_views])
        vals = torch.where(stack > 0, stack, torch.full_like(stack, float("nan")))
        med = torch.nanmedian(vals, dim=0).values
        med = torch.where(torch.isfinite(med), med, torch.zeros_like(med))
        out[name] = med.reshape(h_views[0][name].shape[1:])
    return out


def information_weights(
    h_acc: dict[str, Tensor], typical: dict[str, Tensor], fields: tuple[str, ...]
) -> Tensor:
    """c_i = sum_q log(1 + m_q / Hhat_iq) over Gaussian i's parameters in ``fields`` [N]."""
    total: Tensor | None = None
    for name in fields:
        h = h_acc[name].detach()
        m = typical[name].to(h.dtype)
        term = torch.log1p(m.unsqueeze(0) / h.clamp_min(1e-30))
        term = term.reshape(h.shape[0], -1).sum(1)
        total = term if total is None else total + term
    assert total is not None
    return total
