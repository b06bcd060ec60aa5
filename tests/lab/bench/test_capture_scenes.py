"""Captures as benchmark scenes: the split (every 8th frame unless the capture names one), the
pool in capture order, the initial points (structure-from-motion points where the capture has
them, said in the log) and the background (a photograph is composited on nothing)."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from agilegs.lab.bench.profiles import PROFILES
from agilegs.lab.bench.scene_model import SceneOptions
from agilegs.lab.bench.scenes import load_bench_scene
from agilegs.service.data.colmap import rotmat_to_qvec


def _eyes(n: int) -> list[np.ndarray]:
    return [np.array([3 * math.cos(a), 3 * math.sin(a), 1.0])
            for a in np.linspace(0, 2 * math.pi, n, endpoint=False)]


def _c2w_gl(eye: np.ndarray) -> np.ndarray:
    back = eye / np.linalg.norm(eye)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, np.cross(back, right), back, eye
    return m


def _images(folder: Path, names: list[str], w: int, h: int, mode: str = "RGB") -> None:
    rng = np.random.default_rng(0)
    folder.mkdir(parents=True, exist_ok=True)
    for n in names:
        Image.fromarray(rng.integers(0, 256, size=(h, w, len(mode)), dtype=np.uint8),
                        mode).save(folder / n)


def _write_ply(path: Path, xyz: np.ndarray) -> None:
    from plyfile import PlyData, PlyElement

    v = np.empty(len(xyz), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"),
                                  ("green", "u1"), ("blue", "u1")])
    v["x"], v["y"], v["z"] = xyz.T
    v["red"] = v["green"] = v["blue"] = 128
    PlyData([PlyElement.describe(v, "vertex")]).write(str(path))


def _nerfstudio(root: Path, n: int, *, ply: bool, split: bool, missing: tuple[int, ...] = (),
                mode: str = "RGB") -> None:
    names = [f"frame_{i:05d}.png" for i in range(n)]
    frames = [{"file_path": f"images/{m}", "transform_matrix": _c2w_gl(e).tolist()}
              for m, e in zip(names, _eyes(n), strict=True)]
    meta: dict = {"camera_model": "OPENCV", "fl_x": 20.0, "fl_y": 20.0, "cx": 16.0, "cy": 12.0,
                  "w": 32, "h": 24, "k1": -0.05, "k2": 0.0, "p1": 0.0, "p2": 0.0,
                  "frames": frames}
    if ply:
        _write_ply(root / "sparse_pc.ply", np.random.default_rng(1).normal(size=(40, 3)))
        meta["ply_file_path"] = "sparse_pc.ply"
    if split:
        meta["train_filenames"] = [f"images/{m}" for i, m in enumerate(names) if i % 5]
        meta["test_filenames"] = [f"images/{m}" for i, m in enumerate(names) if i % 5 == 0]
    (root / "transforms.json").write_text(json.dumps(meta))
    _images(root / "images", [m for i, m in enumerate(names) if i not in missing], 32, 24, mode)


def test_a_capture_scene(tmp_path: Path, caplog) -> None:
    """A nerfstudio capture with points and a few frames deleted: every 8th kept frame is a
    test frame, the rest the pool in capture order; the map starts from the ply points on
    black, and the log says both."""
    _nerfstudio(tmp_path, 20, ply=True, split=False, missing=(3, 11))
    with caplog.at_level(logging.INFO):
        sc = load_bench_scene(tmp_path, SceneOptions(width=16, pool_size=100_000))
    kept = [i for i in range(20) if i not in (3, 11)]
    test = [kept[k] for k in range(len(kept)) if k % 8 == 0]
    pool = [kept[k] for k in range(len(kept)) if k % 8]
    assert sc.test_poses.shape[0] == len(test) and sc.pool_size == len(pool)
    eyes = _eyes(20)
    for row, i in enumerate(pool):
        np.testing.assert_allclose(sc.pool_poses[row, :3, 3].numpy(), eyes[i], atol=1e-5)
    assert sc.background == (0.0, 0.0, 0.0)
    assert sc.init_points is not None and sc.init_points.shape == (40, 3)
    assert sc.info["init"] == "ply" and sc.info["skipped_frames"] == 2
    assert sc.info["distortion"] and sc.intrinsics.width == 16
    text = "\n".join(r.getMessage() for r in caplog.records)
    assert "the map starts from the capture's 40 structure-from-motion points" in text
    assert "background black" in text and text.count("2 of 20 frames have no image") == 1
    assert "test views from every 8th frame" in text


def test_a_named_split_and_random_start(tmp_path: Path, caplog) -> None:
    _nerfstudio(tmp_path, 15, ply=False, split=True)
    with caplog.at_level(logging.INFO):
        sc = load_bench_scene(tmp_path, SceneOptions(width=16, pool_size=100_000))
    assert sc.test_poses.shape[0] == 3 and sc.pool_size == 12
    eyes = _eyes(15)
    for row, i in enumerate((0, 5, 10)):
        np.testing.assert_allclose(sc.test_poses[row, :3, 3].numpy(), eyes[i], atol=1e-5)
    assert sc.info["init"] == "random" and sc.info["split"] == "the capture's test_filenames"
    text = "\n".join(r.getMessage() for r in caplog.records)
    assert "5000 random points" in text and "no structure-from-motion points" in text


def test_alpha_captures_keep_the_profile_background(tmp_path: Path) -> None:
    _nerfstudio(tmp_path, 9, ply=False, split=False, mode="RGBA")
    sc = load_bench_scene(tmp_path, SceneOptions(width=16, background=(1.0, 1.0, 1.0)))
    assert sc.background == (1.0, 1.0, 1.0)


def test_a_distorted_colmap_capture(tmp_path: Path, caplog) -> None:
    """A COLMAP text model with an OPENCV camera and points3D: undistorted pinhole
    intrinsics, the sparse points as the start."""
    d = tmp_path / "sparse" / "0"
    d.mkdir(parents=True)
    (d / "cameras.txt").write_text("1 OPENCV 32 24 20 21 16 12 -0.08 0.01 0.001 0.0\n")
    lines = []
    names = [f"img_{i:03d}.jpg" for i in range(10)]
    for i, (n, e) in enumerate(zip(names, _eyes(10), strict=True)):
        c2w = _c2w_gl(e)
        c2w[:3, 1:3] *= -1  # OpenGL camera axes to OpenCV's
        r = c2w[:3, :3].T
        t = -r @ c2w[:3, 3]
        q = rotmat_to_qvec(r)
        lines.append(f"{i + 1} " + " ".join(repr(float(v)) for v in (*q, *t)) + f" 1 {n}\n\n")
    (d / "images.txt").write_text("".join(lines))
    pts = np.random.default_rng(2).normal(size=(30, 3))
    (d / "points3D.txt").write_text("".join(
        f"{k + 1} {p[0]} {p[1]} {p[2]} 10 20 30 0.5 1 0\n" for k, p in enumerate(pts)))
    _images(tmp_path / "images", names, 32, 24)
    with caplog.at_level(logging.INFO):
        sc = load_bench_scene(tmp_path, SceneOptions(width=32, pool_size=100_000))
    assert sc.kind == "colmap" and sc.pool_size == 8 and sc.test_poses.shape[0] == 2
    assert sc.intrinsics.fx < 20.0 and sc.intrinsics.cx == 16.0  # barrel: a wider pinhole
    assert sc.init_points is not None
    torch.testing.assert_close(sc.init_points, torch.from_numpy(pts).float())
    assert sc.background == (0.0, 0.0, 0.0) and sc.info["init"] == "sparse"
    text = "\n".join(r.getMessage() for r in caplog.records)
    assert "camera 1 (OPENCV" in text and "30 structure-from-motion points (COLMAP" in text


def test_the_capture_profile_keeps_every_frame_in_order() -> None:
    p = PROFILES["capture"]
    assert p.initial_views == 10 and p.num_events >= 30
    assert p.scene.pool_size >= 10_000 and p.threads == 1
    from agilegs.lab.scenes import bundled_scene

    with pytest.raises(ValueError, match="is a splat.*cpu_long"):  # not 100,000 renders
        load_bench_scene(bundled_scene("spot"), p.scene)


@pytest.mark.slow
@pytest.mark.parametrize(("name", "frames", "points"),
                         [("skull_photos", 65, 3133), ("brighton_beach", 18, 3478),
                          ("tankard", 69, 2500), ("flowerpot", 80, 2500),
                          ("caliterra", 75, 2500)])
def test_the_captures_posed_by_structure_from_motion_load(name: str, frames: int,
                                                           points: int) -> None:
    root = Path(__file__).resolve().parents[3] / "lab" / "scenes" / name
    sc = load_bench_scene(root, PROFILES["capture"].scene)
    assert sc.kind == "colmap" and sc.pool_size + sc.test_poses.shape[0] == frames
    assert sc.info["init"] == "sparse" and sc.init_points is not None
    assert sc.init_points.shape == (points, 3) and sc.background == (0.0, 0.0, 0.0)
    assert sc.intrinsics.width == 96 and sc.pool_images.std() > 0.05
    # the points lie in front of the cameras that saw them: most project into every view
    c2w = sc.pool_poses.double()
    cam = (sc.init_points.double()[None] - c2w[:, None, :3, 3]) @ c2w[:, :3, :3]  # [V, P, 3]
    assert (cam[..., 2] > 0).double().mean() > 0.9


@pytest.mark.slow
def test_the_buddha_capture_loads() -> None:
    root = Path(__file__).resolve().parents[3] / "lab" / "scenes" / "buddha"
    sc = load_bench_scene(root, PROFILES["capture"].scene)
    assert sc.kind == "colmap" and sc.pool_size + sc.test_poses.shape[0] == 13
    assert sc.intrinsics.width == 96 and sc.pool_images.std() > 0.05
