"""The memory and time estimates: their arithmetic, their errors, and the peaks measured in
fresh processes on small maps staying under them."""

from __future__ import annotations

import math
import multiprocessing as mp
import os
from typing import Any

import pytest

from agilegs.service.nbv.budget import (
    ALLOCATOR_BYTES,
    KINDS,
    MEMORY_MARGIN,
    THREAD_ARENA_BYTES,
    estimate,
    footprint_area,
    mean_footprint,
)


def test_estimates_grow_with_the_work() -> None:
    small = {k: estimate(k, 20_000, 128 * 128, pool=50) for k in KINDS}
    big = {k: estimate(k, 1_000_000, 512 * 512, pool=50) for k in KINDS}
    for k in KINDS:
        assert small[k].peak_bytes == sum(small[k].parts.values())
        assert big[k].peak_bytes == sum(big[k].parts.values())
        if k != "random":
            assert big[k].peak_bytes > 10 * small[k].peak_bytes, k
            assert big[k].seconds > 10 * small[k].seconds, k
    # a differentiated render records its pairs; AGILE-GS+ adds Fisher passes to AGILE-GS
    assert big["render_grad"].peak_bytes > big["render"].peak_bytes
    assert big["agile_plus"].peak_bytes > big["agile"].peak_bytes
    assert big["agile_plus"].seconds > big["agile"].seconds
    # the pool sets a selection's time, not its memory
    full = [estimate("full_eig", 100_000, 256 * 256, pool=p) for p in (10, 200)]
    assert full[0].peak_bytes == full[1].peak_bytes and full[1].seconds == 20 * full[0].seconds
    # float64 and the torch path need more; a measured small footprint less
    e = estimate("fisher", 100_000, 256 * 256)
    assert estimate("fisher", 100_000, 256 * 256, dtype_bytes=8).peak_bytes > e.peak_bytes
    assert estimate("fisher", 100_000, 256 * 256, backend="torch").peak_bytes > e.peak_bytes
    assert estimate("fisher", 100_000, 256 * 256, footprint=4.0).peak_bytes < e.peak_bytes
    # at 1M Gaussians and 512² every method fits this project's 24 GiB with room to spare
    assert max(b.peak_bytes for b in big.values()) < 8 * 2**30


def test_default_footprint() -> None:
    assert footprint_area(0, 100) == 0.0
    assert footprint_area(1_000_000, 512 * 512) == pytest.approx((3 + 8 * 0.512) ** 2)
    assert footprint_area(10, 64) == 64.0  # at most the image


@pytest.mark.parametrize("kwargs, field", [
    ({"kind": "paint"}, "kind"),
    ({"gaussians": -1}, "gaussians"),
    ({"pixels": 0}, "pixels"),
    ({"pool": 2.5}, "pool"),
    ({"dtype_bytes": 2}, "dtype_bytes"),
    ({"footprint": float("nan")}, "footprint"),
    ({"backend": "cuda"}, "backend"),
])
def test_bad_arguments_name_the_field(kwargs: dict[str, Any], field: str) -> None:
    args: dict[str, Any] = {"kind": "fisher", "gaussians": 10, "pixels": 16, **kwargs}
    with pytest.raises(ValueError, match=field):
        estimate(args.pop("kind"), args.pop("gaussians"), args.pop("pixels"), **args)


def _measure(q: Any, kind: str, n: int, res: int, pool: int, threads: int = 1) -> None:
    """In a fresh process: the peak RSS a computation adds, and the estimate beside it."""
    try:
        import torch

        torch.set_num_threads(threads)
        from agilegs.config.selection import SelectConfig
        from agilegs.lab.bench.latency import PeakRSS, densified
        from agilegs.lab.scenes import bundled_scene
        from agilegs.service.nbv import (
            Camera,
            GaussianMap,
            Intrinsics,
            accumulate_information,
            fisher_diag,
            init_information,
            render,
            select,
        )
        from agilegs.service.nbv.candidates import capture_pool, scene_center_radius
        from agilegs.service.nbv.kernels import backend

        g0 = GaussianMap.load(bundled_scene("spot"))
        gm = densified(g0, n) if n > len(g0) else g0.subset(torch.arange(n))
        centre, radius = scene_center_radius(gm.means)
        intr = Intrinsics.from_fov(50.0, res, res)
        poses = capture_pool(centre, 2.6 * radius, pool + 2, seed=0)
        acquired, cands = poses[:2], poses[2:]
        h = init_information(gm, 1e-6)
        for a in acquired:
            h = accumulate_information(h, fisher_diag(gm, Camera(c2w=a, intrinsics=intr)))
        cam = Camera(c2w=cands[0], intrinsics=intr)
        small = gm.subset(torch.arange(50)).clone().requires_grad_()
        render(small, cam).rgb.sum().backward()  # the compiled code loaded: not measured
        backend.release_workspace()
        with PeakRSS() as mem:
            base = mem.peak
            if kind == "render_grad":
                g = gm.clone().requires_grad_()
                render(g, cam).rgb.sum().backward()
            elif kind == "fisher":
                fisher_diag(gm, cam)
            else:
                select(kind, gm, h, cands, intr, config=SelectConfig(), acquired=acquired)
        q.put({"measured": (mem.peak - base) * 2**20, "sh": int(gm.sh.shape[1]),
               "footprint": mean_footprint(gm, cam)})
    except Exception as exc:  # reported to the test
        q.put({"error": repr(exc)})


