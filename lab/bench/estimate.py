"""The wall-time estimate ``agilegs bench run`` prints before it runs (and ``--estimate-only``
prints alone): a short calibration on the scene scaled by the profile's schedule."""

from __future__ import annotations

import time
from collections.abc import Sequence

import torch

from agilegs.config.selection import objective_of
from agilegs.service.nbv import fisher_diag, render
from agilegs.service.nbv.methods.base import get_method

from .profiles import Profile
from .protocol import initial_view_indices, new_mapper
from .scene_model import BenchScene
from .variants import Variant

__all__ = ["estimate_seconds"]


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
    mapper = new_mapper(scene, profile, 0, dev)
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
        cfg = v.config()
        if objective_of(v.method, cfg) == "target" and v.method in ("full_eig", "agile_plus"):
            sel += events * cfg.target_views * t_fisher  # the targets' Fisher T
        out[v.key] = 1.5 * len(seeds) * (base + sel)
    return out
