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
at once, as one batch (:class:`Ascent`, the reference); with a proxy whose kernel serves, each
start's step is one compiled call (:class:`.compiled_ascent.CompiledAscent`).

:func:`optimize_anchor` checks its arguments into one :class:`.records.AnchorInputs`, and
:func:`find_anchor` finds the anchor from it: the proxy (:mod:`.assembly`), the starts, the
ascent; its :class:`AnchorResult` carries typed diagnostics (:class:`.records.AnchorDiagnostics`),
which :meth:`AnchorResult.report` turns into a selection's latency stages and details.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from agilegs.config.selection import FIELD_NAMES, AnchorConfig

from ..camera import Intrinsics
from ..cancel import checkpoint
from ..gaussians import GaussianMap
from ..se3 import hat, pose_distance, project_to_se3, se3_exp
from .assembly import assemble_proxy
from .compiled_ascent import CompiledAscent
from .envelope import PoolEnvelope
from .exact import ExactPsi, exact_psi_fn
from .line_search import CompiledLineSearch
from .proxy import ProxyPsi
from .records import AnchorDiagnostics, AnchorInputs, AscentTally
from .starts import two_pass_pool_psi

__all__ = ["AnchorResult", "Ascent", "ascend", "distinct_best", "find_anchor",
           "optimize_anchor"]


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
        diagnostics: the model, the stages' seconds, the ascent's split, the starts.
        pool_psi: the proxy psi of every pool candidate scored for the starts [D] (None for
            the exact psi without a proxy): the full psi where ``pool_refined`` says, the
            coarse one elsewhere (:mod:`.starts`).
        pool_refined: the candidates whose full psi was evaluated [K] (None: every one).
        modes: the anchors of distinct modes [M, 4, 4], best first (``c2w`` first; only it
            unless ``config.anchors`` > 1).
        mode_psi: psi at each of ``modes``.
        carry: the parts to keep for the next event (with ``carry_over_tolerance`` > 0,
            :mod:`.carry`), else None.
        rates_carry: the directional model's accumulated terms for the next event (with
            ``refit_every`` > 1), else None.
    """

    c2w: Tensor
    psi: float
    psi_trace: list[float]
    traces: list[list[float]]
    starts: Tensor
    evaluations: int
    diagnostics: AnchorDiagnostics
    pool_psi: Tensor | None = None
    pool_refined: Tensor | None = None
    modes: Tensor | None = None
    mode_psi: list[float] = field(default_factory=list)
    carry: Any = None
    rates_carry: Any = None

    def report(self, eligible: list[int], config: AnchorConfig
               ) -> tuple[dict[str, float], dict[str, Any]]:
        """The anchor's part of a selection: its latency stages within ``anchor`` (ms:
        ``anchor.<stage>``, ``anchor.ascent.gradients``, ``anchor.ascent.values``) and its
        details (``eligible``: the candidate of each pool index; ``config``: the settings
        it was found with). psi at the anchor is set against psi at the best candidate,
        both of the function ascended: the proxy's over every eligible candidate, the exact
        one's over the pool starts."""
        d = self.diagnostics
        stages = {f"anchor.{stage}": sec * 1e3 for stage, sec in d.timings_s.items()}
        stages["anchor.ascent.gradients"] = d.ascent.gradient_s * 1e3
        stages["anchor.ascent.values"] = d.ascent.value_s * 1e3
        details: dict[str, Any] = {"ascent_evaluations": {
            "gradient": int(d.ascent.gradient_evaluations),
            "value": int(d.ascent.value_evaluations)}}
        if self.modes is not None and self.modes.shape[0] > 1:
            details["anchor_modes"] = len(self.mode_psi)
        if config.psi == "proxy" and self.pool_psi is not None and self.pool_psi.numel():
            full = (self.pool_psi if self.pool_refined is None
                    else self.pool_psi[self.pool_refined])
            best_psi: float | None = float(full.max())
        else:
            firsts = [tr[0] for tr in self.traces[:len(d.start_indices)] if tr]
            best_psi = max(firsts) if firsts else None
        details.update(
            anchor_psi=float(self.psi),
            best_candidate_psi=best_psi,
            psi_evaluations=self.evaluations,
            anchor_starts=[eligible[i] for i in d.start_indices],
            proxy_samples=d.proxy_samples,
        )
        if config.carry_over_tolerance > 0:
            details["anchor_carried"] = bool(d.carried)
        if config.refit_every > 1:
            details["rates_carried"] = bool(d.rates_carried)
        if self.pool_refined is not None:
            details["anchor_refined"] = int(self.pool_refined.numel())
        if self.pool_psi is not None:
            details["pool_proxy_psi"] = {v: float(p) for v, p in zip(eligible, self.pool_psi)}
        return stages, details


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


