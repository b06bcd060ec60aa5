"""``agilegs bench run``: the paper's progressive next-best-view protocol.

Per scene, method and seed: a fresh map is initialised from a few initial views (the same
views, the same initialisation and the same training seed for every method of a seed), then
trained; every ``interval`` steps one view is selected from the remaining pool by the method
and added to the training set, until the view budget (or the step budget) is reached;
training then runs to ``total_steps``. Only the selection differs between methods.

Reported per run (``DIR/runs/<scene>/<variant>/seed<k>.json``, gathered in
``DIR/results.json``): PSNR and SSIM on the held-out test views (LPIPS only when
``agilegs.service.mapper.quality.lpips_available()``: its weights are never downloaded), PSNR after
each event (the curve against the number of views), each event's selection latency (the
``Selection.latency_ms`` breakdown, wall clock) and the process CPU time of the ``select``
call (``select_cpu_ms``: on a shared machine other processes inflate wall-clock times by
varying amounts, while the CPU time of a single-threaded run measures the work itself), the
time spent recomputing Ĥ, the chosen view sequence, its camera path length and mean frame-index
jump, and how redundant its picks are with the views already acquired (``redundancy``:
:mod:`agilegs.lab.bench.redundancy`). ``DIR/table.md`` lays the means ± std over seeds out
as the paper's main results table, plus latency, trajectory, redundancy and (when asked)
ablation tables; PNG plots go next to it. A rerun with the same ``DIR`` skips the
(scene, method, seed) runs whose file exists with the same settings.

The run's state is a session's record (:class:`~agilegs.service.store.records.SessionRecord`: the
pool with the pool indices as candidate ids, the acquired views, the selector's warm state)
and changes as a session's does: every view, the initial ones included, is acquired with
:func:`~agilegs.service.sessions.transitions.acquire`, which takes it out of the pool and moves
the warm state on to the selection's.

Ĥ (the accumulated information of the acquired views): recomputed at every event from all
acquired views on the current map, Ĥ = λI + Σ_v diag Fisher(v)
(:func:`~agilegs.service.sessions.transitions.recompute_information`, as a session does for a
map pushed to it), as FisherRF does: the map changes under training (and densification
changes its Gaussian count), so an Ĥ accumulated on older maps would describe other Gaussians
(so an acquisition leaves Ĥ to that recomputation). It is computed only for the methods that
read it (full_eig, agile, agile_plus); random, cover and fisherrf receive λI (they ignore Ĥ;
FisherRF rebuilds its own H_train inside its selection, as its code does). Its cost is
recorded per event as ``information_ms``, apart from the selection latency, since every
Fisher-based method pays it alike.

Profiles: :mod:`agilegs.lab.bench.profiles`; variants (a method with changed settings):
:mod:`agilegs.lab.bench.variants`; the command line: :mod:`agilegs.lab.bench.run_cli`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
import torch
from torch import Tensor

from agilegs.config.mapper import MapperConfig
from agilegs.config.selection import SelectConfig
from agilegs.service.mapper.mapper import Mapper
from agilegs.service.mapper.quality import lpips, lpips_available, psnr, ssim
from agilegs.service.nbv import Camera, fisher_diag, init_information, render, select
from agilegs.service.nbv.candidates import pool_radius, scene_center_radius
from agilegs.service.nbv.methods.base import get_method
from agilegs.service.nbv.selectors import state_to
from agilegs.service.nbv.targets import target_gain, target_information, target_subsample
from agilegs.service.sessions.transitions import (
    Limits,
    acquire,
    new_record,
    pool_index,
    recompute_information,
    set_pool,
)
from agilegs.service.store.records import SessionRecord

from .eig_mass import eig_mass as eig_mass_of
from .profiles import RESULTS_FORMAT, Profile
from .redundancy import run_redundancy
from .scene_model import BenchScene
from .variants import Variant

__all__ = [
    "CurvePoint",
    "EventRecord",
    "PhaseTimes",
    "add_pool_view",
    "evaluate",
    "fingerprint",
    "initial_view_indices",
    "run_progressive",
    "trajectory_stats",
]

log = logging.getLogger(__name__)

ProgressFn = Callable[[int, int, str], None]


def initial_view_indices(pool_size: int, count: int, seed: int) -> list[int]:
    """``count`` pool indices spread evenly in capture order, with a seeded offset."""
    if count > pool_size:
        raise ValueError(f"initial views ({count}) exceed the pool ({pool_size})")
    g = torch.Generator().manual_seed(10_007 * int(seed) + 17)
    step = pool_size / count
    offset = float(torch.rand((), generator=g, dtype=torch.float64)) * step
    idx = sorted({min(pool_size - 1, int(math.floor(offset + i * step))) for i in range(count)})
    # rounding collisions (tiny pools): fill with the first free indices
    free = [i for i in range(pool_size) if i not in set(idx)]
    while len(idx) < count:
        idx.append(free.pop(0))
    return sorted(idx)


def trajectory_stats(positions: Tensor, indices: Sequence[int]) -> dict[str, float]:
    """Path length (sum of camera-centre distances along the sequence) and mean |index jump|.

    Args:
        positions: camera centres of the sequence [L, 3], in acquisition order.
        indices: their pool indices (capture order), len L.
    """
    if len(indices) < 2:
        return {"path_length": 0.0, "mean_index_jump": 0.0}
    steps = (positions[1:] - positions[:-1]).double().norm(dim=1)
    jumps = [abs(int(b) - int(a)) for a, b in zip(indices[:-1], indices[1:])]
    return {"path_length": float(steps.sum()), "mean_index_jump": sum(jumps) / len(jumps)}


def run_record(scene: BenchScene, gmap: Any, lam: float) -> SessionRecord:
    """The state of one run as a session's record: the scene's camera, ``gmap``, Ĥ's λ and
    the scene's background for every Fisher render, and the whole pool, candidate id = pool
    index."""
    intr = scene.intrinsics
    d = scene.pool_size
    rec = new_record(
        f"bench-{scene.name}", {k: getattr(intr, k) for k in ("fx", "fy", "cx", "cy", "width",
                                                              "height")}, gmap,
        defaults={"config": {"fisher_background": [float(c) for c in scene.background]}},
        information_config={"lambda": lam})
    limits = Limits(max_pool_size=d, max_views=d, max_gaussians=max(len(gmap), 1),
                    max_shortlist=d, max_image_pixels=intr.width * intr.height)
    poses = scene.pool_poses.detach().cpu().numpy().astype(np.float64)
    return set_pool(rec, poses, list(range(d)), limits, "pool", replace_pool=True)


@torch.no_grad()
def evaluate(
    gmap: Any, scene: BenchScene, *, device: torch.device, with_lpips: bool, full: bool = True
) -> dict[str, Any]:
    """Mean PSNR / SSIM (/ LPIPS) of ``gmap`` on the scene's test views."""
    bg = torch.tensor(scene.background, dtype=gmap.dtype, device=device)
    ps, ss, ls = [], [], []
    for i in range(scene.test_poses.shape[0]):
        cam = scene.test_camera(i).to(device=device, dtype=gmap.dtype)
        out = render(gmap, cam, background=bg).rgb.clamp(0, 1)
        ref = scene.test_images[i].to(device=device, dtype=out.dtype)
        ps.append(psnr(out, ref))
        if full:
            ss.append(ssim(out, ref))
            if with_lpips:
                ls.append(lpips(out, ref))
    res: dict[str, Any] = {"psnr": _finite_mean(ps)}
    if full:
        res.update(
            ssim=sum(ss) / len(ss),
            lpips=(sum(ls) / len(ls)) if ls else None,
            per_view={"psnr": ps, "ssim": ss, "lpips": ls or None},
        )
    return res


