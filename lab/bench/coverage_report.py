"""``agilegs bench coverage DIR``: where each method's views went, and what it cost the test
views, from the run records of ``agilegs bench run --out DIR`` (numpy only; no run is
repeated).

Per run (``DIR/runs/<scene>/<variant>/seed<k>.json``):

- **Test coverage.** For every test view, the camera-centre distance to the nearest view the
  run acquired (in pool radii: the pool's median camera distance from its centre) and the
  smallest angle between its viewing direction (the camera's z axis) and an acquired view's,
  beside its PSNR; per run their means, the Pearson correlation of PSNR with each, and the
  mean PSNR of the test views farther (by angle) than the run's median against the nearer
  half. A record made before test poses were recorded has none of these.
- **Spread of the picks.** Sectors: the capture cut into ``--sectors`` equal azimuth sectors
  around the pool's centre, in the plane of the pool's two main axes (the camera centres'
  principal components), sector 0 centred on the first pool frame; per sector, how many pool
  frames, test frames, initial views and picks it holds. ``empty_sectors``: sectors holding at
  least half their fair share of the pool where the run picked nothing; ``max_share``: the
  largest share of the picks in one sector; ``tv_sectors``: the total-variation distance
  between the picks' and the pool's distribution over the sectors (0: picks spread as the pool;
  1: disjoint). The same along the capture path: the pool's indices (capture order) cut into
  ``--sectors`` equal runs (``tv_path``, ``empty_path``).
- **EIG mass** (runs made with ``bench run --eig-mass``): the means over events of where the
  chosen view's EIG lies (:mod:`agilegs.lab.bench.eig_mass`): the share from the nearer half
  of the Gaussians it informs, from those seen by fewer pool views than the median, from
  Gaussians no acquired view informed, and its target gain.

Writes ``DIR/coverage.md`` (one table per part, a row per method, means over scenes and
seeds, and a table per scene of the sector counts of every run) and ``DIR/coverage.json``
(every run's figures, per test view and per sector).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import statistics
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["add_arguments", "coverage_table", "load_runs", "path_bins", "run", "run_coverage",
           "sector_of", "summarise", "view_coverage"]

EIG_KEYS = ("near_share", "rare_share", "unseen_share", "pool_seen_weighted", "depth_ratio",
            "phi", "target_gain")
"""The per-event EIG-mass figures averaged per run."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    a = parser.add_argument
    a("out", metavar="DIR", help="an agilegs bench run output folder (its runs/ are read)")
    a("--sectors", type=int, default=8,
      help="azimuth sectors around the pool's centre, and runs along the capture path "
           "(default 8)")
    a("--json", dest="json_out", default=None,
      help="write the figures here (default DIR/coverage.json)")


# ----------------------------------------------------------------------------- geometry
def _plane_axes(centres: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pool's centre and its two main axes (principal components of the camera
    centres, largest first)."""
    origin = centres.mean(axis=0)
    _, _, vt = np.linalg.svd(centres - origin, full_matrices=False)
    return origin, vt[0], vt[1]


def sector_of(centres: np.ndarray, pool_centres: np.ndarray, sectors: int) -> np.ndarray:
    """The azimuth sector [P] (0..sectors-1) of camera centres [P, 3] around the centre of
    ``pool_centres`` [D, 3], in the plane of its two main axes; sector 0 is centred on the
    first pool camera's azimuth, the sectors follow in the sense of the main axes."""
    origin, a, b = _plane_axes(pool_centres)

    def azimuth(points: np.ndarray) -> np.ndarray:
        d = np.asarray(points, dtype=np.float64) - origin
        return np.arctan2(d @ b, d @ a)

    start = float(azimuth(np.asarray(pool_centres)[:1])[0]) - math.pi / sectors
    az = (azimuth(centres) - start) % (2 * math.pi)
    return np.minimum((az / (2 * math.pi) * sectors).astype(int), sectors - 1)


