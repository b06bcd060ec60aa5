"""Benchmark profiles: scene sizing, the protocol's schedule and the training settings.

- ``paper``: 10 initial views, one selection every 200 steps, 30K steps (149 selections,
  the pool permitting), 3DGS's training settings; for a GPU (``--device cuda``).
- ``cpu``: 64x64 images, ground truth subsampled to 3000 Gaussians, a pool of 180 cameras
  and 24 test cameras, 4 initial views, one selection every 50 steps up to 12 views (8
  events), 500 steps (densification every 90 steps up to step 400), SH degree 0, at most
  2500 Gaussians in the map, 1 torch thread. The pool is large enough that the shortlist
  (N = 10) is a small part of it, as in the paper (FisherRF's cost is proportional to the
  pool, AGILE-GS+'s to N).
- ``capture``: the paper's shape on a posed capture (COLMAP, transforms.json, rosbag2):
  96-pixel-wide images, the pool is every frame of the capture but the test ones, in capture
  order (never thinned, so that ``--embodied K`` means the K frames nearest the robot's), at
  most 24 test frames, 10 initial views, one selection every 50 steps up to 40 views (30
  events), 1600 steps, densification up to step 1400, at most 8000 Gaussians, 1 torch thread.
  A splat scene is refused (its pool would be rendered): ``cpu_long`` is its profile.
- ``tiny``: for tests, 32x32, 300 Gaussians, a pool of 16, 2 initial views, 3 selections of
  8 steps; runs in seconds.
"""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Literal

from .scene_model import SceneOptions

__all__ = ["PROFILES", "RESULTS_FORMAT", "DepthUse", "Profile", "resolve_profile"]

RESULTS_FORMAT = "agilegs-bench-run/2"

DepthUse = Literal["init", "all", "none"]


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
    "cpu_long": Profile(
        name="cpu_long",
        scene=SceneOptions(width=96, height=96, fov_deg=50.0, max_gaussians=None,
                           pool_size=180, test_count=24, orbit_scale=1.8),
        initial_views=10,
        interval=50,
        total_steps=1800,
        view_budget=40,
        depth="all",
        curve_every=2,
        mapper=dict(_SMALL_MAPPER, densify_until=1500, max_gaussians=8000),
        threads=1,
    ),
    "capture": Profile(
        name="capture",
        scene=SceneOptions(width=96, height=96, fov_deg=50.0, max_gaussians=None,
                           pool_size=100_000, test_count=24, orbit_scale=1.8),
        initial_views=10,
        interval=50,
        total_steps=1600,
        view_budget=40,
        depth="all",
        curve_every=2,
        mapper=dict(_SMALL_MAPPER, densify_until=1400, max_gaussians=8000),
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


def resolve_profile(args: argparse.Namespace) -> Profile:
    """The named profile with the command line's overrides applied (validated); an override
    the command has no flag for (``bench value``, ``bench proxy``) is none."""
    p = PROFILES[args.profile]
    sc = p.scene
    if getattr(args, "pool_size", None) is not None:
        sc = replace(sc, pool_size=args.pool_size)
    if getattr(args, "resolution", None) is not None:
        sc = replace(sc, width=args.resolution, height=args.resolution)
    if getattr(args, "max_gaussians", None) is not None:
        sc = replace(sc, max_gaussians=args.max_gaussians)
    over: dict[str, Any] = {"scene": sc}
    for arg, name in (("initial_views", "initial_views"), ("interval", "interval"),
                      ("steps", "total_steps"), ("view_budget", "view_budget"),
                      ("shortlist_size", "shortlist_size"), ("lam", "lam")):
        v = getattr(args, arg, None)
        if v is not None:
            over[name] = v
    rasterizer = getattr(args, "rasterizer", None)
    if rasterizer is not None:
        over["mapper"] = {**p.mapper, "rasterizer": rasterizer}
    p = replace(p, **over)
    try:
        p.validate()
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    return p
