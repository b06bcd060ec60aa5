"""Up-front estimates of the peak memory and the time of a render, a Fisher pass and a
selection, from the sizes alone (no tensors): enough to refuse what would not fit before
starting it.

``estimate(kind, gaussians, pixels, pool=..., ...)`` returns an :class:`Estimate`: the peak
memory the computation adds to the process (beyond the map and Ĥ, which the caller holds
already), in bytes, a rough time on one thread of this project's reference CPU, and the named
memory terms it added up. The model follows what the code allocates:

- The compiled kernels (:mod:`agilegs.service.nbv.kernels`, ``backend="numba"``): per Gaussian
  the projection's outputs and the binning's record (N terms); per list entry (a visible
  Gaussian in one 8x8 tile; M of them) its record, and for the Fisher its moments; per pixel
  slot of the entries' boxes (S of them) the composited pairs a render that will be
  differentiated records for its backward; per pixel the images.
- The pure-torch path (``backend="torch"``): the (pixel, Gaussian) pairs that pass the α test
  are listed explicitly, with their per-pair terms: about ``TORCH_PAIR_BYTES`` per pair.

M and S follow from the mean area A (pixels) of the Gaussians' α ≥ 1/255 boxes: M ≈ N (1 +
√A / 8)², S ≈ N A, and about ``PASS_FRACTION`` of S pass the α test. A depends on the map (the
Gaussians' sizes) and the view; pass ``footprint`` measured on the map when it is at hand
(:func:`mean_footprint`). Without it, :func:`footprint_area` takes (3 + 8 √(P / N))² pixels,
an upper envelope of the bundled scenes' measured boxes (subsampled to 20k and 100k and
densified to 1M, at 128² to 512²; see docs/maths.md): conservative for small Gaussians, by up
to 3x in area.

Selections (every method evaluates its candidates one after the other, so the pool size sets
the time, not the memory): ``random`` (nothing), ``full_eig`` (one exact Fisher per
candidate), ``fisherrf`` (one FisherRF Hessian per candidate and per acquired view, and
H_train), ``cover`` (one render with a feature channel per candidate, the direction bins), and
``agile`` / ``agile_plus`` (the anchor and the coverage scoring, whose memory is linear in N:
``AGILE_BYTES_PER_GAUSSIAN``, measured; AGILE-GS+ adds ``shortlist`` exact Fisher passes, on
top of what the anchor's results hold).

The memory model is what the code allocates; what the process's allocator adds to it
(arenas per thread, size classes, page rounding, the caches of glibc, the thread count) varies
between machines and allocator settings (measured up to 9 % over the model on another
machine). The estimate is therefore the model's sum times :data:`MEMORY_MARGIN` plus
:data:`ALLOCATOR_BYTES`, plus :data:`THREAD_ARENA_BYTES` for every compute thread beyond the
first, the ``margin`` term of ``parts``: an upper bound of the peak on any
machine as long as the allocator adds less than that; tests/nbv/test_budget.py measures it in
fresh processes under several allocator settings (one arena, the default, two threads).

The time coefficients were fitted to calls in fresh processes on this project's reference
2-core CPU with one thread (within 2x of the measured time, docs/maths.md). Another machine,
or the same one under load, runs slower or faster by a factor the coefficients cannot know:
:class:`SpeedCalibration` learns it from the selections a process has timed (the median
measured / estimated ratio of the recent ones estimated at half a second or more: shorter ones,
and the first call of a process that loads the compiled kernels, measure fixed costs), and
its :meth:`~SpeedCalibration.bound` is the estimate times that factor times
:data:`TIME_MARGIN`, the bound that admission compares with its limit.
"""

from __future__ import annotations

import math
import statistics
import threading
from collections import deque
from dataclasses import dataclass, field
from typing import Literal

__all__ = [
    "AGILE_BYTES_PER_GAUSSIAN",
    "ALLOCATOR_BYTES",
    "THREAD_ARENA_BYTES",
    "MEMORY_MARGIN",
    "KINDS",
    "TIME_MARGIN",
    "SpeedCalibration",
    "PASS_FRACTION",
    "TORCH_PAIR_BYTES",
    "Estimate",
    "EstimateInputs",
    "Kind",
    "estimate",
    "footprint_area",
    "mean_footprint",
]

Kind = Literal["render", "render_grad", "fisher", "random", "full_eig", "fisherrf", "cover",
               "agile", "agile_plus"]
KINDS: tuple[str, ...] = ("render", "render_grad", "fisher", "random", "full_eig", "fisherrf",
                          "cover", "agile", "agile_plus")

