"""deploy/gpu/protocol.sh runs end to end: on a CPU with small sizes (the GPU run itself needs a
lent GPU), every step exits 0 and writes its figures."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.heavy
def test_the_gpu_protocol_script_runs_every_step(tmp_path: Path) -> None:
    out = tmp_path / "out"
    env = {
        **os.environ,
        "OUT": str(out),
        "PYTHON": sys.executable,
        "DEVICE": "cpu",
        "DEADLINE": "500",
        "LATENCY_SIZES": "400",
        "LATENCY": "--width 32 --height 32 --pool 8 --events 1 --acquired 2 --shortlist 4",
        "LATENCY_METHODS": "random,full_eig,agile",
        "LATENCY_SLOW": "",
        "LATENCY_WIDE": "--width 48 --height 32 --pool 8 --events 1 --acquired 2 --shortlist 4",
        "RENDER": "--gaussians 300 --sizes 32 --repeats 1 --threads 1 --no-baseline",
        "PROFILE": "tiny",
        "SHORT": "",
        "OBJECT_RES": "32",
        "CAPTURE_RES": "32",
        "METHODS": "random agile",
        "OMP_NUM_THREADS": "1",
    }
    proc = subprocess.run(["bash", str(ROOT / "deploy/gpu/protocol.sh")], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    steps = (out / "steps.txt").read_text()
    for step in ("bench latency 400: exit 0", "bench latency 400-wide: exit 0",
                 "bench render: exit 0",
                 "bench run spot: exit 0", "bench run skull_photos: exit 0"):
        assert step in steps, steps
    assert "training uses the builtin rasterizer" in steps  # no gsplat on a CPU
    lat = json.loads((out / "latency-400.json").read_text())
    assert set(lat["methods"]) == {"random", "full_eig", "agile"}
    wide = json.loads((out / "latency-400-wide.json").read_text())
    assert (wide["config"]["width"], wide["config"]["height"]) == (48, 32)
    for name in ("spot", "skull_photos"):
        results = json.loads((out / f"run-{name}" / "results.json").read_text())
        assert not results["invocation"]["missing"], results["invocation"]


def test_every_test_file_the_script_names_exists_and_loads_its_conftest() -> None:
    # a moved test file makes pytest exit 4 on the GPU, and the script then turns the
    # Triton kernels off for the whole run; the tests import helpers from tests/conftest.py
    script = (ROOT / "deploy/gpu/protocol.sh").read_text()
    named = set(re.findall(r"tests/[\w/]+\.py", script))
    assert "tests/nbv/kernels/test_gpu_kernel.py" in named
    assert "tests/nbv/kernels/test_gpu_proxy.py" in named
    for path in named:
        assert (ROOT / path).is_file(), path
    assert "--noconftest" not in script
