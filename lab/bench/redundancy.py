"""How redundant a run's picks are with the views it had already acquired.

Angles are seen from the centre of the pool (the mean of the pool's camera centres): the
angle between two views is the angle between their centres' directions from there, in
degrees. For a run of the progressive protocol:

- ``pick_angle_deg`` per event: the angle from the chosen view to the nearest view acquired
  before it (small: the pick looks again where the map was already observed from);
- ``anchor_angle_deg`` per event (methods with an anchor): the same for the anchor's centre;
- ``final_gap_deg``: the mean over the pool's views never acquired of the angle to the
  nearest acquired view at the end (large: part of the pool's view sphere left uncovered);
- ``psi_ratio`` per event (methods with an anchor): ψ at the anchor over ψ at the best
  candidate, where the event recorded both (``anchor_psi``, ``best_candidate_psi``);
- ``probe_win_rate`` (AGILE-GS+): the share of its events where a uniform probe beat every
  candidate of the model under the exact EIG (a model that predicts the EIG keeps it low;
  one that does not, near probes / (probes + 1)).

Only numpy: the records are JSON (``bench run``'s ``runs/<scene>/<variant>/seed<k>.json``).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

__all__ = [
    "angles_to_nearest",
    "pool_directions",
    "redundancy_table",
    "run_redundancy",
    "summarise_redundancy",
]


def pool_directions(centres: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Unit directions [P, 3] of camera centres [P, 3] seen from ``origin`` [3] (a centre at
    the origin gets the zero vector)."""
    d = np.asarray(centres, dtype=np.float64) - np.asarray(origin, dtype=np.float64)
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    return np.where(n > 1e-12, d / np.maximum(n, 1e-12), 0.0)


def angles_to_nearest(dirs: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Angle in degrees from each of ``dirs`` [P, 3] to the nearest of ``ref`` [R, 3] (unit
    vectors); NaN for every entry when ``ref`` is empty."""
    dirs = np.atleast_2d(np.asarray(dirs, dtype=np.float64))
    ref = np.atleast_2d(np.asarray(ref, dtype=np.float64))
    if ref.size == 0:
        return np.full(dirs.shape[0], np.nan)
    cos = np.clip(dirs @ ref.T, -1.0, 1.0).max(axis=1)
    return np.degrees(np.arccos(cos))


def _mean(values: Sequence[float | None]) -> float | None:
    v = [float(x) for x in values if x is not None and math.isfinite(float(x))]
    return statistics.fmean(v) if v else None


def run_redundancy(record: Mapping[str, Any]) -> dict[str, Any] | None:
    """The redundancy figures of one run record (None when it lacks the pool's poses).

    Returns:
        ``events``: per event ``pick_angle_deg``, ``anchor_angle_deg`` (None without an
        anchor), ``psi_ratio`` (None unless recorded); ``pick_angle_mean_deg``,
        ``anchor_angle_mean_deg``, ``psi_ratio_mean`` (means over events) and
        ``final_gap_deg``.
    """
    poses = record.get("pool_poses")
    if not poses:
        return None
    centres = np.asarray(poses, dtype=np.float64)[:, :3, 3]
    origin = centres.mean(axis=0)
    dirs = pool_directions(centres, origin)
    acquired = [int(i) for i in record.get("initial", [])]
    events = []
    for e in record.get("events", []):
        ref = dirs[acquired]
        pick = float(angles_to_nearest(dirs[int(e["choice"])][None], ref)[0])
        anchor = e.get("anchor")
        a_angle = None
        if anchor is not None:
            a_dir = pool_directions(np.asarray(anchor, dtype=np.float64)[:3, 3][None], origin)
            a_angle = float(angles_to_nearest(a_dir, ref)[0])
        ratio = None
        a_psi, b_psi = e.get("anchor_psi"), e.get("best_candidate_psi")
        if a_psi is not None and b_psi is not None and float(b_psi) > 0:
            ratio = float(a_psi) / float(b_psi)
        events.append({"pick_angle_deg": pick, "anchor_angle_deg": a_angle, "psi_ratio": ratio})
        acquired.append(int(e["choice"]))
    judged = [bool(e["probe_won"]) for e in record.get("events", [])
              if e.get("probe_won") is not None]
    taken = set(acquired)
    rest = [i for i in range(centres.shape[0]) if i not in taken]
    gap = angles_to_nearest(dirs[rest], dirs[acquired]) if rest and acquired else np.zeros(0)
    return {
        "events": events,
        "pick_angle_mean_deg": _mean([e["pick_angle_deg"] for e in events]),
        "anchor_angle_mean_deg": _mean([e["anchor_angle_deg"] for e in events]),
        "psi_ratio_mean": _mean([e["psi_ratio"] for e in events]),
        "final_gap_deg": float(gap.mean()) if gap.size else None,
        "probe_win_rate": sum(judged) / len(judged) if judged else None,
    }


def summarise_redundancy(records: Sequence[Mapping[str, Any]]) -> dict[str, float | None]:
    """Means over runs of :func:`run_redundancy`'s figures (each run's own redundancy, or one
    computed from the record when it has none)."""
    found = (r.get("redundancy") or run_redundancy(r) for r in records)
    per: list[Mapping[str, Any]] = [p for p in found if p is not None]
    keys = ("pick_angle_mean_deg", "anchor_angle_mean_deg", "psi_ratio_mean", "final_gap_deg",
            "probe_win_rate")
    return {k: _mean([p.get(k) for p in per]) for k in keys}


def redundancy_table(rows: Sequence[tuple[str, Mapping[str, float | None]]]) -> list[str]:
    """The markdown section of ``table.md``: one row per (method name, its
    :func:`summarise_redundancy` figures)."""

    def num(v: float | None, digits: int) -> str:
        return "–" if v is None else f"{v:.{digits}f}"

    out = [
        "## Redundancy with the acquired views",
        "",
        "Angles seen from the centre of the pool, in degrees, means over events, runs and "
        "scenes: from each pick (and each anchor) to the nearest view acquired before it, and "
        "at the end from every view left in the pool to the nearest acquired one (the gap "
        "the run leaves); ψ(anchor) / ψ(best candidate): the anchor's ψ over the best "
        "eligible candidate's, of the function the anchor ascends; probes won: the share of "
        "AGILE-GS+'s events where a uniform probe beat the model's shortlist under the exact "
        "EIG.",
        "",
        "| Method | pick → nearest acquired (°) | anchor → nearest acquired (°) | "
        "final pool gap (°) | ψ(anchor) / ψ(best candidate) | probes won |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in rows:
        won = r.get("probe_win_rate")
        out.append(f"| {name} | {num(r.get('pick_angle_mean_deg'), 1)} | "
                   f"{num(r.get('anchor_angle_mean_deg'), 1)} | "
                   f"{num(r.get('final_gap_deg'), 1)} | {num(r.get('psi_ratio_mean'), 2)} | "
                   f"{'–' if won is None else f'{100 * won:.0f}%'} |")
    return out + [""]
