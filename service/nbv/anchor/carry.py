"""The anchor's pose-independent parts carried over from one event to the next.

The proxy (its importance sample, rates and local axes, its opacity maps, the unexplored
points) depends on the map, Hhat, the acquired views, the anchor's settings and the pool's
radius, not on the pose. With ``AnchorConfig.carry_over_tolerance`` > 0 the anchor keeps it in
the warm state as tensors, numbers and strings (what the session store keeps of a warm state),
with the fingerprint of what it was built from: the map's Gaussian count and per-field sums of
|parameter|, Hhat's per-field sums and the pool's radius. The next event reuses it while each
of those sums, and the radius, is within the tolerance (relative) of its value at the build,
with the same settings and image size; else it is rebuilt. Hhat only grows by acquisitions, so
the relative change of a field's sum is ||Hhat_now - Hhat_built||_1 / ||Hhat_built||_1 over
that field.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

from agilegs.config.selection import AnchorConfig

from ..camera import Intrinsics
from ..gaussians import GaussianMap
from .proxy import ProxyPsi
from .records import ModelDiagnostics
from .visibility import OpacityMaps

__all__ = ["fingerprint", "pack", "settings_key", "unpack"]

KEPT_EXTRA = ("model", "typical_source", "typical_term", "unexplored_fraction",
              "unexplored_points")
"""The diagnostics that describe the parts (:class:`.records.ModelDiagnostics`, carried
with them by name)."""


def fingerprint(gmap: GaussianMap, h_acc: Mapping[str, Tensor], fields: tuple[str, ...],
                radius: float) -> dict[str, Any]:
    """What the parts are built from, in brief: ``count``, ``map`` (per-field sums of
    |parameter| [5], float64), ``h`` (Hhat's per-field sums [F], float64), ``radius``."""
    with torch.no_grad():
        sums = [getattr(gmap, f).detach().abs().sum(dtype=torch.float64)
                for f in ("means", "log_scales", "quats", "opacity_logits", "sh")]
        h = [h_acc[f].detach().sum(dtype=torch.float64) for f in fields]
    return {"count": int(gmap.num_gaussians), "map": torch.stack(sums).cpu(),
            "h": torch.stack(h).cpu(), "radius": float(radius)}


def settings_key(config: AnchorConfig, intrinsics: Intrinsics, fields: tuple[str, ...]) -> str:
    """The settings the parts depend on, as one string (every anchor setting but the
    tolerance, the proxy's image and the blocks)."""
    items = {k: v for k, v in dataclasses.asdict(config).items() if k != "carry_over_tolerance"}
    return repr((sorted(items.items()), intrinsics, fields))


def pack(proxy: ProxyPsi, extra: Mapping[str, Any], built: Mapping[str, Any],
         key: str) -> dict[str, Any]:
    """The parts as the warm state keeps them: ``proxy`` (its tensors and numbers), the
    diagnostics of :data:`KEPT_EXTRA` in ``extra`` (:meth:`.records.ModelDiagnostics.as_dict`),
    the fingerprint ``built`` and ``key``."""
    p: dict[str, Any] = {
        "means": proxy.means, "cov": proxy.cov, "weight": proxy.weight, "near": proxy.near,
        "edge": proxy.edge, "occ_grid": proxy.occ_grid,
        "occ_tests": [[int(c), float(t)] for c, t in proxy.occ_tests],
    }
    for name in ("rate", "slot_kinds", "axes", "occluders"):
        p[name] = getattr(proxy, name)
    if proxy.grid is not None:
        g = proxy.grid
        p["grid"] = {"means": g.means, "mass": g.mass, "center": g.center,
                     "half_depth": g.half_depth, "cells": g.cells, "bins": g.bins}
    kept = {k: extra[k] for k in KEPT_EXTRA if k in extra}
    return {"proxy": p, "extra": kept, "built": dict(built), "key": key}


def _close(now: Tensor | float, then: Any, tol: float) -> bool:
    now_t = torch.as_tensor(now, dtype=torch.float64)
    then_t = torch.as_tensor(then, dtype=torch.float64)
    if now_t.shape != then_t.shape:
        return False
    return bool(((now_t - then_t).abs() <= tol * then_t.abs()).all())


def unpack(parts: Any, *, now: Mapping[str, Any], key: str, tolerance: float,
           intrinsics: Intrinsics, dtype: torch.dtype
           ) -> tuple[ProxyPsi, ModelDiagnostics] | None:
    """The carried proxy and its model's diagnostics when ``parts`` (from :func:`pack`,
    through the warm state) may serve: the same ``key``, the fingerprint ``now`` within
    ``tolerance`` of the one at the build, tensors of ``dtype``, consistent shapes and the
    model named; else None (rebuild)."""
    try:
        if not isinstance(parts, Mapping) or parts.get("key") != key:
            return None
        built = parts["built"]
        if int(built["count"]) != now["count"] or not (
                _close(now["map"], built["map"], tolerance)
                and _close(now["h"], built["h"], tolerance)
                and _close(now["radius"], built["radius"], tolerance)):
            return None
        p = parts["proxy"]
        means, cov, weight = p["means"], p["cov"], p["weight"]
        s = means.shape[0]
        if (means.dtype != dtype or means.shape != (s, 3) or cov.shape != (s, 3, 3)
                or weight.shape != (s,)):
            return None
        opt = {n: p.get(n) for n in ("rate", "slot_kinds", "axes", "occluders")}
        if opt["rate"] is not None and opt["rate"].shape[0] != s:
            return None
        if opt["axes"] is not None and opt["axes"].shape != (s, 3, 3):
            return None
        grid = None
        if p.get("grid") is not None:
            g = p["grid"]
            grid = OpacityMaps(means=g["means"], mass=g["mass"], intrinsics=intrinsics,
                               center=g["center"], half_depth=float(g["half_depth"]),
                               cells=int(g["cells"]), bins=int(g["bins"]))
        proxy = ProxyPsi(
            means=means, cov=cov, weight=weight, intrinsics=intrinsics,
            near=float(p["near"]), edge=float(p["edge"]), occluders=opt["occluders"],
            occ_grid=int(p["occ_grid"]), rate=opt["rate"],
            occ_tests=tuple((int(c), float(t)) for c, t in p["occ_tests"]), grid=grid,
            slot_kinds=opt["slot_kinds"], axes=opt["axes"])
        return proxy, ModelDiagnostics.from_dict(parts["extra"])
    except (KeyError, TypeError, ValueError, AttributeError, IndexError, RuntimeError):
        return None
