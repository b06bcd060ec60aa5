"""``agilegs bench edge`` runs end to end and prints its figures (tiny settings); the heavy
lane runs it at full size and holds it to its bounds: 1,000 slow or idle connections each
closed within its deadline; 64 concurrent 60 MiB bodies, the peak over idle within
``max_inflight_body_bytes`` and back within 20 % of idle a minute later. Another client's p99
against idle is printed, not asserted (a latency ratio on a shared machine)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest


def _bench(tmp_path: Path, *args: str, timeout: float) -> tuple[str, dict]:
    out = tmp_path / "edge.json"
    proc = subprocess.run([sys.executable, "-m", "agilegs.service.cli", "bench", "edge",
                           "--json", str(out), *args], capture_output=True, text=True,
                          timeout=timeout, check=False)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc.stdout, json.loads(out.read_text())


@pytest.mark.heavy
def test_bench_edge_prints_its_figures(tmp_path: Path) -> None:
    text, res = _bench(tmp_path, "--connections", "30", "--header-timeout", "1",
                       "--body-timeout", "1", "--probes", "20", "--bodies", "4",
                       "--body-mib", "2", "--settle", "1", "--env",
                       f"AGILEGS_MAX_INFLIGHT_BODY_BYTES={5 << 20}", timeout=240)
    assert "30 slow or idle connections" in text and "get_session during" in text
    assert "4 concurrent bodies of 2 MiB" in text and text.splitlines()[-1].startswith("targets:")
    c, b = res["connections"], res["bodies"]
    assert all(c[f"closed_{k}_s"]["open"] == 0 for k in ("idle", "headers", "body"))
    assert res["targets"]["closed within the deadline"]
    assert b["budget_mib"] == 5 and sum(b["statuses"].values()) == 4
    assert b["statuses"].get("503", 0) >= 2  # two fit the budget at once (4 MiB each)


@pytest.mark.heavy
@pytest.mark.timeout(900)
def test_bench_edge_meets_its_targets(tmp_path: Path) -> None:
    text, res = _bench(tmp_path, timeout=880)
    # the latency ratio is a benchmark figure on a shared machine (printed, published in
    # docs/benchmarks.md), not a pass/fail check; every bound the server enforces is
    held = {k: v for k, v in res["targets"].items() if k != "p99 within 2x idle"}
    assert held and all(held.values()), text
    assert "p99 within 2x idle" in res["targets"], text
