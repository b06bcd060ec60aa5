"""``agilegs bench latency``: selection latency and EIG percentile of every method.

Loads a scene as the current map (a seeded subsample to ``--max-gaussians``, or, when the
scene holds fewer, the scene densified to that many: :func:`densified`), builds a
pool as a capture would (``capture_pool``: orbits at three elevations with near-duplicates)
plus a few evenly spread acquired views, forms Hhat = lambda + sum of their Fisher, and then,
for each of ``--events`` selection events, times every entry on the same map, Hhat and pool
in this one process. The exact EIG phi of every pool candidate (the ``full_eig`` method's
scores when it is timed, else computed untimed) is the yardstick of every entry's
``eig_percentile``: the percentage of pool candidates whose phi is at most the chosen one's
(100 = the full-pool pick), averaged over events. After each event the full-pool pick is
acquired (Hhat updated, the view leaves the pool), so every entry sees the same sequence of
states; each keeps its own warm-start state across events.

Two latencies per entry: ``median_ms``, the selection alone (wall clock of ``select`` less
the information a method rebuilds inside it), and ``event_median_ms``, one event of that
method's own algorithm: the selection plus the information upkeep it needs. FisherRF
rebuilds H_train from every training view inside its selection (its ``information`` stage);
the Hhat-based methods (``full_eig``, ``agile``, ``agile_plus``) add the committed view's
Fisher to Hhat (one pass, timed on that view at every event: ``upkeep_ms``); Random and
COVER keep nothing (COVER rebuilds its bins inside its selection). Where the time goes:
``stages_ms`` (per-stage medians of the selection), ``other_median_ms`` (the selection's
total less its stages: the eligible candidates, the pool's radius; the settings and inputs
are validated once, at set-up, as the service does) and ``commit_median_ms``, what the
service pays at commit: the upkeep pass, or nothing where the selection computed the chosen
view's Fisher while scoring (``full_eig``, ``agile_plus``: ``Selection.chosen_information``,
reused at commit).

Memory: ``peak_rss_mb`` per entry is the largest resident set size sampled (every few ms)
during its selections, ``base_rss_mb`` the process's before the first selection, and the run's
``peak_rss_mb`` the process's own peak (``getrusage``).

Entries are methods and variants (:mod:`agilegs.lab.bench.variants`): by default the
methods, the shortlist ablations (``agile@knearest``, ``agile_plus@topnorm``, ...) and the
anchor variants that measure what each shortcut costs (:data:`VARIANTS`). Each record also
holds ``cpu_median_ms`` (process CPU time of the ``select`` call, less sensitive to other
load on a shared machine), ``stages_ms`` (per-stage medians), ``eig_percentile``, for anchor
methods ``proxy_spearman`` (the rank correlation of the anchor's proxy psi of every pool
candidate with the exact phi, mean over events) and, for shortlist methods,
``head_eig_percentile`` (the percentile of the shortlist's first, i.e. what AGILE-GS picks
from that shortlist).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import platform
import resource
import statistics
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import torch

from agilegs.config.selection import SelectConfig
from agilegs.config.types import validate_config
from agilegs.service.nbv import (
    Camera,
    GaussianMap,
    Intrinsics,
    Selection,
    accumulate_information,
    eig_scores,
    fisher_diag,
    init_information,
    load_scene,
    select,
)
from agilegs.service.nbv.candidates import capture_pool, scene_center_radius
from agilegs.service.nbv.methods.base import get_method, method_names
from agilegs.service.nbv.rotations import quat_to_rotmat
from agilegs.service.nbv.selectors import SelectInputs, select_from

from .options import add_latency_arguments, use_threads
from .stages import TABLE_STAGES
from .variants import parse_variant

log = logging.getLogger(__name__)

add_arguments = add_latency_arguments
REFERENCE = "full_eig"
"""The full-pool exact EIG: its phi of every candidate is every entry's yardstick."""
RATIOS = ("full_eig", "fisherrf")
"""Methods every entry's speed is compared with (when timed)."""
ABLATIONS = tuple(
    f"{m}@{s}" for s in ("knearest", "topnorm", "online") for m in ("agile", "agile_plus")
)
VARIANTS = (
    "agile_plus@no_ascent",
    "agile_plus@cold",
    "agile_plus@all_gaussians",
    "agile_plus@start_view",
    "agile_plus@typical",
    "agile_plus@quarter_unseen",
    "agile_plus@point_zbuffer",
    "agile_plus@cover_zbuffer",
    "agile_plus@mixed_zbuffer",
    "agile_plus@exact",
    "agile@paper",
    "agile_plus@paper",
)
SLOW = ("agile_plus@exact", "agile@paper", "agile_plus@paper")
"""Variants that ascend the exact psi through the rasterizer (seconds per selection)."""


