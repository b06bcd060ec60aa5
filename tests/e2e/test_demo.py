"""``agilegs demo`` in its reduced mode: a real server subprocess, the SDK over HTTP."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from agilegs.lab.demo.run import EXPECT, QUICK, attribution, initial_indices


@pytest.mark.timeout(240)
def test_quick_demo_runs_the_closed_loop(tmp_path: Path) -> None:
    out = tmp_path / "out"
    env = {k: v for k, v in os.environ.items() if not k.startswith("AGILEGS_")}
    proc = subprocess.run(
        [sys.executable, "-m", "agilegs.service.cli", "demo", "--quick", "--out", str(out)],
        capture_output=True, text=True, timeout=230, env=env)
    text = proc.stdout + proc.stderr
    assert proc.returncode == 0, text[-4000:]
    for method in ("AGILE-GS+", "Random"):
        lines = [ln for ln in proc.stdout.splitlines()
                 if re.match(rf"event \d+\s+{re.escape(method)}\s", ln)]
        assert len(lines) == QUICK.events + 1, (method, proc.stdout)
        for ln in lines[1:]:  # chosen view, latency breakdown, server time, PSNR
            assert re.search(r"view #\d+", ln) and "total" in ln and "server" in ln, ln
            assert re.search(r"PSNR\s+\d+\.\d+ dB", ln), ln
    assert "anchor" in proc.stdout and "rerank" in proc.stdout
    assert "Keenan Crane" in proc.stdout  # the bundled scene's attribution
    assert proc.stdout.splitlines()[1] == EXPECT  # what to expect, before anything runs
    png = out / "psnr.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    res = json.loads((out / "demo.json").read_text())
    for key in ("agile_plus", "random"):
        r = res["methods"][key]
        assert [c["views"] for c in r["curve"]] == list(
            range(QUICK.initial_views, QUICK.initial_views + QUICK.events + 1))
        assert all(e["mapper_steps"] == QUICK.steps_per_view * c["views"]
                   for e, c in zip(r["events"], r["curve"][1:], strict=True))
        chosen = [e["chosen"] for e in r["events"]]
        assert len(set(chosen)) == len(chosen)  # committed views leave the pool
        assert not set(chosen) & set(res["initial_views"])
    assert "server.log" in {p.name for p in out.iterdir()}
    # the table it writes, and where AGILE-GS+ stands, computed from this run
    table = (out / "psnr.md").read_text()
    deltas = [a["psnr"] - b["psnr"] for a, b in zip(
        res["methods"]["agile_plus"]["curve"], res["methods"]["random"]["curve"], strict=True)]
    rows = [ln for ln in table.splitlines() if re.match(r"\| \d+ \|", ln)]
    assert [float(r.split("|")[-2]) for r in rows] == [round(d, 2) + 0.0 for d in deltas]
    assert f"last event Δ {deltas[-1]:+.2f} dB" in table and table.splitlines()[-1] in proc.stdout
    assert "AGILE-GS+: mean selection" in table and "Random: mean selection" in table
    _exports_the_session(out, proc.stdout)


def _exports_the_session(out: Path, stdout: str) -> None:
    """The demo's AGILE-GS+ session, left in its state folder, leaves as a 3DGS .ply and as
    a dataset by the commands the demo prints."""
    from plyfile import PlyData

    from agilegs.service.cli import main
    from agilegs.service.data.colmap import load_colmap
    from agilegs.service.data.transforms import load_transforms
    from agilegs.service.nbv import GaussianMap

    state = out / "state"
    assert f"agilegs export demo-agile-plus {out / 'map.ply'} --state-dir {state}" in stdout
    assert main(["export", "demo-agile-plus", str(out / "map.ply"), "--state-dir",
                 str(state)]) == 0
    names = [p.name for p in PlyData.read(str(out / "map.ply"))["vertex"].properties]
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[-8:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1",
                          "rot_2", "rot_3"]
    assert len(GaussianMap.load(out / "map.ply")) > 0
    assert main(["export", "demo-agile-plus", str(out / "dataset"), "--state-dir",
                 str(state)]) == 0
    views = load_transforms(out / "dataset" / "transforms.json").views
    assert len(views) == QUICK.initial_views + QUICK.events
    assert len(load_colmap(out / "dataset" / "sparse" / "0", out / "dataset" / "images")[0]
               ) == len(views)


def test_attribution_and_initial_views() -> None:
    assert "Keenan Crane" in attribution("spot") and "CC0" in attribution("spot")
    assert "Newell" in attribution("teapot")
    assert "not bundled" in attribution("/some/scene.splat")
    buddha = attribution(str(Path(__file__).resolve().parents[2] / "lab" / "scenes" / "buddha"))
    assert "CC-BY-4.0" in buddha and "Gasparini" in buddha and "not bundled" not in buddha
    assert initial_indices(60, 3) == [10, 30, 50]
    assert initial_indices(5, 5) == [0, 1, 2, 3, 4]


def test_the_report_says_when_both_methods_took_the_same_views() -> None:
    from rich.console import Console

    from agilegs.lab.demo.report import summary

    def method(chosen: list[int], first: float) -> dict:
        events = [{"chosen": c, "latency_ms": {"total": first if i == 0 else 100.0}}
                  for i, c in enumerate(chosen)]
        return {"events": events, "curve": [{"views": 3 + i, "psnr": 20.0 + i}
                                            for i in range(len(chosen) + 1)]}

    quiet = Console(file=open(os.devnull, "w"))  # noqa: SIM115
    same = summary(quiet, {"methods": {"agile_plus": method([4, 7], 3000.0),
                                       "random": method([7, 4], 100.0)}})
    assert "Both methods acquired the same 2 views" in same
    assert "AGILE-GS+: mean selection 100.0 ms over event 2; the first 3000.0 ms" in same
    apart = summary(quiet, {"methods": {"agile_plus": method([4, 7], 100.0),
                                        "random": method([5, 4], 100.0)}})
    assert "same" not in apart
