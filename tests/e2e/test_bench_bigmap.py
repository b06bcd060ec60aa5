"""``agilegs bench bigmap`` runs end to end (a tiny map) and reports per step the answer, the
server's memory, and a refusal with the limit it names and the estimate."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest


@pytest.mark.heavy
def test_bench_bigmap_reports_memory_time_and_refusals(tmp_path: Path) -> None:
    out = tmp_path / "bigmap.json"
    proc = subprocess.run(
        [sys.executable, "-m", "agilegs.service.cli", "bench", "bigmap", "--gaussians", "3000",
         "--size", "32", "--pool", "12", "--views", "2", "--methods", "random,full_eig",
         "--env", "AGILEGS_MAX_SELECT_SECONDS=0.002", "--json", str(out)],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    res = json.loads(out.read_text())
    steps = res["steps"]
    assert steps["set_gaussians"]["status"] == 200
    assert steps["select random"]["status"] == 200
    refused = steps["select full_eig"]
    assert refused["status"] == 422 and refused["limit"] == "max_select_seconds"
    assert refused["estimate"]["seconds"] > 0.002
    for row in steps.values():
        assert row["peak_mib"] >= row["rss_before_mib"] > 0
    assert res["final"]["views"] == 2 and res["final"]["pool"] == 10
    assert "select full_eig" in proc.stdout and "max_select_seconds" in proc.stdout
