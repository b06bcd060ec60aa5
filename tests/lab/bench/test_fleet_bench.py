"""``agilegs bench fleet``: its command line and how it judges its figures (a run starts an S3
API and several servers for minutes: the fleet itself is tested in tests/e2e/test_fleet.py)."""

from __future__ import annotations

import argparse

from agilegs.lab.bench import fleet


def test_the_defaults_run_every_phase() -> None:
    p = argparse.ArgumentParser()
    fleet.add_arguments(p)
    args = p.parse_args([])
    assert args.phases == "kill,pause,scale" and args.instances == 3 and args.endpoint is None


def test_the_targets() -> None:
    good = {"kill": {"takeover_p99_s": 1.2, "acked_lost": 0, "client_errors": 0},
            "pause": {"writes_through": 0, "logged_lost_lease": True},
            "scale": {"1": 10.0, "2": 19.0, "3": 20.0}}
    assert all(fleet.targets(good).values()) and len(fleet.targets(good)) == 5
    bad = {"kill": {"takeover_p99_s": 6.0, "acked_lost": 1, "client_errors": 2},
           "pause": {"writes_through": 1, "logged_lost_lease": True},
           "scale": {"1": 10.0, "2": 17.0}}
    assert not any(fleet.targets(bad).values())
    assert fleet._pct([3.0, 1.0, 2.0], 0.5) == 2.0
