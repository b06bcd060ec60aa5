"""``agilegs demo --scene CAPTURE``: the robot replays a capture; moving to a chosen frame
returns its photograph."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from agilegs.lab.demo.capture_robot import CaptureRobot, is_capture
from agilegs.lab.demo.run import QUICK, Robot, make_robot

BUDDHA = Path(__file__).resolve().parents[2] / "lab" / "scenes" / "buddha"


def test_an_empty_folder_is_refused_naming_every_layout(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError) as exc:
        make_robot(str(tmp_path / "empty"), QUICK, 0, tmp_path)
    msg = str(exc.value)
    assert ".splat" in msg and "transforms.json" in msg and "COLMAP" in msg


def test_a_capture_with_few_frames_leaves_the_methods_a_choice(tmp_path: Path) -> None:
    from dataclasses import replace

    _, size = make_robot(str(BUDDHA), replace(QUICK, events=8, initial_views=3), 0, tmp_path)
    assert size.events == 4  # of the 8 frames left after the initial views


def test_the_robot_returns_the_frames_photograph(tmp_path: Path) -> None:
    robot, size = make_robot(str(BUDDHA), QUICK, 0, tmp_path)
    assert isinstance(robot, CaptureRobot) and is_capture(str(BUDDHA))
    sc = robot.scene
    assert size.pool_size == sc.pool_size == 11 and size.test_count == 2
    assert size.events == min(QUICK.events, (11 - QUICK.initial_views) // 2)
    assert (robot.intrinsics.width, robot.intrinsics.height) == (32, 18)
    pool = robot.pool.numpy()
    for i in range(sc.pool_size):
        assert robot.frame_of(pool[i]) == i
        img, depth = robot.capture(pool[i])
        expect = (sc.pool_images[i].numpy() * 255 + 0.5).astype(np.uint8)
        assert depth is None and np.array_equal(img, expect)
    # a pose a little off a frame's still reaches that frame
    nudged = pool[4].copy()
    nudged[:3, 3] += 1e-3
    assert robot.frame_of(nudged) == 4
    assert robot.background == (0.0, 0.0, 0.0)
    assert robot.initial_gaussians.is_file()
    assert f"{QUICK.init_gaussians} random points" in robot.summary
    splat, same = make_robot("spot", QUICK, 0, tmp_path)
    assert isinstance(splat, Robot) and same == QUICK and "Gaussians" in splat.summary


@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.heavy
def test_quick_demo_on_a_capture(tmp_path: Path) -> None:
    out = tmp_path / "out"
    env = {k: v for k, v in os.environ.items() if not k.startswith("AGILEGS_")}
    proc = subprocess.run(
        [sys.executable, "-m", "agilegs.service.cli", "demo", "--quick", "--scene", str(BUDDHA),
         "--out", str(out)], capture_output=True, text=True, timeout=290, env=env)
    text = proc.stdout + proc.stderr
    assert proc.returncode == 0, text[-4000:]
    assert "a capture of 13 photographs (colmap)" in proc.stdout
    assert "32x18 images" in proc.stdout and "CC-BY-4.0" in proc.stdout
    assert f"{QUICK.init_gaussians} random points" in text and "5000 random" not in text
    for method in ("AGILE-GS+", "Random"):
        lines = [ln for ln in proc.stdout.splitlines()
                 if re.match(rf"event \d+\s+{re.escape(method)}\s", ln)]
        assert len(lines) == QUICK.events + 1, (method, proc.stdout)
    res = json.loads((out / "demo.json").read_text())
    for key in ("agile_plus", "random"):
        psnrs = [c["psnr"] for c in res["methods"][key]["curve"]]
        assert all(np.isfinite(psnrs)) and min(psnrs) > 5.0
        chosen = [e["chosen"] for e in res["methods"][key]["events"]]
        assert len(set(chosen)) == len(chosen) and not set(chosen) & set(res["initial_views"])