def path_bins(indices: Sequence[int], pool_size: int, bins: int) -> np.ndarray:
    """Which of ``bins`` equal runs of the capture order each pool index falls in."""
    idx = np.asarray(list(indices), dtype=np.int64)
    return np.minimum(idx * bins // max(pool_size, 1), bins - 1)


def _counts(labels: np.ndarray, n: int) -> list[int]:
    return np.bincount(labels, minlength=n).astype(int).tolist() if labels.size else [0] * n


def _tv(a: Sequence[int], b: Sequence[int]) -> float | None:
    sa, sb = sum(a), sum(b)
    if not sa or not sb:
        return None
    return 0.5 * sum(abs(x / sa - y / sb) for x, y in zip(a, b))


def _empty(picks: Sequence[int], pool: Sequence[int]) -> int:
    fair = sum(pool) / max(len(pool), 1)
    return sum(1 for p, q in zip(picks, pool) if q >= 0.5 * fair and p == 0)


def _pearson(x: Sequence[float], y: Sequence[float]) -> float | None:
    if len(x) < 3:
        return None
    xa, ya = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if xa.std() == 0 or ya.std() == 0:
        return None
    return float(np.corrcoef(xa, ya)[0, 1])


# ----------------------------------------------------------------------------- one run
def view_coverage(record: Mapping[str, Any]) -> dict[str, Any] | None:
    """Each test view's distance (pool radii) and viewing angle (degrees) to the nearest
    acquired view, with its PSNR, and their summary; None without test poses."""
    tests, pool = record.get("test_poses"), record.get("pool_poses")
    psnr = (record.get("per_view") or {}).get("psnr")
    if not tests or not pool or psnr is None:
        return None
    t = np.asarray(tests, dtype=np.float64)
    p = np.asarray(pool, dtype=np.float64)
    acq = p[[int(i) for i in record.get("sequence", [])]]
    if not len(acq):
        return None
    origin = p[:, :3, 3].mean(axis=0)
    radius = max(float(np.median(np.linalg.norm(p[:, :3, 3] - origin, axis=1))), 1e-9)
    dist = np.linalg.norm(t[:, None, :3, 3] - acq[None, :, :3, 3], axis=-1).min(axis=1) / radius
    cos = np.clip(t[:, :3, 2] @ acq[:, :3, 2].T, -1.0, 1.0).max(axis=1)
    angle = np.degrees(np.arccos(cos))
    ps = [min(float(x), 100.0) for x in psnr]
    far = angle > np.median(angle)
    return {
        "views": [{"distance": float(d), "angle_deg": float(a), "psnr": q}
                  for d, a, q in zip(dist, angle, ps)],
        "distance_mean": float(dist.mean()),
        "angle_mean_deg": float(angle.mean()),
        "psnr_vs_angle": _pearson(angle.tolist(), ps),
        "psnr_vs_distance": _pearson(dist.tolist(), ps),
        "psnr_far_half": statistics.fmean(q for q, f in zip(ps, far) if f) if far.any() else None,
        "psnr_near_half": (statistics.fmean(q for q, f in zip(ps, far) if not f)
                           if (~far).any() else None),
    }


def run_coverage(record: Mapping[str, Any], sectors: int = 8) -> dict[str, Any] | None:
    """Every figure of one run record (see the module docstring); None without pool poses."""
    pool = record.get("pool_poses")
    if not pool:
        return None
    p = np.asarray(pool, dtype=np.float64)
    centres = p[:, :3, 3]
    picks = [int(i) for i in record.get("selected", [])]
    initial = [int(i) for i in record.get("initial", [])]
    sec = sector_of(centres, centres, sectors)
    out: dict[str, Any] = {
        "scene": record.get("scene"), "variant": record.get("variant"),
        "seed": record.get("seed"), "psnr": record.get("psnr"),
        "sectors": {
            "pool": _counts(sec, sectors),
            "picks": _counts(sec[picks], sectors),
            "initial": _counts(sec[initial], sectors),
        },
    }
    tests = record.get("test_poses")
    if tests:
        tc = np.asarray(tests, dtype=np.float64)[:, :3, 3]
        out["sectors"]["test"] = _counts(sector_of(tc, centres, sectors), sectors)
    s = out["sectors"]
    out["empty_sectors"] = _empty(s["picks"], s["pool"])
    out["max_share"] = max(s["picks"]) / sum(s["picks"]) if picks else None
    out["tv_sectors"] = _tv(s["picks"], s["pool"])
    pool_path = _counts(path_bins(range(len(p)), len(p), sectors), sectors)
    pick_path = _counts(path_bins(picks, len(p), sectors), sectors)
    out["path"] = {"pool": pool_path, "picks": pick_path}
    out["tv_path"] = _tv(pick_path, pool_path)
    out["empty_path"] = _empty(pick_path, pool_path)
    out["test"] = view_coverage(record)
    masses = [e["eig_mass"] for e in record.get("events", []) if e.get("eig_mass")]
    out["eig_mass"] = {k: _mean([m.get(k) for m in masses]) for k in EIG_KEYS} if masses else None
    return out


def _mean(values: Sequence[Any]) -> float | None:
    v = [float(x) for x in values if x is not None and math.isfinite(float(x))]
    return statistics.fmean(v) if v else None


# ----------------------------------------------------------------------------- many runs
def load_runs(out: Path) -> list[dict[str, Any]]:
    """The run records under ``out/runs`` (unreadable files are skipped with a line)."""
    recs = []
    for path in sorted((out / "runs").glob("*/*/seed*.json")):
        try:
            recs.append(json.loads(path.read_text()))
        except (OSError, json.JSONDecodeError) as exc:
            log.warning("skipped %s: %s", path, exc)
    return recs


SUMMARY_KEYS = ("psnr", "empty_sectors", "max_share", "tv_sectors", "tv_path", "empty_path")
TEST_KEYS = ("distance_mean", "angle_mean_deg", "psnr_vs_angle", "psnr_vs_distance",
             "psnr_far_half", "psnr_near_half")


def summarise(runs: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per variant, the means over its runs (scenes and seeds) of every figure."""
    by: dict[str, list[Mapping[str, Any]]] = {}
    for r in runs:
        by.setdefault(str(r["variant"]), []).append(r)
    out: dict[str, dict[str, Any]] = {}
    for key, rs in by.items():
        row: dict[str, Any] = {"runs": len(rs)}
        row.update({k: _mean([r.get(k) for r in rs]) for k in SUMMARY_KEYS})
        row.update({k: _mean([(r.get("test") or {}).get(k) for r in rs]) for k in TEST_KEYS})
        row.update({f"eig_{k}": _mean([(r.get("eig_mass") or {}).get(k) for r in rs])
                    for k in EIG_KEYS})
        out[key] = row
    return out


def _num(v: Any, digits: int) -> str:
    return "–" if v is None else f"{v:.{digits}f}"


def coverage_table(runs: Sequence[Mapping[str, Any]], sectors: int) -> str:
    """``coverage.md``: the summary tables and the sector counts of every run."""
    from agilegs.lab.bench.variants import display_name  # torch: not for --help

    summary = summarise(runs)
    keys = list(summary)
    lines = [
        "# Coverage of the captures and of the test views",
        "",
        f"From {len(runs)} runs; {sectors} azimuth sectors around the pool's centre (and "
        f"{sectors} runs of the capture order). Means over scenes and seeds. See "
        "`agilegs.lab.bench.coverage_report` for each figure.",
        "",
        "## Spread of the picks",
        "",
        "| Method | runs | PSNR | empty sectors | largest sector share | TV to the pool (sectors) "
        "| empty path runs | TV to the pool (path) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for k in keys:
        s = summary[k]
        lines.append(f"| {display_name(k)} | {s['runs']} | {_num(s['psnr'], 2)} | "
                     f"{_num(s['empty_sectors'], 2)} | {_num(s['max_share'], 2)} | "
                     f"{_num(s['tv_sectors'], 2)} | {_num(s['empty_path'], 2)} | "
                     f"{_num(s['tv_path'], 2)} |")
    lines += [
        "",
        "## Test views against the acquired views",
        "",
        "Distance: camera centre to the nearest acquired view's, in pool radii; angle: the "
        "smallest angle between the test view's viewing direction and an acquired view's; "
        "r: Pearson correlation of a test view's PSNR with each, within a run; PSNR of the "
        "test views farther by angle than the run's median, and of the nearer half.",
        "",
        "| Method | distance | angle (°) | r(PSNR, angle) | r(PSNR, distance) | PSNR far half "
        "| PSNR near half |",
        "|---|---|---|---|---|---|---|",
    ]
    for k in keys:
        s = summary[k]
        lines.append(f"| {display_name(k)} | {_num(s['distance_mean'], 3)} | "
                     f"{_num(s['angle_mean_deg'], 1)} | {_num(s['psnr_vs_angle'], 2)} | "
                     f"{_num(s['psnr_vs_distance'], 2)} | {_num(s['psnr_far_half'], 2)} | "
                     f"{_num(s['psnr_near_half'], 2)} |")
    if any(summary[k]["eig_phi"] is not None for k in keys):
        lines += [
            "",
            "## Where the chosen views' EIG lies",
            "",
            "Shares of each chosen view's φ (means over events): from the nearer half of the "
            "Gaussians it informs, from those seen by fewer pool views than their median, "
            "from Gaussians no acquired view informed; pool seen: the φ-weighted fraction of "
            "pool views that see a Gaussian; depth ratio: the φ-weighted mean distance over "
            "the unweighted one; target gain: the fall of the pool's predicted render "
            "variance (8 farthest-point pool views).",
            "",
            "| Method | φ | near share | rare share | unseen share | pool seen | depth ratio "
            "| target gain |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for k in keys:
            s = summary[k]
            lines.append(f"| {display_name(k)} | {_num(s['eig_phi'], 1)} | "
                         f"{_num(s['eig_near_share'], 2)} | {_num(s['eig_rare_share'], 2)} | "
                         f"{_num(s['eig_unseen_share'], 2)} | "
                         f"{_num(s['eig_pool_seen_weighted'], 2)} | "
                         f"{_num(s['eig_depth_ratio'], 2)} | {_num(s['eig_target_gain'], 1)} |")
    scenes = sorted({str(r["scene"]) for r in runs})
    for scene in scenes:
        rs = [r for r in runs if str(r["scene"]) == scene]
        pool = rs[0]["sectors"]["pool"]
        test = rs[0]["sectors"].get("test")
        lines += ["", f"## Sectors of {scene}", "",
                  "Pool frames" + (", test frames" if test else "") + " and each run's picks "
                  "per sector (initial views apart).", "",
                  "| | " + " | ".join(f"S{i}" for i in range(len(pool))) + " |",
                  "|---|" + "---|" * len(pool),
                  "| pool | " + " | ".join(map(str, pool)) + " |"]
        if test:
            lines.append("| test | " + " | ".join(map(str, test)) + " |")
        for r in sorted(rs, key=lambda r: (str(r["variant"]), int(r["seed"] or 0))):
            lines.append(f"| {display_name(str(r['variant']))} s{r['seed']} | "
                         + " | ".join(map(str, r["sectors"]["picks"])) + " |")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if args.sectors < 2:
        raise SystemExit(f"--sectors must be >= 2, got {args.sectors}")
    records = load_runs(out)
    if not records:
        raise SystemExit(f"{out}: no run records under {out / 'runs'}")
    runs = [c for c in (run_coverage(r, args.sectors) for r in records) if c is not None]
    if not runs:
        raise SystemExit(f"{out}: the run records hold no pool poses")
    table = coverage_table(runs, args.sectors)
    (out / "coverage.md").write_text(table)
    path = Path(args.json_out) if args.json_out else out / "coverage.json"
    path.write_text(json.dumps({"sectors": args.sectors, "summary": summarise(runs),
                                "runs": runs}, indent=1))
    sys.stdout.write(table)
    return 0