TILE = 8
REC = 8  # the kernels' record columns before the colours (kernels.REC)
MOMENTS = 34  # the Fisher's moments per entry (kernels.MOMENTS)
PASS_FRACTION = 0.4
"""Share of the box pixels (S) whose pair passes σ ≥ 0 and α ≥ 1/255 (0.38-0.39 measured on
the plant at 20k-1M Gaussians, 128²-512²)."""
TORCH_PAIR_BYTES = {"render": 150, "render_grad": 180, "fisher": 330}
"""Bytes per listed pair of the pure-torch path (measured at 1M Gaussians, 512²: 139, 168 and
320)."""
AGILE_BYTES_PER_GAUSSIAN = 1024
"""The anchor and the coverage scoring of ``agile`` (measured 820-900 bytes per Gaussian at 1M,
512², whatever the pool), on top of ``AGILE_BYTES``."""
AGILE_BYTES = 24 << 20
"""The anchor's and the scoring's fixed part (grids, support samples; 18-22 MB measured at
20k Gaussians)."""
MEMORY_MARGIN = 1.25
"""The memory estimate is the model's sum times this (see the module docstring)..."""
ALLOCATOR_BYTES = 8 << 20
"""... plus this ..."""
THREAD_ARENA_BYTES = 64 << 20
"""... plus this for every compute thread beyond the first: glibc gives each thread its own
arena (up to 64 MiB on 64-bit), whose freed blocks another thread's peak cannot reuse."""
TIME_MARGIN = 2.0
"""A time bound is the estimate times the machine's factor times this: the coefficients are
within 2x of the measured time on the reference CPU, between calls of one kind."""
COVER_CHUNK = 1 << 16  # cover.gaussian_coverage's block of Gaussians
COVER_BINS = 128

# seconds on one thread (kernels): per Gaussian, per list entry, per box pixel; _T_SLACK
# scales them to the wall time of a call in a fresh process on the shared 2-core machine
_T_FISHER = (0.5e-6, 40e-9, 15e-9)
_T_RENDER = (0.2e-6, 20e-9, 8e-9)
_T_SLACK = 1.8
_T_GRAD = 2.5  # forward and backward over the forward alone
_T_TORCH = 8.0  # the torch path over the kernels (Fisher and render alike, measured 7-12x)
_T_AGILE = 3.0e-6  # per Gaussian: the anchor and the scoring
_T_COVER = 2.5e-6  # per Gaussian and candidate: the coverage of every Gaussian


@dataclass(frozen=True)
class Estimate:
    """An estimate (see the module docstring).

    Attributes:
        peak_bytes: peak memory added to the process, bytes.
        seconds: time on one thread of the reference CPU.
        parts: the memory terms (bytes) added up in ``peak_bytes``.
    """

    peak_bytes: int
    seconds: float
    parts: dict[str, int] = field(default_factory=dict)

    @property
    def model_bytes(self) -> int:
        """The model's sum, without the margin."""
        return self.peak_bytes - self.parts.get("margin", 0)

    @property
    def peak_mib(self) -> float:
        return self.peak_bytes / 2**20


def footprint_area(gaussians: int, pixels: int) -> float:
    """The default mean box area A in pixels: (3 + 8 √(P / N))², at most P (see the module
    docstring)."""
    if gaussians <= 0:
        return 0.0
    side = 3.0 + 8.0 * math.sqrt(pixels / gaussians)
    return min(side * side, float(pixels))


def _pass(kind: str, n: int, p: int, area: float, f: int, k: int, channels: int,
          backend: str) -> tuple[dict[str, int], float]:
    """Memory terms and seconds of one render ("render", "render_grad") or Fisher pass."""
    m = n * (1.0 + math.sqrt(area) / TILE) ** 2  # list entries
    s = n * area  # box pixels
    params = n * (11 + 3 * k) * f  # one value per parameter: gradients, Fisher blocks
    parts: dict[str, int] = {}
    if backend == "torch":
        parts["pairs"] = int(PASS_FRACTION * s * TORCH_PAIR_BYTES[kind])
        parts["per_gaussian"] = n * (16 * f + 24)
    else:
        parts["projection"] = n * (13 * f + 8)
        parts["binning"] = int(n * (2 * (REC + channels + 5) * f + 40)
                               + m * ((REC + channels) * f + 24))
        if kind == "fisher":
            parts["moments"] = int(m * MOMENTS * f + n * MOMENTS * 8)
        if kind == "render_grad":
            parts["pairs"] = int(s * (8 + f))
            parts["backward"] = int(m * (7 + channels) * 8 + n * (7 + channels) * (8 + f)
                                    + n * 10 * f)
    if kind == "render":
        parts["images"] = p * ((2 * channels + 4) * f + 16)
    else:
        parts["images"] = p * ((channels + 2) * f + 16)
        parts["outputs"] = params
    coef = _T_FISHER if kind == "fisher" else _T_RENDER
    sec = (coef[0] * n + coef[1] * m + coef[2] * s) * _T_SLACK
    if kind == "render_grad":
        sec *= _T_GRAD
    if backend == "torch":
        sec *= _T_TORCH
    return parts, sec


