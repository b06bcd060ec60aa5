"""Riemannian gradient ascent of psi on SE(3): the anchor T* = argmax_T psi(T).

The retraction is ``T <- T exp(eta xi^)``, xi the gradient of psi w.r.t. a right-perturbation
twist at 0 (``c2w = T @ se3_exp(xi)``). The twist gradient is measured in the metric
``||xi||^2 = ||v||^2 / r^2 + ||w||^2`` (r the pool's radius, so turning by 1 rad and moving by
one radius count alike); each step has length ``eta`` in that metric and is accepted only if
psi does not decrease (after projection into the pool envelope), otherwise eta is halved up to
``backtracks`` times; an accepted step grows eta by 1.5x (at most ``4 * step_size``). A start
stops after ``iterations`` accepted steps, when no step is accepted, when the relative gain of
a step is below ``min_rel_gain`` or when the gradient vanishes. Starts: the ``num_starts`` best
pool candidates under the proxy, plus the previous anchor (warm start). Several starts ascend
at once, as one batch.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from agilegs.config.selection import FIELD_NAMES, AnchorConfig
from agilegs.config.types import validate_config

from ..camera import Intrinsics
from ..cancel import checkpoint
from ..candidates import pool_radius, scene_center_radius
from ..gaussians import GaussianMap
from ..se3 import hat, pose_distance, project_to_se3, se3_exp
from .carry import fingerprint, pack, settings_key, unpack
from .envelope import PoolEnvelope
from .exact import ExactPsi, exact_psi_fn
from .fitting import (
    directional_rates,
    information_weights,
    observation_rates,
    typical_fisher_from_h_acc,
)
from .line_search import CompiledLineSearch
from .proxy import ProxyPsi, pick_occluders
from .unexplored import unexplored_space
from .visibility import OpacityMaps

__all__ = ["AnchorResult", "ascend", "distinct_best", "optimize_anchor",
           "optimize_anchor_validated"]


POOL_CHUNK = 32
"""Pool candidates whose psi is evaluated at once (the request's deadline is checked between
chunks)."""


@dataclass
class AnchorResult:
    """Outcome of the anchor ascent.

    Attributes:
        c2w: the anchor pose [4, 4].
        psi: psi at the anchor.
        psi_trace: psi of the winning start, at its start and after each accepted step.
        traces: the same for every start.
        starts: the start poses [S, 4, 4].
        evaluations: psi evaluations (batched proxy calls count once per pose).
        pool_psi: the proxy psi of every pool candidate scored for the starts [D] (None for
            the exact psi without a proxy).
        modes: the anchors of distinct modes [M, 4, 4], best first (``c2w`` first; only it
            unless ``config.anchors`` > 1).
        mode_psi: psi at each of ``modes``.
        extra: diagnostics (typical Fisher used; ``timings_s``, the seconds of each stage:
            ``visibility`` (the opacity maps), ``rates`` (the model fitted over the acquired
            views, the importance sample), ``unexplored`` (unexplored space), ``starts``
            (the pool's psi, the starts), ``ascent``); ``ascent_split``, the ascent's
            evaluations with and without the gradient, and their seconds (:func:`ascend`);
            ``carried``, whether the proxy was the previous event's, and ``carry``, the
            parts to keep for the next (with ``carry_over_tolerance`` > 0).
    """

    c2w: Tensor
    psi: float
    psi_trace: list[float]
    traces: list[list[float]]
    starts: Tensor
    evaluations: int
    pool_psi: Tensor | None = None
    modes: Tensor | None = None
    mode_psi: list[float] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)


def _metric_step(grad: Tensor, radius: float, eta: Tensor) -> Tensor:
    """Normalised Riemannian step [B, 6] of length eta in the metric ||v||^2/r^2 + ||w||^2.

    Twists are (v, w): translation first, rotation second (the se3_exp convention).
    """
    g = grad.clone()
    g[:, :3] = g[:, :3] * radius**2  # Riemannian gradient: inverse metric applied
    norm = torch.sqrt((g[:, :3] ** 2).sum(1) / radius**2 + (g[:, 3:] ** 2).sum(1))
    return g * (eta / norm.clamp_min(1e-30)).unsqueeze(1)


def _exp_at_zero(xi: Tensor) -> Tensor:
    """``se3_exp(xi)`` [B, 4, 4] for twists ``xi`` [B, 6] that are zero, with its gradient
    there: ``I + hat(xi)`` (the exponential's first order), the same numbers in either
    pass with fewer operations."""
    return torch.eye(4, dtype=xi.dtype, device=xi.device) + hat(xi)


def ascend(
    psi_fn: Callable[[Tensor], Tensor],
    starts: Tensor,
    *,
    config: AnchorConfig,
    envelope: PoolEnvelope | None,
    radius: float,
    batched: bool = True,
    split: dict[str, float] | None = None,
    compiled: bool = True,
) -> tuple[Tensor, Tensor, list[list[float]], int]:
    """Riemannian gradient ascent of psi from every start pose [S, 4, 4].

    ``psi_fn`` maps poses [B, 4, 4] to psi [B]; with ``batched=False`` it is called one pose
    at a time. Returns the final poses [S, 4, 4], their psi [S], the per-start psi traces
    (one entry per accepted step, never decreasing) and the number of psi evaluations.
    ``split``, when given, receives the poses evaluated with their gradient
    (``gradient_evaluations``) and without (``value_evaluations``), and the seconds of each
    (``gradient_s``, ``value_s``; the compiled line searches count as values).

    Each step's gradients are one batch of the active starts; with ``compiled`` and a
    :class:`ProxyPsi` whose kernel serves (:meth:`ProxyPsi.uses_kernel`), each start's line
    search runs on the compiled kernels (:class:`.line_search.CompiledLineSearch`: each
    trial's step, retraction and projection, then its psi), with a cancellation check
    before each start, and finds the accepted trial, which the reference's operations then
    compute; else the trials of the pending starts are batches through ``psi_fn`` (the
    reference, which the compiled search equals). With ``compiled`` and an
    :class:`.exact.ExactPsi` whose values run on the compiled kernels, the gradients are its
    differences of values (:meth:`.exact.ExactPsi.twist_gradient`); else (and always with
    ``compiled=False``) torch autograd through ``psi_fn``.
    """
    dt = starts.dtype
    tally = split if split is not None else {}
    for key in ("gradient_evaluations", "value_evaluations", "gradient_s", "value_s"):
        tally.setdefault(key, 0.0)

    def values(poses: Tensor) -> Tensor:
        t0 = time.perf_counter()
        with torch.no_grad():
            out = evaluate(poses).detach()
        tally["value_s"] += time.perf_counter() - t0
        tally["value_evaluations"] += poses.shape[0]
        return out

    def evaluate(poses: Tensor) -> Tensor:
        if batched:
            return psi_fn(poses)
        out = []
        for p in poses:
            checkpoint()
            out.append(psi_fn(p.unsqueeze(0))[0])
        return torch.stack(out)

    def twist_grad(poses: Tensor, center: Tensor) -> tuple[Tensor, Tensor]:
        t0 = time.perf_counter()
        if differences:
            assert isinstance(psi_fn, ExactPsi)
            val, g = psi_fn.twist_gradient(poses, envelope=envelope, radius=radius,
                                           center=center)
        else:
            xi = torch.zeros(poses.shape[0], 6, dtype=dt, device=poses.device,
                             requires_grad=True)
            moved = poses @ _exp_at_zero(xi)
            if envelope is not None:
                moved = envelope.project(moved)
            val = evaluate(moved)
            (g,) = torch.autograd.grad(val.sum(), xi)
        tally["gradient_s"] += time.perf_counter() - t0
        tally["gradient_evaluations"] += poses.shape[0]
        return val.detach(), g.detach()

    poses = starts.detach().clone()
    if envelope is not None:
        poses = envelope.project(poses)
    cur = values(poses)
    evals = poses.shape[0]
    traces = [[float(v)] for v in cur]
    eta = torch.full((poses.shape[0],), config.step_size, dtype=dt, device=poses.device)
    active = torch.ones(poses.shape[0], dtype=torch.bool, device=poses.device)
    differences = compiled and isinstance(psi_fn, ExactPsi) and psi_fn.differences(poses)
    searcher = (CompiledLineSearch(psi_fn, config, envelope, radius, dt)
                if compiled and batched and isinstance(psi_fn, ProxyPsi)
                and CompiledLineSearch.serves(psi_fn, poses) else None)

    def line_searches(ids: Tensor, grad: Tensor) -> int:
        """The reference line searches of starts ``ids`` [K] along their twist gradients
        [K, 6]: each trial a batch of the pending starts through ``psi_fn``; returns the
        psi evaluations."""
        n_evals = 0
        gnorm = grad.norm(dim=1)
        step_ok = torch.isfinite(gnorm) & (gnorm > 0)
        accepted = torch.zeros(len(ids), dtype=torch.bool, device=poses.device)
        pending = step_ok.clone()
        loc_eta = eta[ids].clone()
        for _trial in range(config.backtracks + 1):
            checkpoint()
            if not bool(pending.any()):
                break
            pid = torch.nonzero(pending).squeeze(1)
            trial = retract(ids[pid], grad[pid], loc_eta[pid])
            val = values(trial)
            n_evals += len(pid)
            ok = torch.isfinite(val) & (val >= cur[ids[pid]])
            for j, k in enumerate(pid.tolist()):
                if bool(ok[j]):
                    accept(int(ids[k]), trial[j], val[j], float(loc_eta[k]))
                    accepted[k] = True
                    pending[k] = False
                else:
                    loc_eta[k] = loc_eta[k] * 0.5
        for k in range(len(ids)):
            if not bool(accepted[k]):
                active[int(ids[k])] = False
        return n_evals

    def retract(sid: Tensor, grad: Tensor, step: Tensor) -> Tensor:
        """The trial poses [K, 4, 4] of starts ``sid`` [K]: a step of length ``step`` [K]
        along the twist gradients [K, 6], projected into the envelope."""
        xi = _metric_step(grad, radius, step)
        with torch.no_grad():
            trial = poses[sid] @ se3_exp(xi)
            if envelope is not None:
                trial = envelope.project(trial)
        return trial

    def accept(s: int, trial: Tensor, val: Tensor, step: float) -> None:
        gain = float(val - cur[s])
        poses[s] = trial
        old = float(cur[s])
        cur[s] = val
        traces[s].append(float(val))
        eta[s] = min(step * 1.5, 4 * config.step_size)
        if gain <= config.min_rel_gain * abs(old):
            active[s] = False

    def compiled_line_searches(ids: Tensor, grad: Tensor) -> int:
        """The line searches of starts ``ids`` through the compiled kernel, which finds each
        start's accepted trial; the accepted trials then computed by the reference's own
        operations (so that the poses and psi kept are the reference's); a start whose
        trial the reference's check rejects (psi within rounding of the current psi) has
        its line search redone by the reference."""
        assert searcher is not None
        t0 = time.perf_counter()
        found, counts = searcher.search(ids, grad, poses, cur, eta)
        tally["value_s"] += time.perf_counter() - t0
        tally["value_evaluations"] += sum(counts)
        n_evals = sum(counts)
        acc = [k for k, n in enumerate(found) if n > 0]
        redo: list[int] = []
        if acc:
            kk = torch.tensor(acc, dtype=torch.long, device=poses.device)
            halved = torch.tensor([0.5 ** (found[k] - 1) for k in acc], dtype=dt,
                                  device=poses.device)
            loc_eta = eta[ids[kk]] * halved  # the reference's step after found - 1 halvings
            trial = retract(ids[kk], grad[kk], loc_eta)
            t0 = time.perf_counter()
            with torch.no_grad():
                val = evaluate(trial).detach()
            tally["value_s"] += time.perf_counter() - t0
            ok = (torch.isfinite(val) & (val >= cur[ids[kk]])).tolist()
            for j, k in enumerate(acc):
                if ok[j]:
                    accept(int(ids[k]), trial[j], val[j], float(loc_eta[j]))
                else:
                    redo.append(k)
        for k, n in enumerate(found):
            if n == 0:
                active[int(ids[k])] = False
        if redo:
            rr = torch.tensor(redo, dtype=torch.long, device=poses.device)
            n_redo = sum(counts[k] for k in redo)
            tally["value_evaluations"] -= n_redo
            n_evals += line_searches(ids[rr], grad[rr]) - n_redo
        return n_evals

    for _ in range(config.iterations):
        checkpoint()
        if not bool(active.any()):
            break
        ids = torch.nonzero(active).squeeze(1)
        _, grad = twist_grad(poses[ids], cur[ids])
        evals += len(ids)
        if searcher is not None:
            evals += compiled_line_searches(ids, grad)
        else:
            evals += line_searches(ids, grad)
    return poses, cur, traces, evals


def optimize_anchor(
    gmap: GaussianMap,
    h_acc: dict[str, Tensor],
    candidates: Tensor,
    intrinsics: Intrinsics,
    *,
    config: AnchorConfig,
    fields: tuple[str, ...] = FIELD_NAMES,
    num_acquired: int = 1,
    envelope: PoolEnvelope | None = None,
    warm_c2w: Tensor | None = None,
    typical: dict[str, Tensor] | None = None,
    generator: torch.Generator | None = None,
    acquired: Tensor | None = None,
    lam: float | None = None,
    background: Tensor | None = None,
    carried: Any = None,
) -> AnchorResult:
    """Find the anchor T* = argmax psi(T): :func:`optimize_anchor_validated` (same arguments)
    once ``config`` is validated (a ``ValueError`` naming the field)."""
    return optimize_anchor_validated(
        gmap, h_acc, candidates, intrinsics, config=validate_config(AnchorConfig, config),
        fields=fields, num_acquired=num_acquired, envelope=envelope, warm_c2w=warm_c2w,
        typical=typical, generator=generator, acquired=acquired, lam=lam, background=background,
        carried=carried,
    )


def optimize_anchor_validated(
    gmap: GaussianMap,
    h_acc: dict[str, Tensor],
    candidates: Tensor,
    intrinsics: Intrinsics,
    *,
    config: AnchorConfig,
    fields: tuple[str, ...] = FIELD_NAMES,
    num_acquired: int = 1,
    envelope: PoolEnvelope | None = None,
    warm_c2w: Tensor | None = None,
    typical: dict[str, Tensor] | None = None,
    generator: torch.Generator | None = None,
    acquired: Tensor | None = None,
    lam: float | None = None,
    background: Tensor | None = None,
    carried: Any = None,
) -> AnchorResult:
    """Find the anchor T* = argmax psi(T) (see the module docstring), with ``config``
    validated by the caller (:func:`optimize_anchor` validates it).

    Args:
        gmap: the current map.
        h_acc: accumulated information per field (same shapes as the map's fields).
        candidates: pool poses [D, 4, 4] to draw the starts from.
        intrinsics: the candidates' intrinsics.
        config: anchor settings.
        fields: parameter blocks entering psi.
        num_acquired: number of acquired views (scales the ``"h_acc"`` typical Fisher).
        envelope: where the anchor may go (None: anywhere).
        warm_c2w: the previous anchor [4, 4], an extra start when ``config.warm_start``.
        typical: m_q per field to use as is (overrides ``config.typical_fisher``).
        generator: seeds the importance sampling.
        acquired: poses of the acquired views [A, 4, 4], which the ``"fitted"`` model is
            fitted over (without any, the ``"typical"`` model is used).
        lam: the lambda in ``h_acc`` (None: estimated, see ``fitting.prior_floor``).
        background: the background colour [3] Hhat's Fisher was rendered with (the exact
            psi renders with it too; None: black).
        carried: the parts a previous event kept (its ``extra["carry"]``, through the warm
            state), reused while ``config.carry_over_tolerance`` allows (:mod:`.carry`).
    """
    timings: dict[str, float] = {}
    last = [time.perf_counter()]

    def lap(stage: str) -> None:
        now = time.perf_counter()
        timings[stage] = timings.get(stage, 0.0) + (now - last[0])
        last[0] = now
        checkpoint()

    dt = gmap.dtype
    radius = envelope.radius if envelope is not None else pool_radius(candidates)
    extra: dict[str, Any] = {}
    prox_intr = intrinsics
    if config.resolution is not None:
        prox_intr = intrinsics.scaled(
            config.resolution,
            max(1, round(config.resolution * intrinsics.height / intrinsics.width)),
        )
    common: dict[str, Any] = dict(
        near=config.near_fraction * radius,
        edge=config.edge_softness * prox_intr.width,
        generator=generator,
    )
    now: dict[str, Any] | None = None
    key = ""
    reused = None
    if config.carry_over_tolerance > 0 and typical is None:
        now = fingerprint(gmap, h_acc, fields, radius)
        key = settings_key(config, prox_intr, fields)
        reused = unpack(carried, now=now, key=key, tolerance=config.carry_over_tolerance,
                        intrinsics=prox_intr, dtype=dt)
    if reused is not None:
        proxy, kept = reused
        extra.update(kept)
        extra["carry"] = carried
        for stage in ("visibility", "rates", "unexplored"):
            lap(stage)
    else:
        proxy = _build_proxy(gmap, h_acc, prox_intr, common, config=config, fields=fields,
                             num_acquired=num_acquired, typical=typical, generator=generator,
                             acquired=acquired, lam=lam, extra=extra, lap=lap)
        if now is not None:
            extra["carry"] = pack(proxy, extra, now, key)
    extra["carried"] = reused is not None
    # starts: best pool candidates under the proxy (+ the previous anchor)
    with torch.no_grad():
        pool = candidates.detach().to(dt)
        placed = envelope.project(pool) if envelope is not None else pool
        # a cancellation check per chunk
        pool_psi = proxy.values_in_parts(placed, POOL_CHUNK, checkpoint)
    k = min(config.num_starts, pool.shape[0])
    separation = config.mode_separation * radius
    if config.anchors > 1:
        best = distinct_best(pool, pool_psi, k, separation, radius)
    else:
        best = torch.topk(pool_psi, k).indices
    starts = pool[best]
    if config.warm_start and warm_c2w is not None:
        starts = torch.cat([starts, warm_c2w.detach().to(dt).reshape(1, 4, 4)])
    # the ascent moves on SE(3): poses within the wire's tolerance start from the nearest
    # rigid transform
    starts = project_to_se3(starts)
    lap("starts")
    split: dict[str, float] = {}
    if config.psi == "proxy":
        poses, vals, traces, evals = ascend(
            proxy, starts, config=config, envelope=envelope, radius=radius, batched=True,
            split=split,
        )
    else:
        exact = exact_psi_fn(gmap, h_acc, intrinsics, config, fields, background=background)
        poses, vals, traces, evals = ascend(
            exact, starts, config=config, envelope=envelope, radius=radius, batched=False,
            split=split,
        )
    win = int(torch.argmax(vals))
    modes = distinct_best(poses, vals, config.anchors, separation, radius)
    lap("ascent")
    extra["timings_s"] = timings
    extra["ascent_split"] = split
    extra["start_indices"] = [int(i) for i in best]
    extra["proxy_samples"] = int(proxy.means.shape[0])
    return AnchorResult(
        c2w=poses[win].detach(),
        psi=float(vals[win]),
        psi_trace=traces[win],
        traces=traces,
        starts=starts,
        evaluations=evals,
        pool_psi=pool_psi.detach(),
        modes=poses[modes].detach(),
        mode_psi=[float(vals[i]) for i in modes],
        extra=extra,
    )


def _build_proxy(gmap: GaussianMap, h_acc: dict[str, Tensor], prox_intr: Intrinsics,
                 common: dict[str, Any], *, config: AnchorConfig, fields: tuple[str, ...],
                 num_acquired: int, typical: dict[str, Tensor] | None,
                 generator: torch.Generator | None, acquired: Tensor | None,
                 lam: float | None, extra: dict[str, Any],
                 lap: Callable[[str], None]) -> ProxyPsi:
    """The proxy psi of the anchor's settings: its visibility, the model's rates and the
    unexplored space (``lap`` after each stage; diagnostics into ``extra``)."""
    dt = gmap.dtype

    if config.visibility == "transmittance":
        center, r98 = scene_center_radius(gmap.means)
        common["grid"] = OpacityMaps.build(
            gmap, prox_intr, center, r98, cells=config.transmittance_cells,
            bins=config.transmittance_bins, max_occluders=config.occluders,
            generator=generator)
    else:
        common.update(
            num_occluders=config.occluders,
            occ_grid=config.occlusion_grid,
            occ_tests=config.occlusion_tests,
            occluders=pick_occluders(gmap, config.occluders, generator),
        )
    lap("visibility")
    fitted = (
        typical is None
        and config.model in ("fitted", "directional")
        and acquired is not None
        and acquired.shape[0] > 0
    )
    if fitted and config.model == "directional":
        assert acquired is not None
        drate = directional_rates(gmap, h_acc, acquired, prox_intr, fields, lam=lam,
                                  near=common["near"], edge=common["edge"],
                                  grid=common.get("grid"), generator=generator)
        c = torch.log1p(drate.rate * drate.typical).sum(1)
        proxy = ProxyPsi.build(
            gmap, c, prox_intr, num_samples=config.num_gaussians, rate=drate.rate,
            slot_kinds=drate.kinds, **common,
        )
        extra["model"] = "directional"
        extra["typical_term"] = drate.typical
        prior_rate: Tensor = drate.prior_rate
        per_gaussian = 1.0
    elif fitted:
        assert acquired is not None
        fit = observation_rates(gmap, h_acc, acquired, prox_intr, fields, lam=lam,
                                unseen=config.unseen, **common)
        c = fit.slots * torch.log1p(fit.rate * fit.typical)
        proxy = ProxyPsi.build(
            gmap, c, prox_intr, num_samples=config.num_gaussians, rate=fit.rate,
            slots=fit.slots, **common,
        )
        extra["model"] = "fitted"
        extra["typical_term"] = fit.typical
        prior_rate = torch.tensor(fit.prior_rate, dtype=dt)
        per_gaussian = float(fit.slots)
    else:
        if typical is not None:
            extra["typical_source"] = "given"
        else:
            typical = typical_fisher_from_h_acc(h_acc, num_acquired, fields, lam=lam)
            extra["typical_source"] = "h_acc"
        c = information_weights(h_acc, typical, fields)
        proxy = ProxyPsi.build(gmap, c, prox_intr, num_samples=config.num_gaussians, **common)
        extra["model"] = "typical"
    lap("rates")
    if fitted and config.unexplored:
        assert acquired is not None
        space = unexplored_space(gmap, acquired, proxy, cells=config.unexplored_cells,
                                 shells=config.unexplored_shells,
                                 count_inside=config.unexplored_inside, generator=generator)
        if space.means.shape[0]:
            rates = prior_rate.to(dt).expand(space.means.shape[0], *prior_rate.shape)
            proxy = proxy.extended(space.means, space.cov, per_gaussian * space.weight, rates)
        extra["unexplored_fraction"] = space.unexplored_fraction
        extra["unexplored_points"] = int(space.means.shape[0])
    lap("unexplored")
    return proxy


def distinct_best(poses: Tensor, scores: Tensor, k: int, separation: float,
                  radius: float) -> Tensor:
    """Up to ``k`` indices of poses [P, 4, 4], best ``scores`` [P] first, each at least
    ``separation`` (world units) from those before it under the SE(3) distance with
    ``radius`` world units per radian (greedy non-maximum suppression; the best is always
    first)."""
    order = torch.sort(scores.detach(), descending=True, stable=True).indices
    chosen: list[int] = []
    nearest: list[float] = []  # every pose's distance to the nearest chosen one
    n = poses.shape[0]
    for i in order.tolist():
        if len(chosen) >= k:
            break
        if chosen and nearest[i] < separation:
            continue
        chosen.append(i)
        if len(chosen) < k:
            d = pose_distance(poses[i].expand(n, 4, 4), poses, radius).tolist()
            nearest = d if not nearest else [min(a, b) for a, b in zip(nearest, d)]
    return torch.tensor(chosen, dtype=torch.long, device=poses.device)