class Ascent:
    """Riemannian gradient ascent of psi from a batch of start poses (the module docstring).

    ``psi_fn`` maps poses [B, 4, 4] to psi [B]; with ``batched=False`` it is called one pose
    at a time. Building the ascent projects the starts [S, 4, 4] into the envelope and
    evaluates them; :meth:`run` then takes the steps. Each step's gradients are one batch of
    the active starts; with ``compiled`` and a :class:`ProxyPsi` whose kernel serves
    (:meth:`ProxyPsi.uses_kernel`), each start's line search runs on the compiled kernels
    (:class:`.line_search.CompiledLineSearch`: each trial's step, retraction and
    projection, then its psi), with a cancellation check before each start, and finds the
    accepted trial, which the reference's operations then compute; else the trials of the
    pending starts are batches through ``psi_fn`` (the reference, which the compiled search
    equals). With ``compiled`` and an :class:`.exact.ExactPsi` whose values run on the
    compiled kernels, the gradients are its differences of values
    (:meth:`.exact.ExactPsi.twist_gradient`); else (and always with ``compiled=False``)
    torch autograd through ``psi_fn``.

    Attributes:
        poses: the current pose of every start [S, 4, 4].
        cur: psi at ``poses`` [S].
        traces: per start, psi at its start and after each accepted step (never decreasing).
        eta: each start's step length in the twist metric [S].
        active: the starts still ascending [S] (bool).
        evaluations: the psi evaluations so far.
        tally: the evaluations with and without the gradient, and their seconds.
    """

    def __init__(self, psi_fn: Callable[[Tensor], Tensor], starts: Tensor, *,
                 config: AnchorConfig, envelope: PoolEnvelope | None, radius: float,
                 batched: bool = True, compiled: bool = True) -> None:
        self.psi_fn = psi_fn
        self.config = config
        self.envelope = envelope
        self.radius = radius
        self.batched = batched
        self.dt = starts.dtype
        self.tally = AscentTally()
        poses = starts.detach().clone()
        if envelope is not None:
            poses = envelope.project(poses)
        self.poses = poses
        self.cur = self._values(poses)
        self.evaluations = poses.shape[0]
        self.traces = [[float(v)] for v in self.cur]
        n, dev = poses.shape[0], poses.device
        self.eta = torch.full((n,), config.step_size, dtype=self.dt, device=dev)
        self.active = torch.ones(n, dtype=torch.bool, device=dev)
        self.differences = (compiled and isinstance(psi_fn, ExactPsi)
                            and psi_fn.differences(poses))
        self.searcher = (CompiledLineSearch(psi_fn, config, envelope, radius, self.dt)
                         if compiled and batched and isinstance(psi_fn, ProxyPsi)
                         and CompiledLineSearch.serves(psi_fn, poses) else None)

    def run(self) -> Ascent:
        """Up to ``config.iterations`` steps of every active start; returns the ascent."""
        for _ in range(self.config.iterations):
            checkpoint()
            if not bool(self.active.any()):
                break
            ids = torch.nonzero(self.active).squeeze(1)
            grad = self._twist_grad(self.poses[ids], self.cur[ids])
            self.evaluations += len(ids)
            if self.searcher is not None:
                self.evaluations += self._compiled_line_searches(ids, grad)
            else:
                self.evaluations += self._line_searches(ids, grad)
        return self

    def _evaluate(self, poses: Tensor) -> Tensor:
        """psi at poses [B, 4, 4] -> [B] (one at a time, with a cancellation check before
        each, unless ``batched``)."""
        if self.batched:
            return self.psi_fn(poses)
        out = []
        for p in poses:
            checkpoint()
            out.append(self.psi_fn(p.unsqueeze(0))[0])
        return torch.stack(out)

    def _values(self, poses: Tensor) -> Tensor:
        """psi at poses [B, 4, 4] -> [B], without gradient (tallied as values)."""
        t0 = time.perf_counter()
        with torch.no_grad():
            out = self._evaluate(poses).detach()
        self.tally.value_s += time.perf_counter() - t0
        self.tally.value_evaluations += poses.shape[0]
        return out

    def _twist_grad(self, poses: Tensor, center: Tensor) -> Tensor:
        """The twist gradients [K, 6] of psi at poses [K, 4, 4] (psi there: ``center`` [K])."""
        t0 = time.perf_counter()
        if self.differences:
            assert isinstance(self.psi_fn, ExactPsi)
            _, g = self.psi_fn.twist_gradient(poses, envelope=self.envelope,
                                              radius=self.radius, center=center)
        else:
            xi = torch.zeros(poses.shape[0], 6, dtype=self.dt, device=poses.device,
                             requires_grad=True)
            moved = poses @ _exp_at_zero(xi)
            if self.envelope is not None:
                moved = self.envelope.project(moved)
            val = self._evaluate(moved)
            (g,) = torch.autograd.grad(val.sum(), xi)
        self.tally.gradient_s += time.perf_counter() - t0
        self.tally.gradient_evaluations += poses.shape[0]
        return g.detach()

    def _retract(self, sid: Tensor, grad: Tensor, step: Tensor) -> Tensor:
        """The trial poses [K, 4, 4] of starts ``sid`` [K]: a step of length ``step`` [K]
        along the twist gradients [K, 6], projected into the envelope."""
        xi = _metric_step(grad, self.radius, step)
        with torch.no_grad():
            trial = self.poses[sid] @ se3_exp(xi)
            if self.envelope is not None:
                trial = self.envelope.project(trial)
        return trial

    def _accept(self, s: int, trial: Tensor, val: Tensor, step: float) -> None:
        """Start ``s`` moves to ``trial`` [4, 4] of psi ``val`` after a step of ``step``: its
        next step 1.5x longer (at most 4 ``step_size``); it stops on a small gain."""
        gain = float(val - self.cur[s])
        self.poses[s] = trial
        old = float(self.cur[s])
        self.cur[s] = val
        self.traces[s].append(float(val))
        self.eta[s] = min(step * 1.5, 4 * self.config.step_size)
        if gain <= self.config.min_rel_gain * abs(old):
            self.active[s] = False

    def _line_searches(self, ids: Tensor, grad: Tensor) -> int:
        """The reference line searches of starts ``ids`` [K] along their twist gradients
        [K, 6]: each trial a batch of the pending starts through ``psi_fn``; returns the
        psi evaluations."""
        n_evals = 0
        gnorm = grad.norm(dim=1)
        step_ok = torch.isfinite(gnorm) & (gnorm > 0)
        accepted = torch.zeros(len(ids), dtype=torch.bool, device=self.poses.device)
        pending = step_ok.clone()
        loc_eta = self.eta[ids].clone()
        for _trial in range(self.config.backtracks + 1):
            checkpoint()
            if not bool(pending.any()):
                break
            pid = torch.nonzero(pending).squeeze(1)
            trial = self._retract(ids[pid], grad[pid], loc_eta[pid])
            val = self._values(trial)
            n_evals += len(pid)
            ok = torch.isfinite(val) & (val >= self.cur[ids[pid]])
            for j, k in enumerate(pid.tolist()):
                if bool(ok[j]):
                    self._accept(int(ids[k]), trial[j], val[j], float(loc_eta[k]))
                    accepted[k] = True
                    pending[k] = False
                else:
                    loc_eta[k] = loc_eta[k] * 0.5
        for k in range(len(ids)):
            if not bool(accepted[k]):
                self.active[int(ids[k])] = False
        return n_evals

    def _compiled_line_searches(self, ids: Tensor, grad: Tensor) -> int:
        """The line searches of starts ``ids`` [K] through the compiled kernel, which finds
        each start's accepted trial; the accepted trials then computed by the reference's
        own operations (so that the poses and psi kept are the reference's); a start whose
        trial the reference's check rejects (psi within rounding of the current psi) has
        its line search redone by the reference. Returns the psi evaluations."""
        assert self.searcher is not None
        dev = self.poses.device
        t0 = time.perf_counter()
        found, counts = self.searcher.search(ids, grad, self.poses, self.cur, self.eta)
        self.tally.value_s += time.perf_counter() - t0
        self.tally.value_evaluations += sum(counts)
        n_evals = sum(counts)
        acc = [k for k, n in enumerate(found) if n > 0]
        redo: list[int] = []
        if acc:
            kk = torch.tensor(acc, dtype=torch.long, device=dev)
            halved = torch.tensor([0.5 ** (found[k] - 1) for k in acc], dtype=self.dt,
                                  device=dev)
            loc_eta = self.eta[ids[kk]] * halved  # the reference's step after found - 1 halvings
            trial = self._retract(ids[kk], grad[kk], loc_eta)
            t0 = time.perf_counter()
            with torch.no_grad():
                val = self._evaluate(trial).detach()
            self.tally.value_s += time.perf_counter() - t0
            ok = (torch.isfinite(val) & (val >= self.cur[ids[kk]])).tolist()
            for j, k in enumerate(acc):
                if ok[j]:
                    self._accept(int(ids[k]), trial[j], val[j], float(loc_eta[j]))
                else:
                    redo.append(k)
        for k, n in enumerate(found):
            if n == 0:
                self.active[int(ids[k])] = False
        if redo:
            rr = torch.tensor(redo, dtype=torch.long, device=dev)
            n_redo = sum(counts[k] for k in redo)
            self.tally.value_evaluations -= n_redo
            n_evals += self._line_searches(ids[rr], grad[rr]) - n_redo
        return n_evals


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
    """:class:`Ascent` from every start pose [S, 4, 4], run: the final poses [S, 4, 4], their
    psi [S], the per-start psi traces and the number of psi evaluations. ``split``, when
    given, receives the ascent's tally (:meth:`.records.AscentTally.as_split`)."""
    run = Ascent(psi_fn, starts, config=config, envelope=envelope, radius=radius,
                 batched=batched, compiled=compiled).run()
    if split is not None:
        split.update(run.tally.as_split())
    return run.poses, run.cur, run.traces, run.evaluations

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
    """Find the anchor T* = argmax psi(T) (see the module docstring): :func:`find_anchor` on
    the arguments, ``config`` validated (a ``ValueError`` naming the field). The arguments
    are :class:`.records.AnchorInputs`'s fields."""
    return find_anchor(AnchorInputs(
        gmap, h_acc, candidates, intrinsics, config, fields=fields, num_acquired=num_acquired,
        envelope=envelope, warm_c2w=warm_c2w, typical=typical, generator=generator,
        acquired=acquired, lam=lam, background=background, carried=carried,
    ).checked())


