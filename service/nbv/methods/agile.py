"""AGILE-GS and AGILE-GS+ (paper sections 4-5).

``agile``: the anchor T* = argmax psi (:mod:`agilegs.service.nbv.anchor`), the coverage matrix
M of the eligible candidates against T*'s support samples (:mod:`agilegs.service.nbv.coverage`),
B = M Pi (a fixed seeded Johnson-Lindenstrauss projection), a shortlist of N rows, and the
shortlist's first. ``agile_plus``: the same shortlist reranked by the exact EIG phi; the argmax.
Beside the model's candidates the rerank scores ``probes`` drawn uniformly from the rest of
the pool (``SelectConfig.probes``, adapted along a session from the warm state): when a probe
beats every candidate of the model the model no longer predicts the exact EIG, and the next
event gives the probes more of the N slots; the choice is never worse than the best probe.

The shortlist strategy is ``SelectConfig.shortlist``: ``leverage`` (the paper's greedy ridge
leverage), or the ablations ``knearest`` (the N candidates nearest the anchor under the SE(3)
distance), ``topnorm`` (the N largest ||b_v||) and ``online`` (online lambda-ridge leverage
row sampling). In embodied mode the anchor's starts are drawn from the eligible candidates, so
that the anchor stays in the reachable neighbourhood.
"""

from __future__ import annotations

import time
from typing import Any

import torch
from torch import Tensor

from ..anchor.ascent import find_anchor
from ..anchor.assembly import uniform_subset
from ..anchor.envelope import PoolEnvelope
from ..anchor.fitting import terms_from_state, terms_to_state, typical_fisher_from_views
from ..anchor.records import AnchorInputs
from ..camera import Camera
from ..cancel import checkpoint
from ..coverage import coverage_blocks, jl_projection, support_samples
from ..information import fisher_diag
from ..leverage import greedy_ridge_leverage_gains, online_ridge_leverage, topnorm_shortlist
from ..se3 import pose_distance
from ..spread import farthest_point_order
from .base import MethodResult, SelectionContext, register, timed
from .common import argmax_first
from .objective import objective_scores_keeping_best


def _typical(ctx: SelectionContext, out: dict[str, Any]) -> dict[str, Tensor] | None:
    """The typical Fisher the anchor's typical model uses as is: with
    ``typical_fisher="start_view"``, the warm state's, else one Fisher pass at a typical view
    (the last acquired one, else the first eligible candidate), kept in ``out["state"]`` for
    the next events; None otherwise (from Hhat)."""
    if ctx.config.anchor.typical_fisher != "start_view":
        return None
    typical = ctx.state.get("typical_fisher")
    if typical is None:
        acquired = ctx.acquired
        ref = (
            acquired[-1].to(ctx.gmap.dtype)
            if acquired is not None and acquired.shape[0]
            else ctx.pool[ctx.eligible[0]]
        )
        cam = Camera(c2w=ref, intrinsics=ctx.intrinsics)
        with torch.no_grad():
            hv = fisher_diag(ctx.gmap.detach(), cam, fields=ctx.fields,
                             background=ctx.background)
        typical = typical_fisher_from_views([hv], ctx.fields)
    out["state"]["typical_fisher"] = typical
    return typical


def _anchor_targets(ctx: SelectionContext) -> tuple[Tensor | None, float]:
    """The views the anchor's samples are weighted by under the ``target`` objective (None
    for ``eig``): ``anchor.target_poses`` of the request's targets, else of the pool, a
    farthest-point subsample under ``ctx.rot_weight`` (all of them for 0); and the
    milliseconds the subsample took."""
    if ctx.config.objective != "target":
        return None, 0.0
    targets = ctx.targets if ctx.targets is not None else ctx.pool
    count = int(ctx.config.anchor.target_poses)
    if count == 0 or count >= targets.shape[0]:
        return targets, 0.0
    t0 = time.perf_counter()
    picks = farthest_point_order(targets, None, ctx.rot_weight, count)
    return targets[picks], (time.perf_counter() - t0) * 1e3


