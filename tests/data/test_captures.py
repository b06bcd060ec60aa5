"""Captures as they come: lens distortion undistorted with OpenCV's maps (against the reference
formula and against a render distorted on purpose), and transforms.json in the instant-ngp and
nerfstudio dialects (shared or per-frame intrinsics, distortion, missing images, masks, ply
points, named splits)."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from agilegs.lab.scenes import bundled_scene
from agilegs.service.data.distortion import (
    Distortion,
    colmap_distortion,
    distort_normalized,
    pinhole_for,
    undistort_image,
)
from agilegs.service.data.images import load_capture_image
from agilegs.service.data.transforms import load_transforms
from agilegs.service.mapper.quality import psnr
from agilegs.service.nbv import Camera, Intrinsics, load_scene, render
from agilegs.service.nbv.candidates import scene_center_radius

cv2 = pytest.importorskip("cv2")

RAW = Intrinsics(70.0, 72.0, 49.0, 35.5, 96, 72)
DISTORTIONS = [
    Distortion("opencv", (-0.25, 0.08, 0.002, -0.001)),  # barrel + tangential
    Distortion("opencv", (0.15, 0.0, 0.0, 0.0, 0.02)),  # pincushion, k3
    Distortion("opencv", (-0.2, 0.05, 0.001, 0.001, 0.01, 0.02, 0.0, 0.01)),  # rational
    Distortion("fisheye", (0.05, -0.01, 0.002, 0.0)),
]


@pytest.mark.parametrize("dist", DISTORTIONS, ids=lambda d: f"{d.kind}{len(d.coeffs)}")
def test_undistortion_maps_follow_the_formula(dist: Distortion) -> None:
    """Each pixel of the undistorted image samples the photograph where the reference formula
    (float64) sends its ray; the border of the new image lies inside the photograph, and a
    slightly wider focal length would leave it."""
    from agilegs.service.data.distortion import _border_inside, _maps

    new = pinhole_for(RAW, dist)
    m1, m2 = _maps(RAW, dist)
    v, u = np.mgrid[0:RAW.height, 0:RAW.width].astype(np.float64)
    x = (u + 0.5 - new.cx) / new.fx
    y = (v + 0.5 - new.cy) / new.fy
    xd, yd = distort_normalized(x, y, dist)
    ud = RAW.fx * xd + RAW.cx - 0.5  # OpenCV's integer pixel centres
    vd = RAW.fy * yd + RAW.cy - 0.5
    np.testing.assert_allclose(m1, ud, atol=2e-3)
    np.testing.assert_allclose(m2, vd, atol=2e-3)
    assert m1.min() >= -0.5 - 1e-3 and m1.max() <= RAW.width - 0.5 + 1e-3
    assert m2.min() >= -0.5 - 1e-3 and m2.max() <= RAW.height - 0.5 + 1e-3
    s = new.fx / RAW.fx
    assert new.fy / RAW.fy == pytest.approx(s) and (new.cx, new.cy) == (RAW.cx, RAW.cy)
    assert not _border_inside(RAW, dist, s * 0.995)


def test_colmap_models_map_to_opencv() -> None:
    assert colmap_distortion("PINHOLE", (1, 1, 0, 0)).is_identity
    assert colmap_distortion("SIMPLE_RADIAL", (1, 0, 0, 0.1)) == Distortion(
        "opencv", (0.1, 0, 0, 0))
    assert colmap_distortion("RADIAL", (1, 0, 0, 0.1, 0.2)) == Distortion(
        "opencv", (0.1, 0.2, 0, 0))
    full = tuple(float(i) for i in range(12))
    assert colmap_distortion("FULL_OPENCV", full).coeffs == full[4:]
    assert colmap_distortion("SIMPLE_RADIAL_FISHEYE", (1, 0, 0, 0.3)) == Distortion(
        "fisheye", (0.3, 0, 0, 0))
    assert colmap_distortion("RADIAL_FISHEYE", (1, 0, 0, 0.3, 0.4)) == Distortion(
        "fisheye", (0.3, 0.4, 0, 0))
    assert colmap_distortion("OPENCV_FISHEYE", full[:8]).coeffs == full[4:8]
    with pytest.raises(ValueError, match="THIN_PRISM_FISHEYE is not supported"):
        colmap_distortion("THIN_PRISM_FISHEYE", full)
    # COLMAP's fisheye formula on one ray: θ_d = θ (1 + k θ²), radius scaled by θ_d / r
    x, y = np.array([0.3]), np.array([-0.4])
    xd, yd = distort_normalized(x, y, Distortion("fisheye", (0.1, 0, 0, 0)))
    th = math.atan(0.5)
    assert xd[0] == pytest.approx(0.3 * th * (1 + 0.1 * th * th) / 0.5)
    assert yd[0] == pytest.approx(-0.4 * th * (1 + 0.1 * th * th) / 0.5)


def _spot_render(intr: Intrinsics) -> np.ndarray:
    gt = load_scene(bundled_scene("spot"), max_gaussians=4000)
    center, r98 = scene_center_radius(gt.means)
    from agilegs.lab.bench.scene_model import orbit_cameras

    pose = orbit_cameras(center, 2.2 * float(r98), (25.0,), 1, azimuth_offset=0.4)[0]
    with torch.no_grad():
        out = render(gt, Camera(c2w=pose.to(gt.dtype), intrinsics=intr),
                     background=torch.tensor([0.9, 0.85, 0.8], dtype=gt.dtype))
    return out.rgb.clamp(0, 1).float().numpy()


def _pixels(intr: Intrinsics, ss: int = 4) -> np.ndarray:
    """A pinhole render of ``intr`` as a camera's pixels: rendered ``ss``× finer, box-filtered
    (the same band limit as :func:`_distorted_photo`'s)."""
    fine = _spot_render(Intrinsics(intr.fx * ss, intr.fy * ss, intr.cx * ss, intr.cy * ss,
                                   intr.width * ss, intr.height * ss))
    return fine.reshape(intr.height, ss, intr.width, ss, 3).mean((1, 3))


def _distorted_photo(raw: Intrinsics, dist: Distortion) -> np.ndarray:
    """The photograph a lens with ``dist`` takes: each of its pixels looks along the ray
    OpenCV's iterative ``undistortPoints`` finds (independent of the undistortion maps), sampled
    from a pinhole render 4× finer on a canvas twice as wide."""
    ss = 4
    wide = Intrinsics(raw.fx * ss, raw.fy * ss, (raw.cx + raw.width / 2) * ss,
                      (raw.cy + raw.height / 2) * ss, 2 * raw.width * ss, 2 * raw.height * ss)
    ref = _spot_render(wide)
    v, u = np.mgrid[0:raw.height * ss, 0:raw.width * ss].astype(np.float64)
    pts = np.stack([(u + 0.5) / ss, (v + 0.5) / ss], axis=-1).reshape(-1, 1, 2)
    k = np.array([[raw.fx, 0, raw.cx], [0, raw.fy, raw.cy], [0, 0, 1]])
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    if dist.kind == "fisheye":
        n = cv2.fisheye.undistortPoints(pts, k, np.asarray(dist.coeffs), R=np.eye(3),
                                        P=np.eye(3), criteria=crit)
    else:
        n = cv2.undistortPoints(pts, k, np.asarray(dist.coeffs), R=np.eye(3), P=np.eye(3),
                                criteria=crit)
    n = n.reshape(raw.height * ss, raw.width * ss, 2)
    mx = (wide.fx * n[..., 0] + wide.cx - 0.5).astype(np.float32)
    my = (wide.fy * n[..., 1] + wide.cy - 0.5).astype(np.float32)
    fine = cv2.remap(ref, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return fine.reshape(raw.height, ss, raw.width, ss, 3).mean((1, 3))  # box filter: pixels


@pytest.mark.parametrize("dist", [DISTORTIONS[0], DISTORTIONS[3]], ids=["opencv", "fisheye"])
def test_a_distorted_render_is_undistorted(tmp_path: Path, dist: Distortion) -> None:
    """Render, distort with known coefficients, save as a photograph, load: the loader's image
    matches a pinhole render of its camera far better than the photograph itself does."""
    photo = _distorted_photo(RAW, dist)
    path = tmp_path / "photo.png"
    Image.fromarray((photo * 255).round().astype(np.uint8)).save(path)
    img, alpha = load_capture_image(path, RAW, dist, (RAW.width, RAW.height))
    assert alpha is None and img.shape == (RAW.height, RAW.width, 3)
    new = pinhole_for(RAW, dist)
    truth = torch.from_numpy(_pixels(new)).float()
    undistorted = psnr(img, truth)
    ignored = psnr(torch.from_numpy(photo).float(), torch.from_numpy(_pixels(RAW)).float())
    assert undistorted > 35.0, (undistorted, ignored)
    assert undistorted > ignored + 8.0, (undistorted, ignored)
    # the same at half the size (undistorted at the file's size, then resized)
    half, _ = load_capture_image(path, RAW, dist, (RAW.width // 2, RAW.height // 2))
    truth_half = torch.from_numpy(_pixels(new.scaled(RAW.width // 2, RAW.height // 2))).float()
    assert psnr(half, truth_half) > 33.0


def test_undistort_image_keeps_channels_and_refuses_wrong_sizes() -> None:
    d = DISTORTIONS[0]
    rgba = np.zeros((RAW.height, RAW.width, 4), dtype=np.uint8)
    rgba[..., 3] = 255
    out, new = undistort_image(rgba, RAW, d)
    assert out.shape == rgba.shape and out.dtype == np.uint8 and (out[..., 3] == 255).all()
    assert new == pinhole_for(RAW, d)
    same, intr = undistort_image(rgba, RAW, Distortion())
    assert same is rgba and intr == RAW
    with pytest.raises(ValueError, match="96x72"):
        undistort_image(rgba[:10], RAW, d)
    with pytest.raises(ValueError, match="4, 5 or 8"):
        Distortion("opencv", (0.1, 0.2))


# ----------------------------------------------------------------------------- transforms.json
def _c2w_gl(eye: np.ndarray) -> list[list[float]]:
    back = eye / np.linalg.norm(eye)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, np.cross(back, right), back, eye
    return m.tolist()


def _eyes(n: int) -> list[np.ndarray]:
    return [np.array([3 * math.cos(a), 3 * math.sin(a), 1.0])
            for a in np.linspace(0, 2 * math.pi, n, endpoint=False)]


def _write_images(folder: Path, names: list[str], w: int, h: int, mode: str = "RGB") -> None:
    rng = np.random.default_rng(3)
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        a = rng.integers(0, 256, size=(h, w, len(mode)), dtype=np.uint8)
        Image.fromarray(a, mode).save(folder / name)


def test_colmap2nerf_capture_with_missing_frames(tmp_path: Path, caplog) -> None:
    """instant-ngp's colmap2nerf: intrinsics and k1 k2 p1 p2 at the top, aabb_scale,
    './images/...' paths, a quarter of the frames deleted: one warning counts them."""
    names = [f"f{i:03d}.jpg" for i in range(12)]
    frames = [{"file_path": f"./images/{n}", "sharpness": 50.0,
               "transform_matrix": _c2w_gl(e)} for n, e in zip(names, _eyes(12), strict=True)]
    meta = {"camera_angle_x": 1.1, "camera_angle_y": 0.9, "fl_x": 40.0, "fl_y": 41.0,
            "k1": -0.1, "k2": 0.01, "p1": 0.001, "p2": 0.0, "cx": 24.5, "cy": 17.5,
            "w": 48.0, "h": 36.0, "aabb_scale": 16, "frames": frames}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    kept = [n for i, n in enumerate(names) if i % 4 != 1]
    _write_images(tmp_path / "images", kept, 48, 36)
    with caplog.at_level(logging.INFO):
        cap = load_transforms(tmp_path / "transforms.json", downscale=2)
    assert [Path(v.name).name for v in cap.views] == kept
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and "3 of 12 frames have no image" in warned[0]
    assert cap.skipped == [f"./images/{names[i]}" for i in (1, 5, 9)]
    assert any("undistorted" in r.getMessage() for r in caplog.records)
    new = pinhole_for(Intrinsics(40.0, 41.0, 24.5, 17.5, 48, 36),
                      Distortion("opencv", (-0.1, 0.01, 0.001, 0.0, 0.0)))
    v = cap.views[0]
    assert v.camera.fx == pytest.approx(new.fx / 2) and v.camera.fy == pytest.approx(new.fy / 2)
    assert v.camera.fx < 20.0  # barrel distortion: the pinhole view is wider
    assert v.image is not None and v.image.shape == (18, 24, 3) and v.alpha is None
    assert not cap.has_split and cap.points is None


def _write_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    from plyfile import PlyData, PlyElement

    v = np.empty(len(xyz), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"),
                                  ("green", "u1"), ("blue", "u1")])
    v["x"], v["y"], v["z"] = xyz.T
    v["red"], v["green"], v["blue"] = rgb.T
    PlyData([PlyElement.describe(v, "vertex")]).write(str(path))


def test_nerfstudio_capture(tmp_path: Path) -> None:
    """nerfstudio: per-frame intrinsics, camera_model OPENCV_FISHEYE, masks, ply_file_path and
    a named test split."""
    names = [f"frame_{i:05d}.png" for i in range(1, 7)]
    frames = []
    for i, (n, e) in enumerate(zip(names, _eyes(6), strict=True)):
        fr = {"file_path": f"images/{n}", "transform_matrix": _c2w_gl(e),
              "fl_x": 30.0 + i, "fl_y": 30.0 + i, "cx": 20.0, "cy": 15.0, "w": 40, "h": 30,
              "k1": 0.02, "k2": -0.01, "k3": 0.0, "k4": 0.0}
        if i == 2:
            fr["mask_path"] = f"masks/{n}"
        frames.append(fr)
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(50, 3))
    rgb = rng.integers(0, 256, size=(50, 3), dtype=np.uint8)
    _write_ply(tmp_path / "sparse_pc.ply", xyz, rgb)
    meta = {"camera_model": "OPENCV_FISHEYE", "ply_file_path": "sparse_pc.ply",
            "train_filenames": [f"images/{n}" for n in names[:4]],
            "test_filenames": [f"images/{n}" for n in names[4:]], "frames": frames}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    _write_images(tmp_path / "images", names, 40, 30)
    (tmp_path / "masks").mkdir()
    mask = np.zeros((30, 40), dtype=np.uint8)
    mask[:, 20:] = 255  # the right half is the scene
    Image.fromarray(mask).save(tmp_path / "masks" / names[2])
    cap = load_transforms(tmp_path / "transforms.json", background=(0.0, 1.0, 0.0))
    assert cap.split == ["train"] * 4 + ["test"] * 2 and cap.has_split
    for i, v in enumerate(cap.views):  # per-frame focal lengths, each undistorted
        new = pinhole_for(Intrinsics(30.0 + i, 30.0 + i, 20.0, 15.0, 40, 30),
                          Distortion("fisheye", (0.02, -0.01, 0.0, 0.0)))
        assert v.camera.fx == pytest.approx(new.fx)
    assert cap.points is not None and cap.colors is not None
    np.testing.assert_allclose(cap.points.numpy(), xyz, atol=1e-6)
    np.testing.assert_allclose(cap.colors.numpy(), rgb / 255.0, atol=1e-6)
    masked = cap.views[2]
    assert masked.alpha is not None and cap.has_alpha
    assert all(v.alpha is None for k, v in enumerate(cap.views) if k != 2)
    assert masked.image is not None
    # left of the principal point the mask says "not the scene": the background shows
    left = masked.alpha[:, :18] == 0
    assert bool(left.all())
    torch.testing.assert_close(masked.image[:, :18], torch.tensor([0.0, 1.0, 0.0]).expand(
        30, 18, 3))
    assert bool((masked.alpha[:, 22:] == 1).all())


def test_transforms_errors_name_the_field(tmp_path: Path) -> None:
    _write_images(tmp_path / "images", ["a.png"], 8, 6)
    base = {"file_path": "images/a.png", "transform_matrix": _c2w_gl(_eyes(1)[0]),
            "fl_x": 8.0, "w": 8, "h": 6}
    cases = [
        ({"camera_model": "EQUIRECTANGULAR"}, "camera_model 'EQUIRECTANGULAR'"),
        ({"k4": 0.1}, "k4"),
        ({"camera_model": "OPENCV_FISHEYE", "p1": 0.01}, "p1/p2"),
        ({"k1": "x"}, "k1 must be a number"),
        ({"mask_path": "masks/none.png"}, "mask"),
    ]
    for extra, match in cases:
        (tmp_path / "transforms.json").write_text(json.dumps({"frames": [{**base, **extra}]}))
        with pytest.raises((ValueError, FileNotFoundError), match=match):
            load_transforms(tmp_path / "transforms.json")
    (tmp_path / "transforms.json").write_text(json.dumps(
        {"frames": [base], "test_filenames": "images/a.png"}))
    with pytest.raises(ValueError, match="test_filenames must be a list"):
        load_transforms(tmp_path / "transforms.json")


def test_a_folding_distortion_is_not_undistorted_beyond_its_fold() -> None:
    """A strong barrel k1 turns the radius back beyond r = 1/sqrt(3|k1|): the pinhole view
    stops before the fold, however much of the photograph lies past it."""
    dist = Distortion("opencv", (-0.6, 0.0, 0.0, 0.0))
    raw = Intrinsics(40.0, 40.0, 50.0, 50.0, 100, 100)
    new = pinhole_for(raw, dist)
    corner = np.hypot(50.0, 50.0) / new.fx  # normalised radius of the new image's corner
    assert 0.9 / math.sqrt(3 * 0.6) < corner <= 1.01 / math.sqrt(3 * 0.6)
    r = np.linspace(0.0, corner, 200)
    rd, _ = distort_normalized(r, np.zeros_like(r), dist)
    assert np.all(np.diff(rd) >= 0)