def _load_map(path: str, max_gaussians: int, seed: int) -> Any:
    """The scene (a .ply / .splat file or a folder holding one), subsampled or densified to
    ``max_gaussians`` (0: as it is); SystemExit naming --scene when it cannot be read."""
    try:
        gmap = load_scene(path)
    except (OSError, ValueError) as exc:
        raise SystemExit(f"--scene {path}: {exc}") from None
    if 0 < max_gaussians < len(gmap):
        gen = torch.Generator().manual_seed(seed)
        idx = torch.sort(torch.randperm(len(gmap), generator=gen)[:max_gaussians]).values
        gmap = gmap.subset(idx)
    elif max_gaussians > len(gmap) > 0:
        gmap = densified(gmap, max_gaussians, seed)
    return gmap


def densified(gmap: GaussianMap, n: int, seed: int = 0) -> GaussianMap:
    """A map of ``n`` Gaussians made from ``gmap`` (fewer than n) as 3D Gaussian Splatting's
    densification splits a Gaussian: Gaussian i % N of the original is the parent of child i,
    drawn from the parent's own 3D normal, with its rotation, opacity and colour and its scales
    divided by k^(1/3) (k children per parent, so the volume they cover stays); the parents
    are dropped. A stand-in for a capture's map of that size (seeded)."""
    n0 = len(gmap)
    g = gmap.detach()
    gen = torch.Generator().manual_seed(seed)
    parent = torch.arange(n) % n0
    k = torch.bincount(parent, minlength=n0).to(g.dtype)
    eps = torch.randn(n, 3, generator=gen, dtype=g.dtype)
    rot = quat_to_rotmat(g.quats[parent])
    offset = (rot @ (torch.exp(g.log_scales[parent]) * eps)[..., None])[..., 0]
    return GaussianMap(
        means=g.means[parent] + offset,
        log_scales=g.log_scales[parent] - torch.log(k[parent])[:, None] / 3.0,
        quats=g.quats[parent],
        opacity_logits=g.opacity_logits[parent],
        sh=g.sh[parent],
    )


def rss_mb() -> float:
    """The process's resident set size in MiB (Linux /proc; elsewhere its peak so far)."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:
        return peak_rss_mb()


def peak_rss_mb() -> float:
    """The process's peak resident set size so far, MiB."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 1024.0


