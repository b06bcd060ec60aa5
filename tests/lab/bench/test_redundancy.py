"""The redundancy figures of a run record, on a ring whose angles are known."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agilegs.lab.bench.redundancy import (
    angles_to_nearest,
    pool_directions,
    run_redundancy,
    summarise_redundancy,
)


def _ring(n: int) -> list[list[list[float]]]:
    poses = []
    for i in range(n):
        a = 2 * math.pi * i / n
        p = np.eye(4)
        p[:3, 3] = [2 * math.cos(a), 0.5, 2 * math.sin(a)]  # centred on (0, 0.5, 0)
        poses.append(p.tolist())
    return poses


def test_angles_to_the_nearest_reference() -> None:
    d = pool_directions(np.array([[1.0, 0, 0], [0, 2.0, 0], [0, 0, 0]]), np.zeros(3))
    np.testing.assert_allclose(d[:2], [[1, 0, 0], [0, 1, 0]])
    np.testing.assert_allclose(d[2], 0)
    ref = np.array([[1.0, 0, 0], [0, 0, 1.0]])
    np.testing.assert_allclose(angles_to_nearest(d[:2], ref), [0.0, 90.0], atol=1e-9)
    assert np.isnan(angles_to_nearest(d[:2], np.zeros((0, 3)))).all()


def test_a_run_record_on_a_ring() -> None:
    # 12 views 30 degrees apart; views 0 and 6 first, then 1 (30 from 0), 3 (90 from both),
    # 9 (90 from 6)
    anchor = np.eye(4)
    a = math.radians(75)
    anchor[:3, 3] = [2 * math.cos(a), 0.5, 2 * math.sin(a)]
    record = {
        "pool_poses": _ring(12),
        "initial": [0, 6],
        "events": [{"choice": 1, "anchor": anchor.tolist(), "anchor_psi": 3.0,
                    "best_candidate_psi": 4.0},
                   {"choice": 3}, {"choice": 9, "anchor": None}],
    }
    red = run_redundancy(record)
    assert red is not None
    picks = [e["pick_angle_deg"] for e in red["events"]]
    np.testing.assert_allclose(picks, [30.0, 60.0, 90.0], atol=1e-6)
    assert red["pick_angle_mean_deg"] == pytest.approx(60.0)
    # the anchor at 75 degrees: 75 from view 0, 105 from view 6
    assert red["events"][0]["anchor_angle_deg"] == pytest.approx(75.0)
    assert red["events"][1]["anchor_angle_deg"] is None
    assert red["events"][0]["psi_ratio"] == pytest.approx(0.75)
    assert red["psi_ratio_mean"] == pytest.approx(0.75)
    # left in the pool: 2, 4, 5, 7, 8, 10, 11, each 30 degrees from an acquired view
    assert red["final_gap_deg"] == pytest.approx(30.0)
    assert run_redundancy({"events": []}) is None
    # the summary prefers a record's own figures and computes the others
    other = dict(record, redundancy={**red, "final_gap_deg": 10.0})
    s = summarise_redundancy([record, other])
    assert s["final_gap_deg"] == pytest.approx(20.0)
    assert s["pick_angle_mean_deg"] == pytest.approx(60.0)


def test_the_share_of_events_a_probe_won() -> None:
    events = [{"choice": 1, "probes": 1, "probe_won": True},
              {"choice": 2, "probes": 2, "probe_won": False},
              {"choice": 3, "probes": 1, "probe_won": False},
              {"choice": 4}]  # an event without probes does not count
    red = run_redundancy({"pool_poses": _ring(12), "initial": [0, 6], "events": events})
    assert red is not None and red["probe_win_rate"] == pytest.approx(1 / 3)
    plain = run_redundancy({"pool_poses": _ring(12), "initial": [0], "events": events[3:]})
    assert plain is not None and plain["probe_win_rate"] is None
    assert summarise_redundancy([{"redundancy": red}, {"redundancy": plain}])[
        "probe_win_rate"] == pytest.approx(1 / 3)