def _warm(ctx: SelectionContext) -> Tensor | None:
    """The warm state's anchor [4, 4] when ``warm_start`` and it is a proper one, else None."""
    warm = ctx.state.get("anchor_c2w") if ctx.config.anchor.warm_start else None
    if warm is not None and (
        not isinstance(warm, Tensor) or warm.shape != (4, 4) or not torch.isfinite(warm).all()
    ):
        return None
    return warm


def _anchor(ctx: SelectionContext, lat: dict[str, float], out: dict[str, Any]) -> Tensor:
    """Run the anchor ascent; fills ``out`` (state, details, psi trace, modes) and ``lat``
    (the anchor's stages, :meth:`AnchorResult.report`); returns T* [4, 4]."""
    cfg = ctx.config
    dt = ctx.gmap.dtype
    with timed(lat, "anchor"):
        with timed(lat, "anchor.envelope"):
            envelope = (
                PoolEnvelope.from_pool(ctx.pool, ctx.aim, cfg.anchor.envelope_margin)
                if cfg.anchor.envelope
                else None
            )
        warm = _warm(ctx)
        acquired = ctx.acquired
        targets, subsample_ms = _anchor_targets(ctx)
        res = find_anchor(AnchorInputs(
            ctx.gmap,
            dict(ctx.h_acc),
            ctx.eligible_poses,
            ctx.intrinsics,
            cfg.anchor,
            fields=ctx.fields,
            num_acquired=int(acquired.shape[0]) if acquired is not None else 1,
            envelope=envelope,
            warm_c2w=warm,
            typical=_typical(ctx, out),
            generator=ctx.generator(2),
            acquired=acquired.to(dt) if acquired is not None else None,
            lam=ctx.lam,
            background=ctx.background,
            carried=ctx.state.get("anchor_parts"),
            rates_carried=terms_from_state(
                {k[len("anchor_"):]: v for k, v in ctx.state.items()
                 if isinstance(k, str) and k.startswith("anchor_rates_")}),
            targets=targets,
        ))
        out["state"]["anchor_c2w"] = res.c2w.clone()
        if res.carry is not None:
            out["state"]["anchor_parts"] = res.carry
        if res.rates_carry is not None:  # flat entries, tensors only
            out["state"].update({f"anchor_{k}": v
                                 for k, v in terms_to_state(res.rates_carry).items()})
    stages, details = res.report(ctx.eligible, cfg.anchor)
    lat.update(stages)  # within "anchor", not added to it
    if subsample_ms:
        lat["anchor.targets"] = lat.get("anchor.targets", 0.0) + subsample_ms
    out["details"].update(details)
    out["psi_trace"] = list(res.psi_trace)
    if res.modes is not None and res.modes.shape[0] > 1:
        out["modes"] = (res.modes, res.mode_psi)
    return res.c2w


def _knearest(ctx: SelectionContext, anchor_c2w: Tensor, n_short: int, lat: dict[str, float]
              ) -> tuple[list[int], dict[int, float]]:
    with timed(lat, "scoring"):
        dist = pose_distance(
            ctx.eligible_poses, anchor_c2w.expand(len(ctx.eligible), 4, 4), ctx.rot_weight
        ).to(torch.float64)
        order = torch.sort(dist, stable=True).indices.tolist()[:n_short]
    with timed(lat, "leverage"):
        shortlist = [ctx.eligible[i] for i in order]
        scores = {ctx.eligible[i]: float(dist[i]) for i in order}
    return shortlist, scores


def _support_map(ctx: SelectionContext) -> tuple[Tensor, Tensor]:
    """The means [M, 3] and opacities [M] the support samples are drawn from: the map's, or
    a seeded uniform sample of ``scoring.support_gaussians`` of them (at large maps: the
    nearest mean of each support grid cell is then the sample's)."""
    g = ctx.gmap
    n, m = g.num_gaussians, int(ctx.config.scoring.support_gaussians)
    if 0 < m < n:
        idx = uniform_subset(n, m, ctx.generator(5)).to(g.means.device)
        return g.means.detach()[idx], torch.sigmoid(g.opacity_logits.detach()[idx])
    return g.means, g.opacities.detach()


