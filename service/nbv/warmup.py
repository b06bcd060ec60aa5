"""Warm-up: compile (or load from numba's on-disk cache) the CPU kernels before the first
decision needs them.

The kernels of :mod:`agilegs.service.nbv.kernels` are compiled by numba the first time each
is called with a new type signature; on a fresh server that first call is the first selection
(seconds to tens of seconds: the anchor's rates and ascent, the Fisher, the rasterizer's
backward). :func:`warm_up` makes those first calls on a small synthetic scene (float32 on the
CPU, as the sessions hold their maps): every selection method once, and a render with its
backward as the mapper trains. The server runs it in the background at start
(``AGILEGS_WARMUP``) and answers ``/readyz`` with 503 until it is done.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence

import torch

from .camera import Camera, Intrinsics
from .candidates import capture_pool
from .gaussians import GaussianMap
from .information import accumulate_information, fisher_diag, init_information
from .methods.base import method_names
from .rasterize import render
from .selectors import select

__all__ = ["warm_up"]

log = logging.getLogger(__name__)


def _scene(n: int, seed: int) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    return GaussianMap(
        means=(torch.rand(n, 3, generator=g) - 0.5) * 0.6,
        log_scales=torch.full((n, 3), -3.0) + 0.3 * torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        opacity_logits=torch.randn(n, generator=g),
        sh=torch.randn(n, 16, 3, generator=g) * 0.3,
    )


def warm_up(methods: Sequence[str] | None = None, *, train: bool = True, gaussians: int = 200,
            seed: int = 0) -> dict[str, float]:
    """Call every kernel a selection (each of ``methods``, default every registered method)
    and, with ``train``, a training step use, on a synthetic scene of ``gaussians``
    Gaussians; the seconds each part took (``"select:<method>"``, ``"train"``, ``"total"``).
    """
    t0 = time.perf_counter()
    out: dict[str, float] = {}
    gmap = _scene(gaussians, seed)
    intr = Intrinsics(fx=28.0, fy=28.0, cx=16.0, cy=16.0, width=32, height=32)
    pool = capture_pool(torch.zeros(3), 1.8, 12, seed=seed)
    acquired = pool[:2]
    lam = 1e-3
    h_acc = init_information(gmap, lam=lam)
    for c2w in acquired:
        h_acc = accumulate_information(h_acc, fisher_diag(gmap, Camera(c2w=c2w,
                                                                       intrinsics=intr)))
    for name in methods if methods is not None else method_names():
        t = time.perf_counter()
        state = None
        for _ in range(2):  # the second event starts warm (the anchor's carried state)
            sel = select(name, gmap, h_acc, pool[2:], intr, acquired=acquired, state=state,
                         lam=lam)
            state = sel.state
        out[f"select:{name}"] = time.perf_counter() - t
    if train:
        t = time.perf_counter()
        trained = gmap.clone().requires_grad_(True)
        rgb = render(trained, Camera(c2w=pool[0], intrinsics=intr)).rgb
        rgb.mean().backward()
        out["train"] = time.perf_counter() - t
    out["total"] = time.perf_counter() - t0
    log.debug("warm-up: %s", {k: round(v, 2) for k, v in out.items()})
    return out
