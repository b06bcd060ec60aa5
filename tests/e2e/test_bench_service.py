"""``agilegs bench service`` runs end to end and prints its figures (tiny settings)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ServerProcess


@pytest.mark.heavy
def test_bench_service_prints_overhead_and_load(server: ServerProcess, tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    proc = subprocess.run(
        [sys.executable, "-m", "agilegs.service.cli", "bench", "service", "--url", server.url,
         "--zenoh", server.zenoh_endpoint, "--requests", "5",
         "--warmup", "1", "--pool", "30", "--max-gaussians", "100", "--size", "16",
         "--clients", "3", "--selections", "2", "--flood-clients", "3",
         "--neighbour-selections", "4", "--flood-method", "cover", "--deadline-requests", "2",
         "--deadline-ms", "1", "--json", str(out)],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    for row in ("http-json/preset", "http-msgpack/preset", "zenoh/preset", "zenoh/inline"):
        assert row in proc.stdout
    assert "selections/s, 0 errors, 0 acknowledged commits lost" in proc.stdout
    res = json.loads(out.read_text())
    assert res["load"]["selections"] == 6 and res["load"]["lost"] == 0
    r = res["overhead"]["http-msgpack/preset"]
    assert r["requests"] == 5 and r["overhead_ms"]["p50"] > 0
    nb = res["neighbour"]
    assert "noisy neighbour" in proc.stdout and nb["errors"] == 0
    assert nb["unloaded_ms"]["p50"] > 0 and nb["loaded_ms"]["p99"] >= nb["loaded_ms"]["p50"]
    # three flooding clients on one session: the per-session queue turned some away
    assert nb["flood_answered"] > 0
    # a 1 ms deadline: the methods that take longer answer 504, none anything but 200 or 504
    dl = res["deadline"]
    assert "deadline: X-Deadline-Ms 1" in proc.stdout and dl["deadline_ms"] == 1
    assert set(dl["methods"]) == {"random", "spread", "fisherrf", "cover", "full_eig", "agile",
                                  "agile_plus"}
    for m in dl["methods"].values():
        assert set(m["statuses"]) <= {"200", "504"} and sum(m["statuses"].values()) == 2
        assert m["overshoot_ms"]["max"] >= m["overshoot_ms"]["p50"] > -1
    assert dl["methods"]["full_eig"]["statuses"] == {"504": 2}