@dataclass(frozen=True)
class EstimateInputs:
    """What :func:`estimate` sizes (its arguments), checked once when built: a
    ``ValueError`` naming the argument for an unknown kind or backend or a bad size."""

    kind: Kind
    gaussians: int
    pixels: int
    pool: int = 0
    shortlist: int = 10
    acquired: int = 5
    sh_coeffs: int = 16
    dtype_bytes: int = 4
    footprint: float | None = None
    backend: Literal["numba", "torch"] = "numba"
    threads: int = 1

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {self.kind!r}")
        if self.backend not in ("numba", "torch"):
            raise ValueError(f"backend must be 'numba' or 'torch', got {self.backend!r}")
        for name, lo in (("gaussians", 0), ("pixels", 1), ("pool", 0), ("shortlist", 0),
                         ("acquired", 0), ("sh_coeffs", 1)):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < lo:
                raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")
        if self.dtype_bytes not in (4, 8):
            raise ValueError(f"dtype_bytes must be 4 or 8, got {self.dtype_bytes!r}")
        fp = self.footprint
        if fp is not None and not (fp >= 0 and math.isfinite(fp)):
            raise ValueError(f"footprint must be a finite area >= 0, got {fp!r}")
        t = self.threads
        if not isinstance(t, int) or isinstance(t, bool) or t < 1:
            raise ValueError(f"threads must be an integer >= 1, got {t!r}")


def _model(x: EstimateInputs) -> Estimate:
    """The model alone, without the margin."""
    n, p, f, k, kind = x.gaussians, x.pixels, x.dtype_bytes, x.sh_coeffs, x.kind
    area = footprint_area(n, p) if x.footprint is None else min(float(x.footprint), float(p))
    if kind in ("render", "render_grad", "fisher"):
        parts, sec = _pass(kind, n, p, area, f, k, 3, x.backend)
        return Estimate(sum(parts.values()), sec, parts)
    fisher_parts, fisher_sec = _pass("fisher", n, p, area, f, k, 3, x.backend)
    fisher_peak = sum(fisher_parts.values())
    if kind == "random":
        return Estimate(1 << 20, 1e-3, {"scores": 1 << 20})
    if kind == "full_eig":
        return Estimate(fisher_peak, x.pool * fisher_sec, {"fisher": fisher_peak})
    if kind == "fisherrf":
        h_train = 2 * n * (7 + 3 * k) * f  # H_train and its inverse, four blocks
        return Estimate(fisher_peak + h_train, (x.pool + x.acquired) * fisher_sec,
                        {"fisher": fisher_peak, "h_train": h_train})
    if kind == "cover":
        r_parts, r_sec = _pass("render", n, p, area, f, k, 4, x.backend)
        render_peak = sum(r_parts.values())
        bins = n * COVER_BINS + min(n, COVER_CHUNK) * COVER_BINS * 3 * f + n * (2 * f + 8)
        projection = n * (16 * f + 8)  # the acquired views' projections (the bins)
        return Estimate(render_peak + bins + projection,
                        x.pool * (r_sec + _T_COVER * n) + x.acquired * 0.4e-6 * n,
                        {"render": render_peak, "bins": bins, "projection": projection})
    agile = AGILE_BYTES + AGILE_BYTES_PER_GAUSSIAN * n
    sec = _T_AGILE * n + 0.05
    if kind == "agile":
        return Estimate(agile, sec, {"anchor_and_scoring": agile})
    return Estimate(agile + fisher_peak, sec + min(x.shortlist, max(x.pool, 1)) * fisher_sec,
                    {"anchor_and_scoring": agile, "fisher": fisher_peak})


