"""``agilegs bench run``: the paper's progressive next-best-view protocol.

Per scene, method and seed: a fresh map is initialised from a few initial views (the same
views, the same initialisation and the same training seed for every method of a seed), then
trained; every ``interval`` steps one view is selected from the remaining pool by the method
and added to the training set, until the view budget (or the step budget) is reached;
training then runs to ``total_steps``. Only the selection differs between methods.

Reported per run (``DIR/runs/<scene>/<variant>/seed<k>.json``, gathered in
``DIR/results.json``): PSNR and SSIM on the held-out test views (LPIPS only when
``agilegs.service.quality.lpips_available()``: its weights are never downloaded), PSNR after
each event (the curve against the number of views), each event's selection latency (the
``Selection.latency_ms`` breakdown, wall clock) and the process CPU time of the ``select``
call (``select_cpu_ms``: on a shared machine other processes inflate wall-clock times by
varying amounts, while the CPU time of a single-threaded run measures the work itself), the
time spent recomputing Ĥ, the chosen view
sequence, its camera path length and mean frame-index jump. ``DIR/table.md`` lays the means
± std over seeds out as the paper's main results table, plus latency, trajectory and (when
asked) ablation tables; PNG plots go next to it. A rerun with the same ``DIR`` skips the
(scene, method, seed) runs whose file exists with the same settings.

Ĥ (the accumulated information of the acquired views): recomputed at every event from all
acquired views on the current map, Ĥ = λI + Σ_v diag Fisher(v), as FisherRF does: the map
changes under training (and densification changes its Gaussian count), so an Ĥ accumulated
on older maps would describe other Gaussians. It is computed only for the methods that read
it (fisherrf, agile, agile_plus); random and cover receive λI (they ignore Ĥ). Its cost is
recorded per event as ``information_ms``, apart from the selection latency, since every
Fisher-based method pays it alike.

Profiles (:data:`PROFILES`; the numbers are those of the dataclasses below):

- ``paper``: 10 initial views, one selection every 200 steps, 30K steps (149 selections,
  the pool permitting), 3DGS's training settings; for a GPU (``--device cuda``).
- ``cpu``: 64x64 images, ground truth subsampled to 3000 Gaussians, a pool of 180 cameras
  and 24 test cameras, 4 initial views, one selection every 50 steps up to 12 views (8
  events), 500 steps (densification every 90 steps up to step 400), SH degree 0, at most
  2500 Gaussians in the map, 1 torch thread. The
  pool is large enough that the shortlist (N = 10) is a small part of it, as in the paper
  (FisherRF's cost is proportional to the pool, AGILE-GS+'s to N).
- ``tiny``: for tests, 32x32, 300 Gaussians, a pool of 16, 2 initial views, 3 selections of
  8 steps; runs in seconds.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import math
import os
import platform
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import torch
from torch import Tensor

from agilegs.service.bench.scenes import BenchScene, SceneOptions, load_bench_scene

log = logging.getLogger(__name__)

METHODS: tuple[str, ...] = ("random", "fisherrf", "cover", "agile", "agile_plus")
SHORTLISTS: tuple[str, ...] = ("leverage", "knearest", "topnorm", "online")
#: methods that read Ĥ (the others get λI)
USES_INFORMATION = frozenset({"fisherrf", "agile", "agile_plus"})
RESULTS_FORMAT = "agilegs-bench-run/2"

DepthUse = Literal["init", "all", "none"]
ProgressFn = Callable[[int, int, str], None]


# ----------------------------------------------------------------------------- profiles
@dataclass(frozen=True)
class Profile:
    """One benchmark profile: scene sizing, the protocol's schedule and training settings.

    Args:
        name: profile name.
        scene: scene sizing (resolution, ground-truth subsample, pool and test sizes).
        initial_views: views the map starts from (chosen evenly spread in capture order with
            a seeded offset; the same for every method of a seed).
        interval: training steps between two selection events (S).
        total_steps: training steps in all.
        view_budget: views in all, initial ones included (None: select until the steps run
            out or the pool is empty).
        lam: λ of Ĥ = λI + Σ H_v.
        shortlist_size: N, the shortlist of agile / agile_plus.
        depth: which views carry ground-truth depth to the mapper (splat scenes only):
            "init" (the initial views: initialisation by back-projection), "all" (every
            acquired view: an RGB-D camera; new views also add Gaussians where the map does
            not cover them) or "none".
        curve_every: evaluate the test views every this many events for the PSNR curve
            (0: only at the end).
        mapper: ``MapperConfig`` overrides (background, seed, scene extent and the means'
            learning-rate decay are set by the protocol).
        threads: torch threads (None: torch's default). The small profiles use 1: on a
            shared 2-core machine intra-op threads of these small tensors mostly contend
            (a training step measured 78 ms with 1 thread against 240-400 ms with 2 under
            load).
    """

    name: str
    scene: SceneOptions
    initial_views: int
    interval: int
    total_steps: int
    view_budget: int | None
    lam: float = 1e-3
    shortlist_size: int = 10
    depth: DepthUse = "all"
    curve_every: int = 1
    mapper: dict[str, Any] = field(default_factory=dict)
    threads: int | None = None

    def validate(self) -> None:
        self.scene.validate()
        for name in ("initial_views", "interval", "total_steps", "shortlist_size"):
            v = getattr(self, name)
            if int(v) < 1:
                raise ValueError(f"profile {self.name}: {name} must be >= 1, got {v}")
        if self.view_budget is not None and self.view_budget < self.initial_views:
            raise ValueError(f"profile {self.name}: view_budget ({self.view_budget}) must be at "
                             f"least initial_views ({self.initial_views})")
        if not self.lam > 0:
            raise ValueError(f"profile {self.name}: lam must be > 0, got {self.lam}")
        if self.depth not in ("init", "all", "none"):
            raise ValueError(f"profile {self.name}: depth must be init, all or none")

    @property
    def num_events(self) -> int:
        """Selection events the schedule allows (before the pool size caps it)."""
        by_steps = max(0, (self.total_steps - 1) // self.interval)
        if self.view_budget is None:
            return by_steps
        return min(by_steps, self.view_budget - self.initial_views)

    def describe(self) -> dict[str, Any]:
        d = asdict(self)
        d["num_events"] = self.num_events
        return d


# Densification of the small profiles: every 90 steps up to step 400, so that no test
# evaluation (every 50 steps, and at the end) falls right after a densification (fresh split
# children cost ~2 dB until they are optimised) and the last 100 steps only optimise.
_SMALL_MAPPER: dict[str, Any] = {
    "sh_degree": 0,
    "sh_degree_interval": None,
    "densify_from": 90,
    "densify_every": 90,
    "densify_until": 400,
    "opacity_reset_every": None,
    "prune_large_from": None,
    "init_stride": 2,
    "max_gaussians": 2500,
}

PROFILES: dict[str, Profile] = {
    "paper": Profile(
        name="paper",
        scene=SceneOptions(width=512, height=512, fov_deg=50.0, max_gaussians=None,
                           pool_size=300, test_count=40, random_init_points=100_000,
                           max_init_points=None),
        initial_views=10,
        interval=200,
        total_steps=30_000,
        view_budget=None,
        depth="init",
        curve_every=10,
        mapper={"sh_degree": 3, "init_stride": 2},
    ),
    "cpu": Profile(
        name="cpu",
        scene=SceneOptions(width=64, height=64, fov_deg=50.0, max_gaussians=3000,
                           pool_size=180, test_count=24),
        initial_views=4,
        interval=50,
        total_steps=500,
        view_budget=12,
        depth="all",
        curve_every=1,
        mapper=dict(_SMALL_MAPPER),
        threads=1,
    ),
    "tiny": Profile(
        name="tiny",
        scene=SceneOptions(width=32, height=32, fov_deg=50.0, max_gaussians=300,
                           pool_size=16, test_count=3, random_init_points=300,
                           max_init_points=2000),
        initial_views=2,
        interval=8,
        total_steps=30,
        view_budget=5,
        shortlist_size=4,
        depth="all",
        curve_every=1,
        mapper=dict(_SMALL_MAPPER, densify_from=9, densify_every=9, densify_until=24,
                    init_stride=4, max_gaussians=600),
        threads=1,
    ),
}


# ----------------------------------------------------------------------------- variants
@dataclass(frozen=True)
class Variant:
    """A method with its shortlist settings; ``key`` names its runs.

    ``agile`` / ``agile_plus`` with the paper's leverage shortlist and the profile's N are the
    plain method names; the shortlist ablation adds ``agile@<strategy>`` and the budget
    ablation ``agile_plus@n<N>``.
    """

    key: str
    method: str
    shortlist: str = "leverage"
    shortlist_size: int = 10
    group: Literal["main", "shortlist", "budget"] = "main"


DISPLAY = {
    "random": "Random",
    "fisherrf": "FisherRF",
    "cover": "COVER",
    "agile": "AGILE-GS",
    "agile_plus": "AGILE-GS+",
}
SHORTLIST_DISPLAY = {
    "leverage": "Ridge leverage",
    "knearest": "K-nearest views",
    "topnorm": "Top independent norm",
    "online": "Online row sampling",
}


def build_variants(
    methods: Sequence[str],
    shortlist_size: int,
    strategies: Sequence[str] = (),
    budgets: Sequence[int] = (),
    shortlist_method: str = "agile",
) -> list[Variant]:
    """The runs' variants: the methods, then the shortlist and budget ablations (deduplicated).

    Args:
        methods: base methods (``METHODS``).
        shortlist_size: the profile's N.
        strategies: shortlist strategies of the ablation, run with ``shortlist_method``.
        budgets: shortlist sizes N of the AGILE-GS+ budget ablation.
        shortlist_method: "agile" (the paper's table) or "agile_plus". With "agile" the
            "topnorm" strategy picks exactly what "leverage" picks: the first greedy
            ridge-leverage pick (S_0 = λ_G I) is the row of largest norm.

    Raises:
        ValueError: an unknown method or strategy, or a budget < 1.
    """
    if shortlist_method not in ("agile", "agile_plus"):
        raise ValueError(f"--shortlist-method must be agile or agile_plus, got "
                         f"{shortlist_method!r}")
    out: dict[str, Variant] = {}
    for m in methods:
        if m not in METHODS:
            raise ValueError(f"--methods: unknown method {m!r} (known: {', '.join(METHODS)})")
        out.setdefault(m, Variant(m, m, shortlist_size=shortlist_size))
    for s in strategies:
        if s not in SHORTLISTS:
            raise ValueError(f"--shortlist-strategies: unknown strategy {s!r} (known: "
                             f"{', '.join(SHORTLISTS)})")
        key = shortlist_method if s == "leverage" else f"{shortlist_method}@{s}"
        out.setdefault(key, Variant(key, shortlist_method, s, shortlist_size, "shortlist"))
    for n in budgets:
        if int(n) < 1:
            raise ValueError(f"--budgets: a shortlist budget must be >= 1, got {n}")
        key = "agile_plus" if int(n) == shortlist_size else f"agile_plus@n{int(n)}"
        out.setdefault(key, Variant(key, "agile_plus", "leverage", int(n), "budget"))
    return list(out.values())


def display_name(key: str) -> str:
    """Human name of a variant key (``agile_plus@n5`` -> ``AGILE-GS+ (N=5)``)."""
    if key in DISPLAY:
        return DISPLAY[key]
    base, _, extra = key.partition("@")
    if extra.startswith("n") and extra[1:].isdigit():
        return f"{DISPLAY.get(base, base)} (N={extra[1:]})"
    return f"{DISPLAY.get(base, base)} [{SHORTLIST_DISPLAY.get(extra, extra)}]"


# ----------------------------------------------------------------------------- helpers
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


def accumulated_information(
    gmap: Any,
    cameras: Sequence[Any],
    lam: float,
    background: Tensor | None,
) -> dict[str, Tensor]:
    """Ĥ = λI + Σ_v diag Fisher(v) over ``cameras`` on the current map (every block)."""
    from agilegs.service.nbv.information import fisher_diag, init_information

    h = init_information(gmap, lam)
    with torch.no_grad():
        for cam in cameras:
            hv = fisher_diag(gmap, cam, background=background)
            for k in h:
                h[k].add_(hv[k].to(h[k].dtype))
    return h


@torch.no_grad()
def evaluate(
    gmap: Any, scene: BenchScene, *, device: torch.device, with_lpips: bool, full: bool = True
) -> dict[str, Any]:
    """Mean PSNR / SSIM (/ LPIPS) of ``gmap`` on the scene's test views."""
    from agilegs.service.nbv.rasterize import render
    from agilegs.service.quality import lpips, psnr, ssim

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


def _fingerprint(scene: BenchScene, variant: Variant, seed: int, profile: Profile,
                 embodied_k: int | None) -> str:
    blob = json.dumps(
        {
            "scene": scene.source,
            "variant": asdict(variant),
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
            acquired poses [A, 4, 4], ``intrinsics``, ``config``, ``background`` [3],
            ``event``), for diagnostics such as ``agilegs bench proxy``.

    Returns:
        The JSON-ready record (see the module docstring).
    """
    from agilegs.service.mapper import Mapper, MapperConfig
    from agilegs.service.nbv.information import init_information
    from agilegs.service.nbv.selectors import SelectConfig, select
    from agilegs.service.quality import lpips_available

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
        depth = None
        if scene.pool_depths is not None and (profile.depth == "all" or (
                profile.depth == "init" and first)):
            depth = scene.pool_depths[i]
        mapper.add_view(scene.pool_camera(i).to(device=dev), scene.pool_images[i].to(dev),
                        depth=None if depth is None else depth.to(dev), name=f"pool_{i}")

    for i in initial:
        add(i, True)
    if mapper.num_gaussians == 0:
        raise RuntimeError(f"scene {scene.name}: the initial views gave no Gaussians (no depth "
                           "and no initial points)")
    acquired = list(initial)
    budget = min(profile.view_budget or d, d)
    bg = torch.tensor(scene.background, dtype=torch.float32, device=dev)
    candidates_all = scene.pool_poses.to(dev)
    cfg = SelectConfig(
        shortlist_size=variant.shortlist_size,
        shortlist=variant.shortlist,  # type: ignore[arg-type]
        embodied_k=embodied_k,
        seed=int(seed),
        fisher_background=tuple(float(c) for c in scene.background),  # type: ignore[arg-type]
    )
    state: dict[str, Any] | None = None
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
        taken = set(acquired)
        remaining = [i for i in range(d) if i not in taken]
        t0 = time.perf_counter()
        if variant.method in USES_INFORMATION:
            cams = [scene.pool_camera(i).to(device=dev, dtype=gmap.dtype) for i in acquired]
            h_acc = accumulated_information(gmap, cams, profile.lam, bg.to(gmap.dtype))
        else:
            h_acc = init_information(gmap, profile.lam)
        h_ms = (time.perf_counter() - t0) * 1e3
        cands = candidates_all[remaining].to(gmap.dtype)
        acq_poses = candidates_all[acquired].to(gmap.dtype)
        if on_event is not None:
            on_event({
                "gmap": gmap,
                "candidates": cands,
                "remaining": remaining,
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
            state=state,
        )
        wall_ms = (time.perf_counter() - t0) * 1e3
        cpu_ms = (time.process_time() - c0) * 1e3
        state = sel.state
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
            "num_gaussians": gmap.num_gaussians,
        })
        times["select_s"] += wall_ms / 1e3
        times["information_s"] += h_ms / 1e3
        log.debug("%s seed %d event %d step %d: view %d in %.1f ms (+ %.1f ms for Ĥ)",
                  variant.key, seed, event, step, choice, sel.latency_ms["total"], h_ms)
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
        "fingerprint": _fingerprint(scene, variant, seed, profile, embodied_k),
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
        "num_gaussians": mapper.num_gaussians,
        "steps": step,
        "views": len(acquired),
        **times,
        "wall_s": time.perf_counter() - t_run,
    }
    return record


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
    from agilegs.service.mapper import Mapper, MapperConfig
    from agilegs.service.nbv.information import fisher_diag
    from agilegs.service.nbv.rasterize import render

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
        if v.method in USES_INFORMATION:
            sel += acq * t_fisher
        if v.method == "fisherrf":
            sel += rem * t_fisher
        elif v.method == "cover":
            sel += rem * t_render * 1.5
        elif v.method == "agile":
            sel += events * 0.1
        elif v.method == "agile_plus":
            sel += events * (0.1 + min(v.shortlist_size, d) * t_fisher)
        out[v.key] = 1.5 * len(seeds) * (base + sel)
    return out


# ----------------------------------------------------------------------------- CLI
def _int_list(text: str, what: str) -> list[int]:
    try:
        return [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise SystemExit(f"{what}: expected comma-separated integers, got {text!r}") from None


def _str_list(text: str) -> list[str]:
    return [s.strip() for s in text.split(",") if s.strip()]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", action="append", required=True, metavar="PATH",
                        help="a ground-truth splat (.splat/.ply or its folder), a "
                        "transforms.json image set or a COLMAP model folder; repeat for "
                        "several scenes")
    parser.add_argument("--methods", default=",".join(METHODS),
                        help=f"comma-separated subset of {','.join(METHODS)}")
    parser.add_argument("--profile", default="cpu", choices=sorted(PROFILES),
                        help="paper: 10 initial views, +1 per 200 steps, 30K steps (GPU); cpu: "
                        "64x64, pool 180, 4 initial, +1 per 50 steps to 12 views, 500 steps; "
                        "tiny: for tests")
    parser.add_argument("--seeds", default="0,1", help="comma-separated seeds")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder")
    parser.add_argument("--embodied", type=int, default=None, metavar="K",
                        help="only the K nearest candidates to the current view are eligible "
                        "(the paper's K = 5)")
    parser.add_argument("--shortlist-strategies", default="", metavar="LIST",
                        help="shortlist ablation of AGILE-GS: any of "
                        f"{','.join(SHORTLISTS)}")
    parser.add_argument("--shortlist-method", default="agile", choices=("agile", "agile_plus"),
                        help="the method of the shortlist ablation (default agile, as the "
                        "paper's table)")
    parser.add_argument("--budgets", default="", metavar="LIST",
                        help="shortlist-budget ablation of AGILE-GS+, e.g. 5,10,20,50")
    parser.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    parser.add_argument("--threads", type=int, default=0,
                        help="torch threads (0: the profile's: 1 for cpu and tiny)")
    g = parser.add_argument_group("profile overrides")
    g.add_argument("--initial-views", type=int, default=None)
    g.add_argument("--interval", type=int, default=None, help="steps between selections")
    g.add_argument("--steps", type=int, default=None, help="total training steps")
    g.add_argument("--view-budget", type=int, default=None, help="views in all")
    g.add_argument("--pool-size", type=int, default=None)
    g.add_argument("--resolution", type=int, default=None, help="image width (and height)")
    g.add_argument("--max-gaussians", type=int, default=None, help="ground-truth subsample")
    g.add_argument("--shortlist-size", type=int, default=None, help="N")
    g.add_argument("--lam", type=float, default=None, help="λ of Ĥ")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    parser.add_argument("--estimate-only", action="store_true",
                        help="print the wall-time estimate and stop")


def resolve_profile(args: argparse.Namespace) -> Profile:
    """The named profile with the command line's overrides applied (validated)."""
    p = PROFILES[args.profile]
    sc = p.scene
    if args.pool_size is not None:
        sc = replace(sc, pool_size=args.pool_size)
    if args.resolution is not None:
        sc = replace(sc, width=args.resolution, height=args.resolution)
    if args.max_gaussians is not None:
        sc = replace(sc, max_gaussians=args.max_gaussians)
    over: dict[str, Any] = {"scene": sc}
    for arg, name in (("initial_views", "initial_views"), ("interval", "interval"),
                      ("steps", "total_steps"), ("view_budget", "view_budget"),
                      ("shortlist_size", "shortlist_size"), ("lam", "lam")):
        v = getattr(args, arg, None)
        if v is not None:
            over[name] = v
    p = replace(p, **over)
    try:
        p.validate()
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    return p


def _run_path(out: Path, scene: str, variant: str, seed: int) -> Path:
    return out / "runs" / scene / variant.replace("@", "_at_") / f"seed{seed}.json"


def _load_done(path: Path, fingerprint: str) -> dict[str, Any] | None:
    if not path.is_file():
        return None
    try:
        rec = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        log.warning("%s unreadable (%s): running it again", path, exc)
        return None
    if rec.get("fingerprint") != fingerprint:
        log.warning("%s was made with other settings: running it again", path)
        return None
    return dict(rec)


def _write_json(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(json.dumps(data, indent=1, default=_json_default))
    os.replace(tmp, path)


def _json_default(o: Any) -> Any:
    if isinstance(o, Tensor):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def environment() -> dict[str, Any]:
    return {
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    }


def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from agilegs.service.bench import report

    console = Console(stderr=True)
    profile = resolve_profile(args)
    threads = args.threads if args.threads > 0 else profile.threads
    if threads:
        torch.set_num_threads(threads)
    try:
        variants = build_variants(
            _str_list(args.methods), profile.shortlist_size,
            _str_list(args.shortlist_strategies),
            _int_list(args.budgets, "--budgets"),
            args.shortlist_method,
        )
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    seeds = _int_list(args.seeds, "--seeds")
    if not seeds or not variants:
        raise SystemExit("--seeds and --methods must name at least one seed and method")
    if args.embodied is not None and args.embodied < 1:
        raise SystemExit(f"--embodied must be >= 1, got {args.embodied}")
    device = torch.device(args.device)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    scenes: dict[str, BenchScene] = {}
    for path in args.scene:
        try:
            sc = load_bench_scene(path, profile.scene)
        except (FileNotFoundError, ValueError) as exc:
            raise SystemExit(f"--scene {path}: {exc}") from None
        if sc.name in scenes:
            raise SystemExit(f"--scene: two scenes are named {sc.name!r}")
        if sc.pool_size < profile.initial_views + 1:
            raise SystemExit(f"--scene {path}: its pool ({sc.pool_size} views) must exceed the "
                             f"{profile.initial_views} initial views")
        scenes[sc.name] = sc
    estimates = {}
    for name, sc in scenes.items():
        est = estimate_seconds(sc, variants, seeds, profile, device=device,
                               embodied_k=args.embodied)
        estimates[name] = est
        console.print(f"[bold]{name}[/]: estimated {sum(est.values()) / 60:.1f} min for "
                      f"{len(variants)} methods x {len(seeds)} seeds ("
                      + ", ".join(f"{k} {v / 60:.1f}" for k, v in est.items()) + " min)")
    total_est = sum(sum(e.values()) for e in estimates.values())
    console.print(f"estimated total: {total_est / 60:.1f} min on {torch.get_num_threads()} "
                  f"threads ({profile.name} profile)")
    if args.estimate_only:
        return 0

    jobs = [(name, v, s) for name in scenes for s in seeds for v in variants]
    executed: list[dict[str, Any]] = []
    skipped: list[dict[str, Any]] = []
    records: dict[tuple[str, str, int], dict[str, Any]] = {}
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
               TimeElapsedColumn(), TimeRemainingColumn())
    with Progress(*columns, console=console, transient=False) as bar:
        overall = bar.add_task("runs", total=len(jobs))
        for name, v, s in jobs:
            sc = scenes[name]
            fp = _fingerprint(sc, v, s, profile, args.embodied)
            path = _run_path(out, name, v.key, s)
            done = _load_done(path, fp)
            tag = {"scene": name, "variant": v.key, "seed": s}
            if done is not None:
                log.info("skip %s / %s / seed %d: done (%s)", name, v.key, s, path)
                skipped.append(tag)
                records[(name, v.key, s)] = done
                bar.advance(overall)
                continue
            task = bar.add_task(f"{name} {v.key} s{s}", total=profile.total_steps)

            def on_progress(done_steps: int, total: int, note: str, task: Any = task,
                            label: str = f"{name} {v.key} s{s}") -> None:
                bar.update(task, completed=done_steps, total=total,
                           description=f"{label} ({note})")

            rec = run_progressive(sc, v, s, profile, embodied_k=args.embodied, device=device,
                                  progress=on_progress)
            _write_json(path, rec)
            records[(name, v.key, s)] = rec
            executed.append(tag)
            bar.remove_task(task)
            bar.advance(overall)
            log.info("%s / %s / seed %d: PSNR %.2f dB, SSIM %.4f, %.1f ms per selection, "
                     "%.0f s", name, v.key, s, rec["psnr"], rec["ssim"],
                     rec["latency_ms"]["mean"] or 0.0, rec["wall_s"])
    results = report.build_results(
        records=records,
        scenes={n: report.scene_summary(sc) for n, sc in scenes.items()},
        variants=[asdict(v) for v in variants],
        seeds=seeds,
        profile=profile.describe(),
        settings={"embodied_k": args.embodied, "device": str(device),
                  "shortlist_method": args.shortlist_method,
                  "threads": torch.get_num_threads(), "estimate_s": estimates,
                  "args": {k: v for k, v in vars(args).items() if not k.startswith("_")}},
        environment=environment(),
        invocation={"executed": executed, "skipped": skipped,
                    "wall_s": time.perf_counter() - t_start},
    )
    _write_json(out / "results.json", results)
    table = report.render_table(results)
    (out / "table.md").write_text(table)
    if not args.no_plots:
        from agilegs.service.bench import plots

        written = plots.write_plots(results, scenes, out)
        log.info("plots: %s", ", ".join(str(p.name) for p in written))
    sys.stdout.write(table)
    sys.stdout.flush()
    console.print(f"{len(executed)} runs done, {len(skipped)} skipped; wrote {out}")
    return 0