class PeakRSS:
    """The largest RSS sampled every ``interval`` seconds while the block runs (MiB)."""

    def __init__(self, interval: float = 0.005) -> None:
        self.interval = interval
        self.peak = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> PeakRSS:
        self.peak = rss_mb()

        def poll() -> None:
            while not self._stop.wait(self.interval):
                self.peak = max(self.peak, rss_mb())

        self._thread = threading.Thread(target=poll, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.peak = max(self.peak, rss_mb())


def spearman(a: torch.Tensor, b: torch.Tensor) -> float:
    """Spearman rank correlation of two score vectors [D] (ties broken by index)."""
    if a.numel() < 2:
        return float("nan")
    ra = a.argsort(stable=True).argsort().to(torch.float64)
    rb = b.argsort(stable=True).argsort().to(torch.float64)
    return float(torch.corrcoef(torch.stack([ra, rb]))[0, 1])


def _method_list(spec: str) -> list[str]:
    """The entries to time: ``all``, ``base`` (the methods), ``fast`` (all but the exact-psi
    variant) or comma-separated method names and variant keys, in any order."""
    base = list(method_names())
    if spec == "all":
        return base + list(ABLATIONS + VARIANTS)
    if spec == "fast":
        return base + [m for m in ABLATIONS + VARIANTS if m not in SLOW]
    if spec == "base":
        return base
    names = list(dict.fromkeys(s.strip() for s in spec.split(",") if s.strip()))
    if not names:
        raise SystemExit("--methods: name at least one method")
    for n in names:
        try:
            parse_variant(n)
        except ValueError as exc:
            raise SystemExit(f"--methods: {exc}") from None
    return names


def eig_percentile(phi: torch.Tensor, value: float) -> float:
    """Percentage of the pool whose phi [D] is at or below ``value`` (100: the best view)."""
    return 100.0 * float((phi <= value + 1e-12 * abs(value)).to(torch.float64).mean())


@dataclass(frozen=True)
class Plan:
    """The entries to time, and the device of the map, Ĥ, the pool and the methods."""

    names: list[str]
    device: torch.device


@dataclass
class Setup:
    """What every entry selects on: map, camera, pool [D, 4, 4], acquired views [A, 4, 4], Ĥ."""

    gmap: GaussianMap
    intrinsics: Intrinsics
    pool: torch.Tensor
    acquired: torch.Tensor
    h_acc: dict[str, torch.Tensor]
    base: SelectConfig


@dataclass
class EntryRecord:
    """One entry's figures, an item per event (the lists) or over them (``peak_mb``):
    ``latency_ms`` and ``event_ms`` as ``median_ms`` and ``event_median_ms`` above."""

    latency_ms: list[float] = field(default_factory=list)
    event_ms: list[float] = field(default_factory=list)
    cpu_ms: list[float] = field(default_factory=list)
    stages: list[dict[str, float]] = field(default_factory=list)
    other_ms: list[float] = field(default_factory=list)
    commit_ms: list[float] = field(default_factory=list)
    pct: list[float] = field(default_factory=list)
    head_pct: list[float] = field(default_factory=list)
    shortlist_best_pct: list[float] = field(default_factory=list)
    picks: list[int] = field(default_factory=list)
    evaluations: list[float] = field(default_factory=list)
    gradient_evals: list[float] = field(default_factory=list)
    value_evals: list[float] = field(default_factory=list)
    psi_gain: list[float] = field(default_factory=list)
    spearman: list[float] = field(default_factory=list)
    peak_mb: float = 0.0
    reused: bool = False
    """The last selection computed the chosen view's Fisher (reused at commit)."""

    def add(self, sel: Selection, cpu_ms: float, peak_mb: float, phi: torch.Tensor) -> None:
        """One event's selection, with the exact EIG of the pool ``phi`` [D]."""
        lat = sel.latency_ms
        self.peak_mb = max(self.peak_mb, peak_mb)
        self.latency_ms.append(lat["total"] - lat["information"])
        self.event_ms.append(lat["total"])  # the upkeep is added by add_upkeep
        self.cpu_ms.append(cpu_ms)
        self.stages.append(dict(lat))
        # "total" and the sub-stages ("anchor.<stage>", within their stage) left out
        self.other_ms.append(lat["total"] - sum(v for k, v in lat.items()
                                                if k != "total" and "." not in k))
        self.commit_ms.append(0.0)  # the upkeep is added by add_upkeep, unless reused
        self.reused = sel.chosen_information is not None
        self.pct.append(eig_percentile(phi, float(phi[sel.index])))
        self.picks.append(sel.index)
        if sel.shortlist:
            self.head_pct.append(eig_percentile(phi, float(phi[sel.shortlist[0]])))
            self.shortlist_best_pct.append(max(eig_percentile(phi, float(phi[i]))
                                               for i in sel.shortlist))
        if "psi_evaluations" in sel.details:
            self.evaluations.append(float(sel.details["psi_evaluations"]))
        split = sel.details.get("ascent_evaluations")
        if split:
            self.gradient_evals.append(float(split["gradient"]))
            self.value_evals.append(float(split["value"]))
        if sel.psi_trace:
            self.psi_gain.append(sel.psi_trace[-1] / sel.psi_trace[0])
        pool_psi = sel.details.get("pool_proxy_psi")
        if pool_psi and len(pool_psi) == phi.numel():
            proxy = torch.tensor([pool_psi[i] for i in range(phi.numel())], dtype=torch.float64,
                                 device=phi.device)
            self.spearman.append(spearman(proxy, phi))

    def add_upkeep(self, upkeep_ms: float) -> None:
        """The committed view's Fisher added to Ĥ, which an Ĥ method pays per event (at
        commit, unless its selection computed it)."""
        self.event_ms[-1] += upkeep_ms
        if not self.reused:
            self.commit_ms[-1] = upkeep_ms

    def summary(self) -> dict[str, Any]:
        """The entry's figures in the JSON (medians and means over the events)."""
        med, mean = statistics.median, statistics.fmean
        out: dict[str, Any] = {
            "median_ms": med(self.latency_ms),
            "latency_ms": self.latency_ms,
            "event_median_ms": med(self.event_ms),
            "event_ms": self.event_ms,
            "cpu_median_ms": med(self.cpu_ms),
            "stages_ms": {k: med(s[k] for s in self.stages) for k in self.stages[0]},
            "other_median_ms": med(self.other_ms),
            "commit_median_ms": med(self.commit_ms),
            "eig_percentile": mean(self.pct),
            "eig_percentiles": self.pct,
            "picks": self.picks,
            "peak_rss_mb": self.peak_mb,
        }
        if self.head_pct:
            out["head_eig_percentile"] = mean(self.head_pct)
            out["shortlist_best_eig_percentile"] = mean(self.shortlist_best_pct)
        if self.evaluations:
            out["psi_evaluations"] = med(self.evaluations)
        if self.gradient_evals:
            out["gradient_evaluations"] = med(self.gradient_evals)
            out["value_evaluations"] = med(self.value_evals)
        if self.psi_gain:
            out["psi_gain"] = mean(self.psi_gain)
        if self.spearman:
            out["proxy_spearman"] = mean(self.spearman)
        return out


@dataclass
class Timings:
    """What the events measured: every entry's record, each event's upkeep pass, the RSS before
    the first selection and, on a GPU, the memory allocated then and the peak after it."""

    entries: dict[str, EntryRecord]
    upkeep_ms: list[float]
    base_rss_mb: float
    gpu_base_mb: float | None = None
    gpu_peak_mb: float | None = None


def run(args: argparse.Namespace) -> int:
    plan = parse(args)
    setup = set_up(args, plan.device)
    timings = time_events(setup, plan.names, args.events, args.shortlist)
    result = summarise(args, setup, plan, timings)
    write(result, args.json_out)
    return 0


def parse(args: argparse.Namespace) -> Plan:
    """The entries to time (``--methods``) and the device, the numbers checked, torch's
    threads set."""
    use_threads(args.threads)
    if args.pool < 1 or args.shortlist < 1 or args.events < 1 or args.acquired < 0:
        raise SystemExit("--pool, --shortlist and --events must be >= 1, --acquired >= 0")
    names = _method_list(args.methods)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit(f"--device {args.device}: CUDA is not available here")
    return Plan(names, device)


def set_up(args: argparse.Namespace, device: torch.device) -> Setup:
    """The map, a capture-like pool, ``--acquired`` views spread evenly over it and their Ĥ,
    on ``device``."""
    t_setup = time.perf_counter()
    gmap = _load_map(args.scene, args.max_gaussians, args.seed).to(device=device)
    center, r98 = scene_center_radius(gmap.means)
    intr = Intrinsics.from_fov(args.fov, args.width, args.height)
    total = args.pool + args.acquired
    poses = capture_pool(center.cpu(), args.orbit_scale * r98, total, seed=args.seed).to(device)
    acq_idx = (sorted({int(round(i * total / args.acquired)) % total
                       for i in range(args.acquired)}) if args.acquired else [])
    acquired = poses[acq_idx]
    pool = poses[[i for i in range(total) if i not in set(acq_idx)]]
    h_acc = init_information(gmap, args.lam)
    with torch.no_grad():
        for p in acquired:
            h_acc = accumulate_information(h_acc, fisher_diag(gmap, Camera(c2w=p, intrinsics=intr)))
    base = SelectConfig(shortlist_size=args.shortlist, seed=args.seed)
    log.info("map %d Gaussians, pool %d, %d acquired, setup %.1f s", len(gmap), len(pool),
             len(acquired), time.perf_counter() - t_setup)
    # warm-up: first calls pay one-off allocation costs
    select("agile", gmap, h_acc, pool, intr, config=base, acquired=acquired)
    with torch.no_grad():
        fisher_diag(gmap, Camera(c2w=pool[0], intrinsics=intr))
    return Setup(gmap, intr, pool, acquired, h_acc, base)


def time_events(setup: Setup, names: list[str], events: int, shortlist: int) -> Timings:
    """``events`` selection events: every entry selects on the same map, Ĥ and pool (each with
    its own warm state), then the full-pool EIG's pick is acquired for all."""
    gmap, intr, pool, acquired, h_acc = (setup.gmap, setup.intrinsics, setup.pool,
                                         setup.acquired, setup.h_acc)
    entries = {n: EntryRecord() for n in names}
    base_rss = rss_mb()
    device = setup.gmap.means.device
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
        gpu_base = torch.cuda.memory_allocated(device)
    upkeep_ms: list[float] = []
    states: dict[str, dict[str, Any] | None] = {n: None for n in names}
    variants = {n: parse_variant(n, shortlist) for n in names}
    # every entry's settings validated once, as the service does: each event selects through
    # select_from on the map, Hhat and pool set up (and checked) here
    configs = {n: validate_config(SelectConfig, variants[n].config(setup.base)) for n in names}
    order = sorted(names, key=lambda n: n != REFERENCE)  # the yardstick first, when timed
    for event in range(events):
        phi_all: torch.Tensor | None = None
        if REFERENCE not in names:  # the yardstick, untimed
            phi_all = eig_scores(gmap, h_acc, pool, intr)
        for name in order:
            cpu0 = time.process_time()
            with PeakRSS() as mem:
                sel = select_from(SelectInputs(variants[name].method, gmap, h_acc, pool, intr,
                                               configs[name], acquired), state=states[name])
            cpu_ms = (time.process_time() - cpu0) * 1e3
            states[name] = sel.state
            if name == REFERENCE:
                phi_all = torch.tensor([sel.scores[i] for i in range(len(pool))],
                                       dtype=torch.float64)
            assert phi_all is not None
            entries[name].add(sel, cpu_ms, mem.peak, phi_all)
            log.info("event %d %-26s %9.1f ms  pick %3d  eig pct %5.1f", event, name,
                     sel.latency_ms["total"], sel.index, entries[name].pct[-1])
        # acquire the full-EIG pick: the same trajectory for every method
        assert phi_all is not None
        nxt = int(torch.argmax(phi_all))
        t0 = time.perf_counter()
        with torch.no_grad():
            hv = fisher_diag(gmap, Camera(c2w=pool[nxt], intrinsics=intr))
        h_acc = accumulate_information(h_acc, hv)
        upkeep = (time.perf_counter() - t0) * 1e3
        upkeep_ms.append(upkeep)
        for name in names:  # the Hhat methods add the committed view's Fisher to Hhat
            if get_method(variants[name].method).uses_information:
                entries[name].add_upkeep(upkeep)
        acquired = torch.cat([acquired, pool[nxt : nxt + 1]])
        pool = torch.cat([pool[:nxt], pool[nxt + 1 :]])
    if device.type == "cuda":
        return Timings(entries, upkeep_ms, base_rss, gpu_base / 2**20,
                       torch.cuda.max_memory_allocated(device) / 2**20)
    return Timings(entries, upkeep_ms, base_rss)


def summarise(args: argparse.Namespace, setup: Setup, plan: Plan,
              timings: Timings) -> dict[str, Any]:
    """The JSON: the settings and the machine, every entry's figures and its speed-ups over
    the :data:`RATIOS` methods timed, the process's memory."""
    methods_out = {name: rec.summary() for name, rec in timings.entries.items()}
    for ref in RATIOS:
        if ref not in methods_out:
            continue
        r = methods_out[ref]
        for out in methods_out.values():
            out[f"speedup_vs_{ref}"] = r["median_ms"] / max(out["median_ms"], 1e-9)
            out[f"event_speedup_vs_{ref}"] = r["event_median_ms"] / max(out["event_median_ms"],
                                                                       1e-9)
            out[f"cpu_speedup_vs_{ref}"] = r["cpu_median_ms"] / max(out["cpu_median_ms"], 1e-9)
    result: dict[str, Any] = {
        "config": {
            "scene": str(args.scene),
            "pool": args.pool,
            "shortlist": args.shortlist,
            "width": args.width,
            "height": args.height,
            "fov_deg": args.fov,
            "max_gaussians": args.max_gaussians,
            "gaussians": len(setup.gmap),
            "events": args.events,
            "acquired": args.acquired,
            "orbit_scale": args.orbit_scale,
            "lam": args.lam,
            "seed": args.seed,
            "device": (torch.cuda.get_device_name(plan.device) if plan.device.type == "cuda"
                       else "cpu"),
            "torch_threads": torch.get_num_threads(),
            "torch": torch.__version__,
            "cpu_count": os.cpu_count(),
            "platform": platform.platform(),
            "methods": plan.names,
        },
        "base_rss_mb": timings.base_rss_mb,
        # the kernel's high-water mark lags the sampled RSS by a little: the larger of both
        "peak_rss_mb": max([peak_rss_mb(), timings.base_rss_mb]
                           + [r.peak_mb for r in timings.entries.values()]),
        "upkeep_ms": timings.upkeep_ms,
        "methods": methods_out,
    }
    if timings.gpu_base_mb is not None:
        result["gpu_base_mb"] = timings.gpu_base_mb
        result["gpu_peak_mb"] = timings.gpu_peak_mb
    return result


def write(result: dict[str, Any], json_out: str | None) -> None:
    """The tables and the memory line on stdout; the JSON to ``json_out``."""
    _print_table(result["methods"])
    sys.stdout.write(f"RSS before the selections {result['base_rss_mb']:.0f} MiB; process peak "
                     f"{result['peak_rss_mb']:.0f} MiB\n")
    if json_out:
        Path(json_out).parent.mkdir(parents=True, exist_ok=True)
        Path(json_out).write_text(json.dumps(result, indent=2))
        log.info("wrote %s", json_out)


def _print_table(methods: dict[str, Any]) -> None:
    lines = [
        "| method | selection ms | per event ms | information | anchor | scoring | leverage | "
        "rerank | other | commit | full EIG / method | FisherRF / method | "
        "FisherRF / method (per event) | CPU ms | EIG pct | head pct | proxy Spearman | "
        "peak RSS MB |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, m in methods.items():
        s = m["stages_ms"]
        head = m.get("head_eig_percentile")
        rho = m.get("proxy_spearman")
        lines.append(
            f"| {name} | {m['median_ms']:.1f} | {m['event_median_ms']:.1f} | "
            f"{s['information']:.1f} | {s['anchor']:.1f} | {s['scoring']:.1f} | "
            f"{s['leverage']:.1f} | {s['rerank']:.1f} | {m['other_median_ms']:.2f} | "
            f"{m['commit_median_ms']:.1f} | "
            f"{_ratio(m, 'speedup_vs_full_eig')} | "
            f"{_ratio(m, 'speedup_vs_fisherrf')} | {_ratio(m, 'event_speedup_vs_fisherrf')} | "
            f"{m['cpu_median_ms']:.1f} | {m['eig_percentile']:.1f} | "
            f"{'' if head is None or math.isnan(head) else f'{head:.1f}'} | "
            f"{'' if rho is None or math.isnan(rho) else f'{rho:.2f}'} | "
            f"{m['peak_rss_mb']:.0f} |"
        )
    sys.stdout.write("\n".join(lines) + "\n")
    split = [(n, m) for n, m in methods.items() if "anchor.ascent" in m["stages_ms"]]
    if split:
        out = [
            "",
            "| method | anchor ms | " + " | ".join(TABLE_STAGES) + " | ascent: gradient "
            "evaluations | ms | ms each | ascent: value evaluations | ms | ms each |",
            "|---|---|" + "---|" * (len(TABLE_STAGES) + 6),
        ]
        for name, m in split:
            s = m["stages_ms"]
            cells = " | ".join(f"{s['anchor.' + k]:.1f}" if f"anchor.{k}" in s else "–"
                               for k in TABLE_STAGES)
            parts = []
            for kind, key in (("gradient", "anchor.ascent.gradients"),
                              ("value", "anchor.ascent.values")):
                ev = m.get(f"{kind}_evaluations")
                ms = s.get(key)
                parts.append(
                    f"{'' if ev is None else f'{ev:.0f}'} | "
                    f"{'' if ms is None else f'{ms:.1f}'} | "
                    f"{f'{ms / ev:.2f}' if ev and ms is not None else ''}")
            out.append(f"| {name} | {s['anchor']:.1f} | {cells} | " + " | ".join(parts) + " |")
        sys.stdout.write("\n".join(out) + "\n")


def _ratio(m: dict[str, Any], key: str) -> str:
    return f"{m[key]:.1f}x" if key in m else ""