class _Stages:
    """The seconds of the pipeline's stages (a cancellation check after each)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.last = time.perf_counter()

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.seconds[stage] = self.seconds.get(stage, 0.0) + (now - self.last)
        self.last = now
        checkpoint()


def find_anchor(inputs: AnchorInputs) -> AnchorResult:
    """Find the anchor T* = argmax psi(T) (see the module docstring) from ``inputs``, whose
    ``config`` is taken as validated (:func:`optimize_anchor` validates it): the proxy
    (:func:`.assembly.assemble_proxy`), its psi over the pool and the starts, the ascent
    (:class:`.compiled_ascent.CompiledAscent` where it serves the proxy, else
    :class:`Ascent`) and the distinct modes."""
    stages = _Stages()
    cfg = inputs.config
    radius = inputs.radius
    built = assemble_proxy(inputs, radius, stages.lap)
    proxy = built.proxy
    pool, pool_psi, refined, best, starts = _starts(inputs, proxy, radius,
                                                     built.model.typical_term)
    stages.lap("starts")
    ascent: Ascent | CompiledAscent
    if cfg.psi == "proxy" and CompiledAscent.serves(proxy, starts):
        ascent = CompiledAscent(proxy, starts, config=cfg, envelope=inputs.envelope,
                                radius=radius).run()
    elif cfg.psi == "proxy":
        ascent = Ascent(proxy, starts, config=cfg, envelope=inputs.envelope, radius=radius,
                        batched=True).run()
    else:
        exact = exact_psi_fn(inputs.gmap, inputs.h_acc, inputs.intrinsics, cfg, inputs.fields,
                             background=inputs.background)
        ascent = Ascent(exact, starts, config=cfg, envelope=inputs.envelope, radius=radius,
                        batched=False).run()
    poses, vals = ascent.poses, ascent.cur
    win = int(torch.argmax(vals))
    modes = distinct_best(poses, vals, cfg.anchors, cfg.mode_separation * radius, radius)
    stages.lap("ascent")
    diagnostics = AnchorDiagnostics(
        model=built.model, carried=built.carried, rates_carried=built.rates_carried,
        timings_s=stages.seconds,
        ascent=ascent.tally, start_indices=[int(i) for i in best],
        proxy_samples=int(proxy.means.shape[0]),
    )
    return AnchorResult(
        c2w=poses[win].detach(),
        psi=float(vals[win]),
        psi_trace=ascent.traces[win],
        traces=ascent.traces,
        starts=starts,
        evaluations=ascent.evaluations,
        diagnostics=diagnostics,
        pool_psi=pool_psi.detach(),
        pool_refined=refined,
        modes=poses[modes].detach(),
        mode_psi=[float(vals[i]) for i in modes],
        carry=built.carry,
        rates_carry=built.rates_carry,
    )


def _starts(inputs: AnchorInputs, proxy: ProxyPsi, radius: float, typical: float | None
            ) -> tuple[Tensor, Tensor, Tensor | None, Tensor, Tensor]:
    """The pool [D, 4, 4] in the map's dtype, its proxy psi [D] (full, or coarse outside the
    refined candidates: :func:`.starts.two_pass_pool_psi` with ``config.start_samples`` and
    ``config.start_refined``, ``typical`` the model's typical term), the refined candidates
    [K] (None: all), the best candidates under the full psi [k] (``config.num_starts``; of
    distinct modes with ``config.anchors`` > 1) and the start poses [S, 4, 4] (theirs, and
    the previous anchor's with ``config.warm_start``)."""
    cfg = inputs.config
    dt = inputs.gmap.dtype
    k = min(cfg.num_starts, inputs.candidates.shape[0])
    sep = cfg.mode_separation * radius

    def values(psi: ProxyPsi, poses: Tensor) -> Tensor:
        return psi.values_in_parts(poses, POOL_CHUNK, checkpoint)  # a check per chunk

    with torch.no_grad():
        pool = inputs.candidates.detach().to(dt)
        placed = inputs.envelope.project(pool) if inputs.envelope is not None else pool
        pool_psi, refined = two_pass_pool_psi(
            proxy, placed, samples=cfg.start_samples, refined=cfg.start_refined,
            typical=typical, values=values,
            also=(lambda rough: distinct_best(pool, rough, k, sep, radius))
            if cfg.anchors > 1 else None)
    among = torch.arange(pool.shape[0], device=pool.device) if refined is None else refined
    if cfg.anchors > 1:
        best = among[distinct_best(pool[among], pool_psi[among], k, sep, radius)]
    else:
        best = among[torch.topk(pool_psi[among], min(k, among.numel())).indices]
    starts = pool[best]
    if cfg.warm_start and inputs.warm_c2w is not None:
        starts = torch.cat([starts, inputs.warm_c2w.detach().to(dt).reshape(1, 4, 4)])
    # the ascent moves on SE(3): poses within the wire's tolerance start from the nearest
    # rigid transform
    return pool, pool_psi, refined, best, project_to_se3(starts)

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