ALLOCATORS = {"default": ({}, 1), "one-arena": ({"MALLOC_ARENA_MAX": "1"}, 1),
              "two-threads": ({}, 2), "eager-trim": ({"MALLOC_TRIM_THRESHOLD_": "0",
                                                      "MALLOC_MMAP_THRESHOLD_": "65536"}, 1)}
"""Allocator settings the peaks are measured under (environment of the fresh process, torch
threads)."""


def _measured(kind: str, n: int, res: int, pool: int, allocator: str) -> dict[str, Any]:
    env, threads = ALLOCATORS[allocator]
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)  # the spawned process starts with it (glibc reads it at start)
    try:
        proc = ctx.Process(target=_measure, args=(q, kind, n, res, pool, threads))
        proc.start()
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    out = q.get(timeout=600)
    proc.join()
    assert "error" not in out, out
    return out


@pytest.mark.slow
@pytest.mark.parametrize("kind, n, res, pool, allocator", [
    ("render_grad", 30_000, 128, 4, "default"),
    ("fisher", 30_000, 128, 4, "default"),
    ("agile_plus", 30_000, 96, 12, "default"),
    ("cover", 30_000, 96, 4, "default"),
    # the allocator's other settings: the heavy lane (`pytest -m heavy`)
    pytest.param("cover", 30_000, 96, 4, "one-arena", marks=pytest.mark.heavy),
    pytest.param("cover", 30_000, 96, 4, "two-threads", marks=pytest.mark.heavy),
    pytest.param("agile_plus", 30_000, 96, 12, "eager-trim", marks=pytest.mark.heavy),
    ("fisher", 30_000, 128, 4, "two-threads"),
])
def test_measured_peaks_stay_under_the_estimate(kind: str, n: int, res: int, pool: int,
                                                allocator: str) -> None:
    out = _measured(kind, n, res, pool, allocator)
    threads = ALLOCATORS[allocator][1]
    est = estimate(kind, n, res * res, pool=pool, acquired=2, sh_coeffs=out["sh"],  # type: ignore[arg-type]
                   threads=threads)
    tight = estimate(kind, n, res * res, pool=pool, acquired=2, sh_coeffs=out["sh"],  # type: ignore[arg-type]
                     footprint=out["footprint"], threads=threads)
    assert out["measured"] > 0
    # the bound: the model with its stated margin
    assert est.peak_bytes == (est.model_bytes + math.ceil(est.model_bytes * (MEMORY_MARGIN - 1))
                              + ALLOCATOR_BYTES + (threads - 1) * THREAD_ARENA_BYTES)
    assert out["measured"] <= min(tight.peak_bytes, est.peak_bytes), (out, tight, est)
    # and not a vacuous one
    assert est.peak_bytes < 30 * out["measured"] + (64 << 20), (out, est)


def test_speed_calibration_learns_the_typical_recent_ratio() -> None:
    from agilegs.service.nbv.budget import TIME_MARGIN, SpeedCalibration

    speed = SpeedCalibration(window=3, min_seconds=0.5, floor=0.25)
    assert speed.factor == 1.0 and speed.bound(2.0) == 2.0 * TIME_MARGIN
    speed.observe(0.1, 5.0)  # too short an estimate to say anything: ignored
    speed.observe(float("nan"), 1.0)
    assert speed.factor == 1.0 and speed.samples == 0
    speed.observe(1.0, 3.0)  # three times slower than the reference
    assert speed.factor == pytest.approx(3.0)
    assert speed.bound(2.0) == pytest.approx(2.0 * 3.0 * TIME_MARGIN)
    speed.observe(2.0, 6.0)
    speed.observe(1.0, 40.0)  # one call that waited on another does not set the factor
    assert speed.factor == pytest.approx(3.0)
    speed.observe(1.0, 0.5)
    speed.observe(1.0, 0.5)  # the window keeps the last three
    assert speed.factor == pytest.approx(0.5) and speed.samples == 3
    for _ in range(3):
        speed.observe(1.0, 0.01)  # never below the floor
    assert speed.factor == pytest.approx(0.25)
    with pytest.raises(ValueError, match="window"):
        SpeedCalibration(window=0)