def _finite_mean(values: Sequence[float]) -> float:
    # an exact match (inf dB) is capped at 100 dB so that means stay finite
    return sum(min(v, 100.0) for v in values) / max(len(values), 1)


def fingerprint(scene: BenchScene, variant: Variant, seed: int, profile: Profile,
                 embodied_k: int | None, eig_mass: bool = False) -> str:
    facts: dict[str, Any] = {
        "scene": scene.source,
        "variant": asdict(variant),
        # the settings it selects with: a changed default is another run
        "config": asdict(variant.config()),
        "seed": seed,
        "profile": profile.describe(),
        "embodied_k": embodied_k,
        "format": RESULTS_FORMAT,
    }
    if eig_mass:  # a run that also records where its picks' EIG lies
        facts["eig_mass"] = True
    blob = json.dumps(facts, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


# ----------------------------------------------------------------------------- one run
def new_mapper(scene: BenchScene, profile: Profile, seed: int, device: torch.device,
               **settings: Any) -> Mapper:
    """A trainer with the profile's settings (and ``settings``), the scene's background and
    the pool's extent, seeded, started from the scene's initial points where it has them."""
    pool_pos = scene.pool_poses[:, :3, 3]
    extent = 1.1 * float((pool_pos - pool_pos.mean(0)).norm(dim=1).max())
    mapper = Mapper(config=MapperConfig(**{
        **profile.mapper, "background": scene.background, "seed": int(seed),
        "scene_extent": max(extent, 1e-6), **settings}), device=device)
    if scene.init_points is not None:
        mapper.init_from_points(scene.init_points, scene.init_colors)
    return mapper


def add_pool_view(mapper: Mapper, scene: BenchScene, i: int, profile: Profile, *,
                  first: bool = False, device: torch.device | str = "cpu") -> None:
    """Give ``mapper`` pool view ``i`` (its image, and its depth as the profile says:
    ``all`` views, the ``init`` ones only (``first``), or ``none``)."""
    dev = torch.device(device)
    depth = None
    if scene.pool_depths is not None and (profile.depth == "all" or (
            profile.depth == "init" and first)):
        depth = scene.pool_depths[i]
    mapper.add_view(scene.pool_camera(i).to(device=dev), scene.pool_images[i].to(dev),
                    depth=None if depth is None else depth.to(dev), name=f"pool_{i}")


@dataclass
class PhaseTimes:
    """Seconds a run spent training, selecting, recomputing Ĥ, evaluating and on the EIG mass
    of its picks (the record's ``train_s``, ``select_s``, ``information_s``, ``eval_s`` and
    ``diagnostics_s``)."""

    train_s: float = 0.0
    select_s: float = 0.0
    information_s: float = 0.0
    eval_s: float = 0.0
    diagnostics_s: float = 0.0


@dataclass(frozen=True)
class CurvePoint:
    """A point of the PSNR curve: the test PSNR after ``step`` steps with ``views`` views."""

    views: int
    step: int
    psnr: float


@dataclass(frozen=True)
class EventRecord:
    """One selection event of a run (an entry of the record's ``events``): the chosen pool
    index, the shortlist's, ``Selection.latency_ms``, the time of Ĥ recomputed on the current
    map and per acquired view (``upkeep_ms``: what an incremental Ĥ pays per committed view; 0
    for the methods that do not read Ĥ), [pool index, score] of every finite score, the
    anchor's camera-to-world pose [4, 4] (the replay's), and AGILE-GS+'s probes (the last
    ``probes`` of the shortlist) with whether one of them beat the model's candidates."""

    event: int
    step: int
    views_before: int
    choice: int
    shortlist: list[int]
    eligible: int
    latency_ms: dict[str, float]
    select_wall_ms: float
    select_cpu_ms: float
    information_ms: float
    upkeep_ms: float
    num_gaussians: int
    scores: list[list[float]]
    anchor: list[list[float]] | None
    anchor_psi: float | None
    best_candidate_psi: float | None
    probes: int | None = None
    probe_won: bool | None = None
    eig_mass: dict[str, Any] | None = None


class _ProgressiveRun:
    """The state of one run of the progressive protocol: the trainer, the session's record
    (pool, acquired views, warm state), the step count, the PSNR curve, the events and the time
    per phase."""

    def __init__(self, scene: BenchScene, variant: Variant, seed: int, profile: Profile, *,
                 embodied_k: int | None, device: torch.device,
                 progress: ProgressFn | None, eig_mass: bool = False) -> None:
        self.scene, self.variant, self.seed, self.profile = scene, variant, seed, profile
        self.embodied_k, self.device, self.progress = embodied_k, device, progress
        self.eig_mass = eig_mass
        self.t_run = time.perf_counter()
        torch.manual_seed(seed)
        d = scene.pool_size
        self.mapper = new_mapper(scene, profile, seed, device,
                                 lr_means_steps=profile.total_steps)
        self.initial = initial_view_indices(d, profile.initial_views, seed)
        for i in self.initial:
            add_pool_view(self.mapper, scene, i, profile, first=True, device=device)
        if self.mapper.num_gaussians == 0:
            raise RuntimeError(f"scene {scene.name}: the initial views gave no Gaussians (no "
                               "depth and no initial points)")
        rec = run_record(scene, self.mapper.gmap, profile.lam)
        for i in self.initial:  # Ĥ is recomputed at every event (see the module docstring)
            rec, _ = acquire(rec, rec.pool_poses[pool_index(rec, i, "initial")],
                             candidate_id=i, update_information=False)
        self.rec = rec
        self.acquired = list(self.initial)
        self.budget = min(profile.view_budget or d, d)
        self.background = torch.tensor(scene.background, dtype=torch.float32, device=device)
        self.candidates_all = scene.pool_poses.to(device)
        self.config = variant.config(SelectConfig(
            embodied_k=embodied_k,
            seed=int(seed),
            fisher_background=tuple(float(c) for c in scene.background),  # type: ignore[arg-type]
        ))
        self.uses_information = get_method(variant.method).uses_information
        self.events: list[EventRecord] = []
        self.curve: list[CurvePoint] = []
        self.times = PhaseTimes()
        self.step = 0

    def wants_event(self) -> bool:
        """Another selection fits the view budget and the steps left."""
        return (len(self.acquired) < self.budget
                and self.step + self.profile.interval < self.profile.total_steps)

    def train(self, n: int) -> None:
        """``n`` training steps, in chunks of at most 10 between progress reports."""
        t0 = time.perf_counter()
        done = 0
        while done < n:
            k = min(10, n - done)
            self.mapper.step(k)
            done += k
            self.step += k
            if self.progress is not None:
                self.progress(self.step, self.profile.total_steps,
                              f"{len(self.acquired)} views, {self.mapper.num_gaussians} G")
        self.times.train_s += time.perf_counter() - t0

    def point_on_curve(self) -> None:
        t0 = time.perf_counter()
        q = evaluate(self.mapper.gmap, self.scene, device=self.device, with_lpips=False,
                     full=False)
        self.curve.append(CurvePoint(len(self.acquired), self.step, q["psnr"]))
        self.times.eval_s += time.perf_counter() - t0

    def select_event(self, on_event: Callable[[dict[str, Any]], None] | None) -> EventRecord:
        """Recompute Ĥ on the current map, select from the remaining pool, acquire the choice
        and give its view to the trainer."""
        gmap = self.mapper.gmap
        remaining = [int(i) for i in self.rec.pool_ids]
        t0 = time.perf_counter()
        h_acc = (recompute_information(self.rec, gmap) if self.uses_information
                 else init_information(gmap, self.profile.lam))
        self.rec = replace(self.rec, gmap=gmap, h_acc=h_acc)
        h_ms = (time.perf_counter() - t0) * 1e3
        cands = self.candidates_all[remaining].to(gmap.dtype)
        acq_poses = self.candidates_all[self.acquired].to(gmap.dtype)
        if on_event is not None:
            on_event({"gmap": gmap, "mapper": self.mapper, "step": self.step,
                      "candidates": cands, "remaining": remaining,
                      "acquired_indices": list(self.acquired), "acquired": acq_poses,
                      "intrinsics": self.scene.intrinsics, "config": self.config,
                      "background": self.background.to(gmap.dtype), "event": len(self.events)})
        t0 = time.perf_counter()
        c0 = time.process_time()
        sel = select(
            self.variant.method, gmap, h_acc, cands, self.scene.intrinsics, config=self.config,
            acquired=acq_poses,
            current_pose=acq_poses[-1] if self.embodied_k is not None else None,
            state=state_to(self.device, self.rec.warm_state), lam=self.profile.lam,
        )
        wall_ms = (time.perf_counter() - t0) * 1e3
        cpu_ms = (time.process_time() - c0) * 1e3
        choice = remaining[sel.index]
        ev = EventRecord(
            event=len(self.events),
            step=self.step,
            views_before=len(self.acquired),
            choice=choice,
            shortlist=[remaining[i] for i in sel.shortlist],
            eligible=len(sel.eligible),
            latency_ms={k: float(v) for k, v in sel.latency_ms.items()},
            select_wall_ms=wall_ms,
            select_cpu_ms=cpu_ms,
            information_ms=h_ms,
            upkeep_ms=h_ms / len(self.acquired) if self.uses_information else 0.0,
            num_gaussians=gmap.num_gaussians,
            scores=[[remaining[i], float(v)] for i, v in sel.scores.items()
                    if math.isfinite(float(v))],
            anchor=None if sel.anchor_c2w is None else _matrix(sel.anchor_c2w),
            anchor_psi=sel.details.get("anchor_psi"),
            best_candidate_psi=sel.details.get("best_candidate_psi"),
            probes=sel.details.get("probes"),
            probe_won=sel.details.get("probe_won"),
            eig_mass=self._eig_mass(gmap, h_acc, sel, cands) if self.eig_mass else None,
        )
        self.events.append(ev)
        self.times.select_s += wall_ms / 1e3
        self.times.information_s += h_ms / 1e3
        log.debug("%s seed %d event %d step %d: view %d in %.1f ms (+ %.1f ms for Ĥ)",
                  self.variant.key, self.seed, ev.event, self.step, choice,
                  sel.latency_ms["total"], h_ms)
        self.rec, _ = acquire(self.rec, self.rec.pool_poses[sel.index], candidate_id=choice,
                              update_information=False, next_state=sel.state)
        self.acquired.append(choice)
        add_pool_view(self.mapper, self.scene, choice, self.profile, device=self.device)
        return ev

    def _eig_mass(self, gmap: Any, h_acc: dict[str, Tensor], sel: Any, cands: Tensor
                  ) -> dict[str, Any]:
        """Where the chosen view's EIG lies (:mod:`agilegs.lab.bench.eig_mass`), against Ĥ of
        the acquired views on this map (computed here for the methods that do not read it),
        and its fall of the pool's predicted render variance (the target objective's gain,
        T from ``target_views`` farthest-point pool views)."""
        t0 = time.perf_counter()
        if not self.uses_information:
            h_acc = recompute_information(self.rec, gmap)
        bg = self.background.to(gmap.dtype)
        pose = cands[sel.index]
        h_view = sel.chosen_information
        if h_view is None or set(h_view) != set(h_acc):
            h_view = fisher_diag(gmap, Camera(c2w=pose, intrinsics=self.scene.intrinsics),
                                 background=bg)
        out = eig_mass_of(gmap, h_acc, h_view, pose, self.candidates_all,
                          self.scene.intrinsics, self.profile.lam)
        radius = pool_radius(cands, scene_center_radius(gmap.means)[0])  # select's rot_weight
        picks = target_subsample(cands, radius, self.config.target_views)
        fields = tuple(h_acc)
        t_info = target_information(gmap, cands[picks], self.scene.intrinsics, fields=fields,
                                    background=bg)
        out["target_gain"] = target_gain(h_view, h_acc, t_info)
        self.times.diagnostics_s += time.perf_counter() - t0
        return out

    def final_evaluation(self) -> dict[str, Any]:
        """The test views' PSNR / SSIM (/ LPIPS) of the final map; closes the curve."""
        t0 = time.perf_counter()
        final = evaluate(self.mapper.gmap, self.scene, device=self.device,
                         with_lpips=lpips_available())
        self.times.eval_s += time.perf_counter() - t0
        self.curve.append(CurvePoint(len(self.acquired), self.step, final["psnr"]))
        return final


def run_progressive(
    scene: BenchScene,
    variant: Variant,
    seed: int,
    profile: Profile,
    *,
    embodied_k: int | None = None,
    device: torch.device | str = "cpu",
    progress: ProgressFn | None = None,
    on_event: Callable[[dict[str, Any]], None] | None = None,
    eig_mass: bool = False,
) -> dict[str, Any]:
    """One (method, seed) run of the progressive protocol on ``scene``; the run's record.

    Args:
        scene: the loaded scene.
        variant: the method and its shortlist settings.
        seed: seeds the initial views, training, and every random choice of the selector.
        profile: schedule and training settings.
        embodied_k: only the K nearest remaining candidates to the current (last acquired)
            view are eligible (None: the whole remaining pool).
        device: where the map is trained and the selection runs.
        progress: called as ``progress(steps_done, total_steps, note)`` during the run.
        on_event: called before each selection with its inputs (keys ``gmap``, ``candidates``
            [R, 4, 4] the remaining pool, ``remaining`` their pool indices, ``acquired`` the
            acquired poses [A, 4, 4], ``acquired_indices``, ``intrinsics``, ``config``,
            ``background`` [3], ``event``, ``step``, and ``mapper``, the live trainer: clone
            it to branch), for diagnostics such as ``agilegs bench proxy`` and ``bench
            value``.
        eig_mass: also record, per event, where the chosen view's EIG lies (the event's
            ``eig_mass``: :func:`agilegs.lab.bench.eig_mass.eig_mass`, and its target gain);
            its time is ``diagnostics_s``, apart from the selection's.

    Returns:
        The JSON-ready record (see the module docstring).
    """
    run = _ProgressiveRun(scene, variant, seed, profile, embodied_k=embodied_k,
                          device=torch.device(device), progress=progress, eig_mass=eig_mass)
    while run.wants_event():
        run.train(profile.interval)
        if profile.curve_every and len(run.events) % profile.curve_every == 0:
            run.point_on_curve()
        run.select_event(on_event)
    if profile.total_steps > run.step:
        run.train(profile.total_steps - run.step)
    final = run.final_evaluation()
    return _run_summary(run, final)


def _run_summary(run: _ProgressiveRun, final: dict[str, Any]) -> dict[str, Any]:
    """The JSON-ready record of a finished run (its keys: the module docstring)."""
    scene, variant, acquired, initial = run.scene, run.variant, run.acquired, run.initial
    seq = [initial[-1]] + acquired[len(initial):]
    traj = trajectory_stats(scene.pool_poses[seq, :3, 3], seq)
    totals = [e.latency_ms["total"] for e in run.events]
    record: dict[str, Any] = {
        "format": RESULTS_FORMAT,
        "scene": scene.name,
        "variant": variant.key,
        "method": variant.method,
        "shortlist": variant.shortlist,
        "shortlist_size": variant.shortlist_size,
        "group": variant.group,
        "seed": int(run.seed),
        "embodied_k": run.embodied_k,
        "profile": run.profile.name,
        "fingerprint": fingerprint(scene, variant, run.seed, run.profile, run.embodied_k,
                                   run.eig_mass),
        "initial": initial,
        "sequence": acquired,
        "selected": acquired[len(initial):],
        "psnr": final["psnr"],
        "ssim": final["ssim"],
        "lpips": final["lpips"],
        "per_view": final["per_view"],
        "curve": [asdict(c) for c in run.curve],
        "events": [asdict(e) for e in run.events],
        "latency_ms": {
            "mean": sum(totals) / len(totals) if totals else None,
            "median": _median(totals),
            "per_event": totals,
        },
        "path_length": traj["path_length"],
        "mean_index_jump": traj["mean_index_jump"],
        "trajectory": [[float(x) for x in p] for p in scene.pool_poses[seq, :3, 3]],
        # the pool's camera-to-world poses [D, 4, 4] and intrinsics (agilegs view --run)
        "pool_poses": [_matrix(p) for p in scene.pool_poses],
        # the test views' [T, 4, 4], in per_view's order (agilegs bench coverage)
        "test_poses": [_matrix(p) for p in scene.test_poses],
        "intrinsics": {k: float(getattr(scene.intrinsics, k))
                       for k in ("fx", "fy", "cx", "cy", "width", "height")},
        "num_gaussians": run.mapper.num_gaussians,
        "rasterizer": run.mapper.rasterizer,
        "steps": run.step,
        "views": len(acquired),
        **asdict(run.times),
        "wall_s": time.perf_counter() - run.t_run,
    }
    record["redundancy"] = run_redundancy(record)
    return record


def _matrix(pose: Tensor) -> list[list[float]]:
    """A pose [4, 4] as nested lists, rounded to 1e-7 (the records stay small)."""
    return [[round(float(x), 7) for x in row] for row in pose.detach().cpu().double()]


def _median(values: Sequence[float]) -> float | None:
    if not values:
        return None
    s = sorted(values)
    m = len(s) // 2
    return s[m] if len(s) % 2 else 0.5 * (s[m - 1] + s[m])