def _rows(ctx: SelectionContext, anchors: list[tuple[Tensor, float]], lat: dict[str, float],
          details: dict[str, Any]) -> tuple[Tensor, Tensor]:
    """B = M Pi of the eligible candidates [E, d], and of the acquired views that condition
    the leverage shortlist [A, d] (empty unless ``condition_on_acquired``).

    ``anchors``: (pose [4, 4], weight) of each anchor, the best first. With several, M is
    their coverage matrices side by side, each scaled by the square root of its weight (its
    psi over the best one's), so that ||b_v||^2 adds the candidate's coverage of every
    anchor's support samples in proportion to that anchor's psi.
    """
    sc = ctx.config.scoring
    dt = ctx.gmap.dtype
    acquired = ctx.acquired
    with timed(lat, "scoring"):
        sigma_p = sc.sigma_p if sc.sigma_p is not None else 0.5 * ctx.radius
        # the acquired views' rows (scored like the candidates; rows are independent)
        # condition the leverage shortlist: one coverage matrix for both
        n_elig = len(ctx.eligible)
        rows = ctx.eligible_poses
        if (
            ctx.config.shortlist == "leverage"
            and sc.condition_on_acquired
            and acquired is not None
            and acquired.shape[0]
        ):
            rows = torch.cat([rows, acquired.detach().to(dt)])
        means, opacities = _support_map(ctx)
        samples: list[Tensor] = []
        for a, (pose, _) in enumerate(anchors):
            checkpoint()
            samples.append(support_samples(
                means,
                pose,
                ctx.intrinsics,
                opacities=opacities,
                grid=sc.grid,
                ray_samples=sc.ray_samples,
                ray_min_fraction=sc.ray_min_fraction,
                min_opacity=sc.min_opacity,
                near=sc.near,
                max_samples=sc.max_samples,
                generator=ctx.generator(3 + 16 * a),
            ))
        checkpoint()
        m, rho = coverage_blocks(samples, rows, anchors, ctx.intrinsics, sigma_p=sigma_p,
                                 gamma=sc.gamma, eps=sc.eps * ctx.radius, near=sc.near)
        pi = jl_projection(m.shape[1], sc.jl_dim, seed=ctx.config.seed, dtype=dt,
                           device=m.device)
        b_all = m @ pi
    details["support_samples"] = int(m.shape[1])
    details["rho"] = {v: float(r) for v, r in zip(ctx.eligible, rho[:n_elig])}
    return b_all[:n_elig], b_all[n_elig:]


def shortlist(ctx: SelectionContext, anchor_c2w: Tensor, lat: dict[str, float],
              details: dict[str, Any], modes: tuple[Tensor, list[float]] | None = None,
              size: int | None = None) -> tuple[list[int], dict[int, float]]:
    """The shortlist of ``ctx.config.shortlist`` (``size`` candidates, default N) and its
    per-candidate scores (conditional leverage at pick time, ||b||, distance to the anchor,
    or NaN for online). ``modes``: the anchors of distinct modes and their psi (the best,
    ``anchor_c2w``, first), whose support samples the coverage matrix spans together."""
    cfg = ctx.config
    sc = cfg.scoring
    n_short = min(int(cfg.shortlist_size if size is None else size), len(ctx.eligible))
    if cfg.shortlist == "knearest":
        return _knearest(ctx, anchor_c2w, n_short, lat)
    anchors = [(anchor_c2w, 1.0)]
    if modes is not None:
        poses, psi = modes
        top = max(psi[0], 1e-30)
        anchors += [(poses[i], psi[i] / top) for i in range(1, len(psi))]
    b, prior = _rows(ctx, anchors, lat, details)
    with timed(lat, "leverage"):
        bmax = float((b.to(torch.float64) ** 2).sum(1).max())
        ridge = sc.ridge if sc.ridge_absolute else sc.ridge * max(bmax, 1e-30)
        ridge = max(ridge, 1e-300)  # a relative ridge on tiny rows must not underflow to 0
        if cfg.shortlist == "leverage":
            loc, gains = greedy_ridge_leverage_gains(b, n_short, ridge, prior)
        elif cfg.shortlist == "topnorm":
            loc = topnorm_shortlist(b, n_short)
            norms = b.to(torch.float64).norm(dim=1)
            gains = [float(norms[i]) for i in loc]
        else:
            loc = online_ridge_leverage(
                b, n_short, ridge, generator=ctx.generator(4), oversample=sc.online_oversample
            )
            gains = [float("nan")] * len(loc)
        picked = [ctx.eligible[i] for i in loc]
        scores = {v: g for v, g in zip(picked, gains)}
    return picked, scores


