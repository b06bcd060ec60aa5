"""A rosbag2 (written here by ``rosbags``, MCAP and sqlite3) as a benchmark scene: its frames
become the posed-scene model, and ``agilegs bench run --scene BAG`` runs on it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from agilegs.client.ros2 import BagFrame, write_bag
from agilegs.lab.bench.scene_model import SceneOptions, orbit_cameras
from agilegs.lab.bench.scenes import detect_scene_kind, load_bench_scene
from agilegs.lab.scenes import bundled_scene
from agilegs.service.cli import main
from agilegs.service.nbv import Camera, Intrinsics, load_scene, render
from agilegs.service.nbv.candidates import scene_center_radius


def _frames(n: int, size: int, depth: bool) -> list[BagFrame]:
    """Frames rendered from the bundled splat on an orbit, 30 Hz stamps, depth in mm."""
    gt = load_scene(bundled_scene("spot"), max_gaussians=300)
    center, r98 = scene_center_radius(gt.means)
    poses = orbit_cameras(center, 2.6 * float(r98), (20.0,), n)
    intr = Intrinsics.from_fov(50.0, size, size)
    out = []
    with torch.no_grad():
        for i, p in enumerate(poses):
            r = render(gt, Camera(c2w=p, intrinsics=intr), background=torch.zeros(3))
            rgb = (r.rgb.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
            mm = (torch.where(r.alpha > 0.5, r.depth, torch.zeros_like(r.depth)).numpy()
                  * 1000).round().astype(np.uint16)
            out.append(BagFrame(stamp_ns=10**9 + i * 33_333_333, rgb=rgb,
                                intrinsics={"fx": intr.fx, "fy": intr.fy, "cx": intr.cx,
                                            "cy": intr.cy, "width": size, "height": size},
                                c2w=p.double().numpy(), depth=mm if depth else None,
                                depth_scale=0.001))
    return out


@pytest.mark.heavy
def test_a_bag_is_a_posed_scene(tmp_path: Path) -> None:
    frames = _frames(10, 16, depth=True)
    bag = write_bag(tmp_path / "capture", frames, storage="mcap", poses="tf")
    assert detect_scene_kind(bag) == "rosbag"
    mcap = next(bag.glob("*.mcap"))
    assert detect_scene_kind(mcap) == "rosbag"
    scene = load_bench_scene(bag, SceneOptions(width=16))
    assert scene.kind == "rosbag" and scene.info["type"] == "posed"
    assert scene.test_poses.shape[0] == 2 and scene.pool_size == 8  # frames 0 and 8 held out
    torch.testing.assert_close(scene.test_poses[1], torch.from_numpy(frames[8].c2w).float())
    torch.testing.assert_close(scene.pool_poses[0], torch.from_numpy(frames[1].c2w).float())
    torch.testing.assert_close(scene.pool_images[0],
                               torch.from_numpy(frames[1].rgb).float() / 255)
    k = frames[0].intrinsics
    assert (scene.intrinsics.fx, scene.intrinsics.cx) == (k["fx"], k["cx"])
    # every pool frame has depth: the mapper back-projects it (metres)
    assert scene.pool_depths is not None and scene.info["init"] == "depth"
    torch.testing.assert_close(scene.pool_depths[0],
                               torch.from_numpy(frames[1].depth_m()))  # type: ignore[arg-type]
    # at half the width, the images and the intrinsics are scaled together
    half = load_bench_scene(mcap, SceneOptions(width=8))
    assert half.pool_images.shape == (8, 8, 8, 3) and half.intrinsics.fx == k["fx"] / 2
    torch.testing.assert_close(half.pool_images[0],
                               scene.pool_images[0].reshape(8, 2, 8, 2, 3).mean((1, 3)))


@pytest.mark.heavy
def test_bench_run_on_a_sqlite3_bag(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "orbit", _frames(18, 16, depth=False), storage="sqlite3",
                    poses="pose")
    out = tmp_path / "bench"
    argv = ["bench", "run", "--scene", str(next(bag.glob("*.db3"))), "--methods", "random",
            "--profile", "tiny", "--seeds", "0", "--out", str(out), "--no-plots",
            "--bag-topics", "pose=/camera/pose,depth=none"]
    assert main(argv) == 0
    res = json.loads((out / "results.json").read_text())
    (scene,) = res["scenes"].values()
    assert scene["kind"] == "rosbag" and scene["runs"]["random"]["0"]["psnr"] > 5.0
