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
during its selections, and ``base_rss_mb`` the process's before the first selection (the map,
Hhat and the pool); ``peak_rss_mb`` of the run is the process's own peak (``getrusage``).

Entries are methods and variants (:mod:`agilegs.service.bench.variants`): by default the
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
from pathlib import Path
from types import TracebackType
from typing import Any

import torch

from agilegs.config.selection import SelectConfig
from agilegs.config.types import validate_config
from agilegs.service.nbv.camera import Camera, Intrinsics
from agilegs.service.nbv.candidates import capture_pool, scene_center_radius
from agilegs.service.nbv.gaussians import GaussianMap, load_scene
from agilegs.service.nbv.information import (
    accumulate_information,
    eig_scores,
    fisher_diag,
    init_information,
)
from agilegs.service.nbv.methods.base import get_method, method_names
from agilegs.service.nbv.rotations import quat_to_rotmat
from agilegs.service.nbv.selectors import select, select_validated

from .options import add_latency_arguments
from .stages import ANCHOR_STAGES
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


def run(args: argparse.Namespace) -> int:
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    if args.pool < 1 or args.shortlist < 1 or args.events < 1 or args.acquired < 0:
        raise SystemExit("--pool, --shortlist and --events must be >= 1, --acquired >= 0")
    names = _method_list(args.methods)
    t_setup = time.perf_counter()
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit(f"--device {args.device}: CUDA is not available here")
    gmap = _load_map(args.scene, args.max_gaussians, args.seed).to(device=device)
    center, r98 = scene_center_radius(gmap.means)
    intr = Intrinsics.from_fov(args.fov, args.width, args.height)
    total = args.pool + args.acquired
    poses = capture_pool(center.cpu(), args.orbit_scale * r98, total, seed=args.seed).to(device)
    acq_idx = (
        sorted({int(round(i * total / args.acquired)) % total for i in range(args.acquired)})
        if args.acquired
        else []
    )
    acquired = poses[acq_idx]
    keep = [i for i in range(total) if i not in set(acq_idx)]
    pool = poses[keep]
    h_acc = init_information(gmap, args.lam)
    with torch.no_grad():
        for p in acquired:
            h_acc = accumulate_information(h_acc, fisher_diag(gmap, Camera(c2w=p, intrinsics=intr)))
    base = SelectConfig(shortlist_size=args.shortlist, seed=args.seed)
    log.info(
        "map %d Gaussians, pool %d, %d acquired, setup %.1f s",
        len(gmap),
        len(pool),
        len(acquired),
        time.perf_counter() - t_setup,
    )
    # warm-up: first calls pay one-off allocation costs
    select("agile", gmap, h_acc, pool, intr, config=base, acquired=acquired)
    with torch.no_grad():
        fisher_diag(gmap, Camera(c2w=pool[0], intrinsics=intr))

    records: dict[str, dict[str, Any]] = {
        n: {"latency_ms": [], "event_ms": [], "cpu_ms": [], "stages": [], "pct": [],
            "head_pct": [], "picks": [], "other_ms": [], "commit_ms": [], "peak_mb": 0.0}
        for n in names
    }
    base_rss = rss_mb()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
        gpu_base = torch.cuda.memory_allocated(device)
    upkeep_ms: list[float] = []
    states: dict[str, dict[str, Any] | None] = {n: None for n in names}
    variants = {n: parse_variant(n, args.shortlist) for n in names}
    # every entry's settings validated once, as the service does: each event selects through
    # select_validated on the map, Hhat and pool set up (and checked) here
    configs = {n: validate_config(SelectConfig, variants[n].config(base)) for n in names}
    order = sorted(names, key=lambda n: n != REFERENCE)  # the yardstick first, when timed
    for event in range(args.events):
        phi_all: torch.Tensor | None = None
        if REFERENCE not in names:  # the yardstick, untimed
            phi_all = eig_scores(gmap, h_acc, pool, intr)
        for name in order:
            v = variants[name]
            cpu0 = time.process_time()
            with PeakRSS() as mem:
                sel = select_validated(
                    v.method, gmap, h_acc, pool, intr, config=configs[name],
                    acquired=acquired, state=states[name],
                )
            cpu_ms = (time.process_time() - cpu0) * 1e3
            records[name]["peak_mb"] = max(records[name]["peak_mb"], mem.peak)
            states[name] = sel.state
            if name == REFERENCE:
                phi_all = torch.tensor(
                    [sel.scores[i] for i in range(len(pool))], dtype=torch.float64
                )
            assert phi_all is not None
            rec = records[name]
            rec["latency_ms"].append(sel.latency_ms["total"] - sel.latency_ms["information"])
            rec["event_ms"].append(sel.latency_ms["total"])  # the upkeep is added below
            rec["cpu_ms"].append(cpu_ms)
            rec["stages"].append(dict(sel.latency_ms))
            # "total" and the sub-stages ("anchor.<stage>", within their stage) left out
            staged = sum(v for k, v in sel.latency_ms.items() if k != "total" and "." not in k)
            rec["other_ms"].append(sel.latency_ms["total"] - staged)
            rec["commit_ms"].append(0.0)  # the upkeep is added below, unless reused
            rec["reused"] = sel.chosen_information is not None
            rec["pct"].append(eig_percentile(phi_all, float(phi_all[sel.index])))
            rec["picks"].append(sel.index)
            if sel.shortlist:
                rec["head_pct"].append(eig_percentile(phi_all, float(phi_all[sel.shortlist[0]])))
                rec.setdefault("shortlist_best_pct", []).append(
                    max(eig_percentile(phi_all, float(phi_all[i])) for i in sel.shortlist)
                )
            if "psi_evaluations" in sel.details:
                rec.setdefault("evaluations", []).append(float(sel.details["psi_evaluations"]))
            split = sel.details.get("ascent_evaluations")
            if split:
                rec.setdefault("gradient_evals", []).append(float(split["gradient"]))
                rec.setdefault("value_evals", []).append(float(split["value"]))
            if sel.psi_trace:
                rec.setdefault("psi_gain", []).append(sel.psi_trace[-1] / sel.psi_trace[0])
            pool_psi = sel.details.get("pool_proxy_psi")
            if pool_psi and len(pool_psi) == len(pool):
                proxy = torch.tensor([pool_psi[i] for i in range(len(pool))], dtype=torch.float64)
                rec.setdefault("spearman", []).append(spearman(proxy, phi_all))
            log.info(
                "event %d %-26s %9.1f ms  pick %3d  eig pct %5.1f",
                event,
                name,
                sel.latency_ms["total"],
                sel.index,
                rec["pct"][-1],
            )
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
                records[name]["event_ms"][-1] += upkeep
                if not records[name]["reused"]:
                    records[name]["commit_ms"][-1] = upkeep
        acquired = torch.cat([acquired, pool[nxt : nxt + 1]])
        pool = torch.cat([pool[:nxt], pool[nxt + 1 :]])

    methods_out: dict[str, Any] = {}
    for name, rec in records.items():
        stages = {k: statistics.median(s[k] for s in rec["stages"]) for k in rec["stages"][0]}
        out: dict[str, Any] = {
            "median_ms": statistics.median(rec["latency_ms"]),
            "latency_ms": rec["latency_ms"],
            "event_median_ms": statistics.median(rec["event_ms"]),
            "event_ms": rec["event_ms"],
            "cpu_median_ms": statistics.median(rec["cpu_ms"]),
            "stages_ms": stages,
            "other_median_ms": statistics.median(rec["other_ms"]),
            "commit_median_ms": statistics.median(rec["commit_ms"]),
            "eig_percentile": statistics.fmean(rec["pct"]),
            "eig_percentiles": rec["pct"],
            "picks": rec["picks"],
            "peak_rss_mb": rec["peak_mb"],
        }
        if rec["head_pct"]:
            out["head_eig_percentile"] = statistics.fmean(rec["head_pct"])
            out["shortlist_best_eig_percentile"] = statistics.fmean(rec["shortlist_best_pct"])
        if rec.get("evaluations"):
            out["psi_evaluations"] = statistics.median(rec["evaluations"])
        if rec.get("gradient_evals"):
            out["gradient_evaluations"] = statistics.median(rec["gradient_evals"])
            out["value_evaluations"] = statistics.median(rec["value_evals"])
        if rec.get("psi_gain"):
            out["psi_gain"] = statistics.fmean(rec["psi_gain"])
        if rec.get("spearman"):
            out["proxy_spearman"] = statistics.fmean(rec["spearman"])
        methods_out[name] = out
    for ref in RATIOS:
        if ref not in methods_out:
            continue
        r = methods_out[ref]
        for out in methods_out.values():
            out[f"speedup_vs_{ref}"] = r["median_ms"] / max(out["median_ms"], 1e-9)
            out[f"event_speedup_vs_{ref}"] = r["event_median_ms"] / max(out["event_median_ms"],
                                                                       1e-9)
            out[f"cpu_speedup_vs_{ref}"] = r["cpu_median_ms"] / max(out["cpu_median_ms"], 1e-9)
    result = {
        "config": {
            "scene": str(args.scene),
            "pool": args.pool,
            "shortlist": args.shortlist,
            "width": args.width,
            "height": args.height,
            "fov_deg": args.fov,
            "max_gaussians": args.max_gaussians,
            "gaussians": len(gmap),
            "events": args.events,
            "acquired": args.acquired,
            "orbit_scale": args.orbit_scale,
            "lam": args.lam,
            "seed": args.seed,
            "device": (torch.cuda.get_device_name(device) if device.type == "cuda"
                       else "cpu"),
            "torch_threads": torch.get_num_threads(),
            "torch": torch.__version__,
            "cpu_count": os.cpu_count(),
            "platform": platform.platform(),
            "methods": names,
        },
        "base_rss_mb": base_rss,
        # the kernel's high-water mark lags the sampled RSS by a little: the larger of both
        "peak_rss_mb": max([peak_rss_mb(), base_rss] + [r["peak_mb"] for r in records.values()]),
        "upkeep_ms": upkeep_ms,
        "methods": methods_out,
    }
    if device.type == "cuda":
        result["gpu_base_mb"] = gpu_base / 2**20
        result["gpu_peak_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
    _print_table(methods_out)
    sys.stdout.write(f"RSS before the selections {base_rss:.0f} MiB; process peak "
                     f"{result['peak_rss_mb']:.0f} MiB\n")
    if args.json_out:
        Path(args.json_out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json_out).write_text(json.dumps(result, indent=2))
        log.info("wrote %s", args.json_out)
    return 0


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
            "| method | anchor ms | " + " | ".join(ANCHOR_STAGES) + " | ascent: gradient "
            "evaluations | ms | ms each | ascent: value evaluations | ms | ms each |",
            "|---|---|" + "---|" * (len(ANCHOR_STAGES) + 6),
        ]
        for name, m in split:
            s = m["stages_ms"]
            cells = " | ".join(f"{s.get('anchor.' + k, float('nan')):.1f}"
                               for k in ANCHOR_STAGES)
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