def estimate(
    kind: Kind,
    gaussians: int,
    pixels: int,
    *,
    pool: int = 0,
    shortlist: int = 10,
    acquired: int = 5,
    sh_coeffs: int = 16,
    dtype_bytes: int = 4,
    footprint: float | None = None,
    backend: Literal["numba", "torch"] = "numba",
    threads: int = 1,
) -> Estimate:
    """Peak memory (an upper bound: the model with its margin) and time of a computation
    (see the module docstring).

    Args:
        kind: "render" (forward only), "render_grad" (forward and backward), "fisher" (one
            ``fisher_diag``), or a selection method: "random", "full_eig", "fisherrf",
            "cover", "agile", "agile_plus".
        gaussians: N, the map's Gaussians.
        pixels: P, width x height of the candidates' images.
        pool: the candidates a selection scores (its eligible pool).
        shortlist: AGILE-GS+'s reranked shortlist N.
        acquired: the acquired views (FisherRF rebuilds H_train from them; COVER bins them).
        sh_coeffs: SH coefficients per colour channel, (degree + 1)².
        dtype_bytes: 4 (float32, the default maps) or 8.
        footprint: mean α ≥ 1/255 box area of a visible Gaussian in pixels (None:
            :func:`footprint_area`).
        backend: "numba" (the compiled kernels) or "torch".
        threads: the compute threads the process runs it on (each beyond the first adds
            :data:`THREAD_ARENA_BYTES` to the margin).

    Raises:
        ValueError: naming the argument, for an unknown kind or backend or a bad size.
    """
    x = EstimateInputs(kind, gaussians, pixels, pool=pool, shortlist=shortlist,
                       acquired=acquired, sh_coeffs=sh_coeffs, dtype_bytes=dtype_bytes,
                       footprint=footprint, backend=backend, threads=threads)
    model = _model(x)
    margin = (math.ceil(model.peak_bytes * (MEMORY_MARGIN - 1.0)) + ALLOCATOR_BYTES
              + (threads - 1) * THREAD_ARENA_BYTES)
    return Estimate(model.peak_bytes + margin, model.seconds,
                    {**model.parts, "margin": margin})


def mean_footprint(gmap: object, camera: object, *, tile_size: int = 8) -> float:
    """The mean α ≥ 1/255 box area (pixels) of ``gmap``'s visible Gaussians from ``camera``,
    for :func:`estimate`'s ``footprint`` (one projection; the kernels' binning where they
    run, else the same boxes from the torch projection)."""
    import torch

    from agilegs.service.nbv.camera import Camera
    from agilegs.service.nbv.gaussians import GaussianMap
    from agilegs.service.nbv.projection import project_map
    from agilegs.service.nbv.rasterize import ALPHA_MIN

    if not isinstance(gmap, GaussianMap) or not isinstance(camera, Camera):
        raise TypeError("mean_footprint takes a GaussianMap and a Camera")
    with torch.no_grad():
        proj = project_map(gmap.detach(), camera)
    vis = proj.radii > 0
    if not bool(vis.any()):
        return 0.0
    op = proj.opacities[vis].to(torch.float64)
    cov = proj.cov2d[vis].to(torch.float64)
    kk = 2.0 * torch.log(torch.clamp(op / ALPHA_MIN, min=1.0))
    hx = torch.sqrt(kk * cov[:, 0].clamp_min(0))
    hy = torch.sqrt(kk * cov[:, 2].clamp_min(0))
    # the box of the ellipse, within the image and the binned tiles' reach (3σ radius)
    r = proj.radii[vis].to(torch.float64)
    wx = torch.minimum(2 * hx + 1, 2 * r + tile_size).clamp(max=camera.width)
    wy = torch.minimum(2 * hy + 1, 2 * r + tile_size).clamp(max=camera.height)
    return float((wx * wy).mean())


class SpeedCalibration:
    """This machine's speed against the reference CPU, learnt from timed computations.

    :meth:`observe` records measured / estimated seconds of a computation whose estimate is at
    least ``min_seconds`` (shorter ones are dominated by fixed costs: the kernels' loading, the
    request's own work); :attr:`factor` is the (high) median of the last ``window`` ratios (1
    before any: one outlier, a call that waited on another, does not set it), at least
    ``floor``; :meth:`bound` is ``seconds x factor x TIME_MARGIN``. Thread-safe.
    """

    def __init__(self, window: int = 32, min_seconds: float = 0.5, floor: float = 0.25
                 ) -> None:
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window!r}")
        if not (min_seconds >= 0 and floor > 0):
            raise ValueError("min_seconds must be >= 0 and floor > 0")
        self._ratios: deque[float] = deque(maxlen=window)
        self._lock = threading.Lock()
        self.min_seconds = min_seconds
        self.floor = floor

    def observe(self, estimated_s: float, measured_s: float) -> None:
        """Record one computation (its up-front estimate and its measured wall time, s)."""
        if not (math.isfinite(estimated_s) and math.isfinite(measured_s)):
            return
        if estimated_s < self.min_seconds or estimated_s <= 0 or measured_s < 0:
            return
        with self._lock:
            self._ratios.append(measured_s / estimated_s)

    @property
    def samples(self) -> int:
        """How many ratios the window holds."""
        with self._lock:
            return len(self._ratios)

    @property
    def factor(self) -> float:
        """The high median of the recent measured / estimated ratios (1 before any), at least
        ``floor``."""
        with self._lock:
            typical = statistics.median_high(self._ratios) if self._ratios else 1.0
        return max(typical, self.floor)

    def bound(self, seconds: float) -> float:
        """An estimate in seconds of the reference CPU as a bound on this machine (s)."""
        return seconds * self.factor * TIME_MARGIN
