"""``agilegs bench firstcall``: a fresh server's first selection against its tenth, with and
without the warm-up, in a small run."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest


@pytest.mark.timeout(600)
def test_firstcall_reports_both_servers(tmp_path: Path) -> None:
    out = tmp_path / "firstcall.json"
    proc = subprocess.run(
        [sys.executable, "-m", "agilegs.service.cli", "bench", "firstcall", "--max-gaussians",
         "300", "--pool", "12", "--size", "32", "--selections", "3", "--json", str(out)],
        capture_output=True, text=True, timeout=580)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "| warm-up |" in proc.stdout and "| no warm-up |" in proc.stdout
    results = json.loads(out.read_text())["results"]
    assert [r["variant"] for r in results] == ["warm-up", "no warm-up"]
    for r in results:
        assert len(r["round_trip_ms"]) == 3 and r["ready_s"] > 0
        assert r["first_ms"] == r["round_trip_ms"][0] and r["ratio"] > 0
