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
:mod:`agilegs.service.bench.redundancy`). ``DIR/table.md`` lays the means ± std over seeds out
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

Profiles: :mod:`agilegs.service.bench.profiles`; variants (a method with changed settings):
:mod:`agilegs.service.bench.variants`; the command line: :mod:`agilegs.service.bench.run_cli`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, replace
from typing import Any

import numpy as np
import torch
from torch import Tensor

from agilegs.config.mapper import MapperConfig
from agilegs.config.selection import SelectConfig
from agilegs.service.mapper.mapper import Mapper
from agilegs.service.mapper.quality import lpips, lpips_available, psnr, ssim
from agilegs.service.nbv.information import fisher_diag, init_information
from agilegs.service.nbv.methods.base import get_method
from agilegs.service.nbv.rasterize import render
from agilegs.service.nbv.selectors import select
from agilegs.service.sessions.transitions import (
    Limits,
    acquire,
    new_record,
    pool_index,
    recompute_information,
    set_pool,
)
from agilegs.service.store.records import SessionRecord

from .profiles import RESULTS_FORMAT, Profile
from .redundancy import run_redundancy
from .scene_model import BenchScene
from .variants import Variant

__all__ = [
    "add_pool_view",
    "estimate_seconds",
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


def _on(device: torch.device, state: Any) -> Any:
    """A warm state with its tensors on ``device`` (the record keeps them on the CPU)."""
    if isinstance(state, Tensor):
        return state.to(device)
    if isinstance(state, dict):
        return {k: _on(device, v) for k, v in state.items()}
    if isinstance(state, list):
        return [_on(device, v) for v in state]
    return state


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
                 embodied_k: int | None) -> str:
    blob = json.dumps(
        {
            "scene": scene.source,
            "variant": asdict(variant),
            # the settings it selects with: a changed default is another run
            "config": asdict(variant.config()),
            "seed": seed,
            "profile": profile.describe(),
            "embodied_k": embodied_k,
            "format": RESULTS_FORMAT,
        },
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


# ----------------------------------------------------------------------------- one run
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

    Returns:
        The JSON-ready record (see the module docstring).
    """
    dev = torch.device(device)
    t_run = time.perf_counter()
    torch.manual_seed(seed)
    d = scene.pool_size
    pool_pos = scene.pool_poses[:, :3, 3]
    extent = 1.1 * float((pool_pos - pool_pos.mean(0)).norm(dim=1).max())
    mcfg = MapperConfig(**{
        **profile.mapper,
        "background": scene.background,
        "seed": int(seed),
        "scene_extent": max(extent, 1e-6),
        "lr_means_steps": profile.total_steps,
    })
    mapper = Mapper(config=mcfg, device=dev)
    initial = initial_view_indices(d, profile.initial_views, seed)
    if scene.init_points is not None:
        mapper.init_from_points(scene.init_points, scene.init_colors)

    def add(i: int, first: bool) -> None:
        add_pool_view(mapper, scene, i, profile, first=first, device=dev)

    for i in initial:
        add(i, True)
    if mapper.num_gaussians == 0:
        raise RuntimeError(f"scene {scene.name}: the initial views gave no Gaussians (no depth "
                           "and no initial points)")
    rec = run_record(scene, mapper.gmap, profile.lam)
    for i in initial:  # Ĥ is recomputed at every event (see the module docstring)
        rec, _ = acquire(rec, rec.pool_poses[pool_index(rec, i, "initial")], candidate_id=i,
                         update_information=False)
    acquired = list(initial)
    budget = min(profile.view_budget or d, d)
    bg = torch.tensor(scene.background, dtype=torch.float32, device=dev)
    candidates_all = scene.pool_poses.to(dev)
    cfg = variant.config(SelectConfig(
        embodied_k=embodied_k,
        seed=int(seed),
        fisher_background=tuple(float(c) for c in scene.background),  # type: ignore[arg-type]
    ))
    events: list[dict[str, Any]] = []
    curve: list[dict[str, Any]] = []
    times = {"train_s": 0.0, "select_s": 0.0, "information_s": 0.0, "eval_s": 0.0}
    step = 0
    total = profile.total_steps

    def train(n: int) -> None:
        nonlocal step
        t0 = time.perf_counter()
        chunk = max(1, min(n, 10))
        done = 0
        while done < n:
            k = min(chunk, n - done)
            mapper.step(k)
            done += k
            step += k
            if progress is not None:
                progress(step, total, f"{len(acquired)} views, {mapper.num_gaussians} G")
        times["train_s"] += time.perf_counter() - t0

    def point_on_curve() -> None:
        t0 = time.perf_counter()
        q = evaluate(mapper.gmap, scene, device=dev, with_lpips=False, full=False)
        curve.append({"views": len(acquired), "step": step, "psnr": q["psnr"]})
        times["eval_s"] += time.perf_counter() - t0

    event = 0
    while len(acquired) < budget and step + profile.interval < total:
        train(profile.interval)
        if profile.curve_every and event % profile.curve_every == 0:
            point_on_curve()
        gmap = mapper.gmap
        remaining = [int(i) for i in rec.pool_ids]
        t0 = time.perf_counter()
        uses_information = get_method(variant.method).uses_information
        h_acc = (recompute_information(rec, gmap) if uses_information
                 else init_information(gmap, profile.lam))
        rec = replace(rec, gmap=gmap, h_acc=h_acc)
        h_ms = (time.perf_counter() - t0) * 1e3
        cands = candidates_all[remaining].to(gmap.dtype)
        acq_poses = candidates_all[acquired].to(gmap.dtype)
        if on_event is not None:
            on_event({
                "gmap": gmap,
                "mapper": mapper,
                "step": step,
                "candidates": cands,
                "remaining": remaining,
                "acquired_indices": list(acquired),
                "acquired": acq_poses,
                "intrinsics": scene.intrinsics,
                "config": cfg,
                "background": bg.to(gmap.dtype),
                "event": event,
            })
        t0 = time.perf_counter()
        c0 = time.process_time()
        sel = select(
            variant.method,
            gmap,
            h_acc,
            cands,
            scene.intrinsics,
            config=cfg,
            acquired=acq_poses,
            current_pose=acq_poses[-1] if embodied_k is not None else None,
            state=_on(dev, rec.warm_state),
            lam=profile.lam,
        )
        wall_ms = (time.perf_counter() - t0) * 1e3
        cpu_ms = (time.process_time() - c0) * 1e3
        choice = remaining[sel.index]
        events.append({
            "event": event,
            "step": step,
            "views_before": len(acquired),
            "choice": choice,
            "shortlist": [remaining[i] for i in sel.shortlist],
            "eligible": len(sel.eligible),
            "latency_ms": {k: float(v) for k, v in sel.latency_ms.items()},
            "select_wall_ms": wall_ms,
            "select_cpu_ms": cpu_ms,
            "information_ms": h_ms,
            # an incremental Hhat adds one committed view's Fisher per event: the recompute's
            # cost per view
            "upkeep_ms": h_ms / len(acquired) if uses_information else 0.0,
            "num_gaussians": gmap.num_gaussians,
            # for the replay (agilegs view --run): pool indices and their scores, the anchor
            "scores": [[remaining[i], float(v)] for i, v in sel.scores.items()
                       if math.isfinite(float(v))],
            "anchor": None if sel.anchor_c2w is None else _matrix(sel.anchor_c2w),
            "anchor_psi": sel.details.get("anchor_psi"),
            "best_candidate_psi": sel.details.get("best_candidate_psi"),
        })
        times["select_s"] += wall_ms / 1e3
        times["information_s"] += h_ms / 1e3
        log.debug("%s seed %d event %d step %d: view %d in %.1f ms (+ %.1f ms for Ĥ)",
                  variant.key, seed, event, step, choice, sel.latency_ms["total"], h_ms)
        rec, _ = acquire(rec, rec.pool_poses[sel.index], candidate_id=choice,
                         update_information=False, next_state=sel.state)
        acquired.append(choice)
        add(choice, False)
        event += 1
    if total > step:
        train(total - step)
    t0 = time.perf_counter()
    final = evaluate(mapper.gmap, scene, device=dev, with_lpips=lpips_available())
    times["eval_s"] += time.perf_counter() - t0
    curve.append({"views": len(acquired), "step": step, "psnr": final["psnr"]})
    seq = [initial[-1]] + acquired[len(initial):]
    traj = trajectory_stats(scene.pool_poses[seq, :3, 3], seq)
    totals = [e["latency_ms"]["total"] for e in events]
    record: dict[str, Any] = {
        "format": RESULTS_FORMAT,
        "scene": scene.name,
        "variant": variant.key,
        "method": variant.method,
        "shortlist": variant.shortlist,
        "shortlist_size": variant.shortlist_size,
        "group": variant.group,
        "seed": int(seed),
        "embodied_k": embodied_k,
        "profile": profile.name,
        "fingerprint": fingerprint(scene, variant, seed, profile, embodied_k),
        "initial": initial,
        "sequence": acquired,
        "selected": acquired[len(initial):],
        "psnr": final["psnr"],
        "ssim": final["ssim"],
        "lpips": final["lpips"],
        "per_view": final["per_view"],
        "curve": curve,
        "events": events,
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
        "intrinsics": {k: float(getattr(scene.intrinsics, k))
                       for k in ("fx", "fy", "cx", "cy", "width", "height")},
        "num_gaussians": mapper.num_gaussians,
        "rasterizer": mapper.rasterizer,
        "steps": step,
        "views": len(acquired),
        **times,
        "wall_s": time.perf_counter() - t_run,
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


# ----------------------------------------------------------------------------- estimate
def estimate_seconds(
    scene: BenchScene, variants: Sequence[Variant], seeds: Sequence[int], profile: Profile,
    *, device: torch.device | str = "cpu", embodied_k: int | None = None,
) -> dict[str, float]:
    """Rough wall-time estimate (s) per variant for all seeds, from a short calibration.

    Times a few training steps, one render and one Fisher pass on the seed-0 initial map and
    scales them by the schedule (the map grows during a run, so this is a lower bound made
    roughly honest by a factor 1.5).
    """
    dev = torch.device(device)
    pool_pos = scene.pool_poses[:, :3, 3]
    extent = 1.1 * float((pool_pos - pool_pos.mean(0)).norm(dim=1).max())
    mcfg = MapperConfig(**{**profile.mapper, "background": scene.background, "seed": 0,
                           "scene_extent": max(extent, 1e-6)})
    mapper = Mapper(config=mcfg, device=dev)
    if scene.init_points is not None:
        mapper.init_from_points(scene.init_points, scene.init_colors)
    for i in initial_view_indices(scene.pool_size, profile.initial_views, 0):
        depth = scene.pool_depths[i].to(dev) if scene.pool_depths is not None else None
        mapper.add_view(scene.pool_camera(i).to(device=dev), scene.pool_images[i].to(dev),
                        depth=depth if profile.depth != "none" else None)
    mapper.step(1)
    t0 = time.perf_counter()
    mapper.step(3)
    t_step = (time.perf_counter() - t0) / 3
    g = mapper.gmap
    cam = scene.pool_camera(0).to(device=dev)
    with torch.no_grad():
        t0 = time.perf_counter()
        render(g, cam)
        t_render = time.perf_counter() - t0
        t0 = time.perf_counter()
        fisher_diag(g, cam)
        t_fisher = time.perf_counter() - t0
    d = scene.pool_size
    events = min(profile.num_events, min(profile.view_budget or d, d) - profile.initial_views)
    n_test = scene.test_poses.shape[0]
    base = profile.total_steps * t_step + (events + 1) * n_test * t_render * 2
    acq = sum(profile.initial_views + e for e in range(events))
    rem = sum(d - profile.initial_views - e for e in range(events))
    if embodied_k is not None:
        rem = events * min(embodied_k, d)
    out: dict[str, float] = {}
    for v in variants:
        sel = 0.0
        if get_method(v.method).uses_information or v.method == "fisherrf":
            sel += acq * t_fisher  # Hhat, or FisherRF's own H_train
        if v.method in ("fisherrf", "full_eig"):
            sel += rem * t_fisher
        elif v.method == "cover":
            sel += rem * t_render * 1.5
        elif v.method == "agile":
            sel += events * 0.1
        elif v.method == "agile_plus":
            sel += events * (0.1 + min(v.shortlist_size, d) * t_fisher)
        out[v.key] = 1.5 * len(seeds) * (base + sel)
    return out