def probe_count(ctx: SelectionContext, n_short: int) -> int:
    """How many of the ``n_short`` reranked slots go to probes at this event: the warm
    state's count (``config.probes`` at the first event), at least ``config.probes``, at most
    half of the slots (``n_short`` <= the eligible candidates, so that the model's shortlist
    always leaves enough of them to draw from)."""
    least = int(ctx.config.probes)
    if least == 0:
        return 0
    held = ctx.state.get("probes")
    now = int(held) if isinstance(held, Tensor) and held.numel() == 1 else least
    return max(0, min(max(now, least), n_short // 2))


def draw_probes(ctx: SelectionContext, picked: list[int], n: int) -> list[int]:
    """``n`` eligible candidates outside ``picked``, drawn uniformly (seeded by the event), or
    with ``config.probe_draw = "spread"`` in their farthest-point order from the acquired
    views."""
    if n <= 0:
        return []
    taken = set(picked)
    rest = [v for v in ctx.eligible if v not in taken]
    if ctx.config.probe_draw == "spread":
        far = farthest_point_order(ctx.pool[rest], ctx.acquired, ctx.rot_weight, n)
        return [rest[i] for i in far]
    order = torch.randperm(len(rest), generator=ctx.generator(6))[:n].tolist()
    return [rest[i] for i in order]


def _judge_model(ctx: SelectionContext, phi: Tensor, n_model: int, n_probes: int,
                 out: dict[str, Any]) -> None:
    """Whether the model's shortlist beat the probes under the exact EIG ``phi`` [n_model +
    n_probes] (model first), and the probe count of the next event (in the warm state)."""
    model_best = float(phi[:n_model].max()) if n_model else float("-inf")
    probe_best = float(phi[n_model:].max())
    probe_won = probe_best > model_best
    least, most = int(ctx.config.probes), int(ctx.config.shortlist_size) // 2
    nxt = min(2 * n_probes, most) if probe_won else max(n_probes // 2, least)
    out["state"]["probes"] = torch.tensor(max(nxt, least), dtype=torch.long)
    out["details"].update(probes=n_probes, probe_won=probe_won, model_best_phi=model_best,
                          probe_best_phi=probe_best)


class AgileMethod:
    """AGILE-GS (``rerank=False``) or AGILE-GS+ (``rerank=True``)."""

    uses_information = True

    def __init__(self, name: str, rerank: bool) -> None:
        self.name = name
        self.rerank = rerank

    def __call__(self, ctx: SelectionContext) -> MethodResult:
        lat: dict[str, float] = {}
        out: dict[str, Any] = {"state": {}, "details": {}, "psi_trace": []}
        anchor_c2w = _anchor(ctx, lat, out)
        n_short = min(int(ctx.config.shortlist_size), len(ctx.eligible))
        n_probes = probe_count(ctx, n_short) if self.rerank else 0
        picked, scores = shortlist(ctx, anchor_c2w, lat, out["details"], out.get("modes"),
                                   size=n_short - n_probes)
        index = picked[0]
        chosen: dict[str, Tensor] | None = None
        if self.rerank:
            probes = draw_probes(ctx, picked, n_probes)
            with timed(lat, "rerank"):
                sl = torch.as_tensor(picked + probes, dtype=torch.long)
                phi, chosen = objective_scores_keeping_best(ctx, ctx.pool[sl], lat, "rerank")
            out["details"]["shortlist_scores"] = scores
            if probes:
                _judge_model(ctx, phi, len(picked), len(probes), out)
            picked = picked + probes
            scores = {v: float(p) for v, p in zip(picked, phi)}
            index = picked[argmax_first(phi)]
        return MethodResult(
            index=index,
            shortlist=picked,
            scores=scores,
            anchor_c2w=anchor_c2w,
            psi_trace=out["psi_trace"],
            latency_ms=lat,
            state=out["state"],
            details=out["details"],
            chosen_information=chosen,
        )


register(AgileMethod("agile", rerank=False))
register(AgileMethod("agile_plus", rerank=True))
