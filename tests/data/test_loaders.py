"""Loaders: COLMAP models (text and binary, written here byte by byte) and transforms.json."""

from __future__ import annotations

import json
import logging
import math
import struct
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from agilegs.service.data.colmap import (
    load_colmap,
    qvec_to_rotmat,
    read_colmap_model,
    rotmat_to_qvec,
)
from agilegs.service.data.images import View
from agilegs.service.data.transforms import load_transforms_json

Rotation = pytest.importorskip("scipy.spatial.transform").Rotation

# (id, model name, model id, width, height, params)
CAMERAS = [
    (1, "PINHOLE", 1, 40, 30, (50.0, 52.0, 20.5, 14.5)),
    (2, "SIMPLE_RADIAL", 2, 32, 24, (40.0, 16.0, 12.0, 0.01)),
    (3, "OPENCV", 4, 48, 36, (60.0, 61.0, 24.0, 18.0, 0.0, 0.0, 0.0, 0.0)),
    (4, "SIMPLE_PINHOLE", 0, 20, 20, (25.0, 10.0, 10.0)),
    (5, "RADIAL", 3, 20, 16, (22.0, 10.0, 8.0, 0.0, 0.0)),
    (6, "FULL_OPENCV", 6, 40, 30, (50.0, 51.0, 20.0, 15.0, -0.05, 0.01, 0.001, -0.001,
                                   0.0, 0.0, 0.0, 0.0)),
    (7, "SIMPLE_RADIAL_FISHEYE", 8, 40, 30, (30.0, 20.0, 15.0, 0.02)),
    (8, "RADIAL_FISHEYE", 9, 40, 30, (30.0, 20.0, 15.0, 0.0, 0.0)),
    (9, "OPENCV_FISHEYE", 5, 40, 30, (30.0, 31.0, 20.0, 15.0, 0.01, -0.01, 0.0, 0.0)),
]
DISTORTED = {2, 6, 7, 9}


def _random_images(seed: int = 0):
    rng = np.random.default_rng(seed)
    images = []
    names = ["frame_c.png", "frame_a.png", "frame_d.png", "frame_b.png", "frame_e.png",
             "frame_f.png", "frame_i.png", "frame_h.png", "frame_g.png"]
    for k, name in enumerate(names):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        if k == 0:
            q = -q  # COLMAP may store either sign
        t = rng.normal(size=3).tolist()
        images.append(
            (10 + k, tuple(float(v) for v in q), tuple(t), CAMERAS[k % len(CAMERAS)][0], name)
        )
    return images


def _random_points(n: int = 7, seed: int = 1):
    rng = np.random.default_rng(seed)
    pts = []
    for i in range(n):
        xyz = tuple(float(v) for v in rng.normal(size=3))
        rgb = tuple(int(c) for c in rng.integers(0, 256, size=3))
        track = [(10 + int(j), int(rng.integers(0, 50))) for j in range(int(rng.integers(1, 4)))]
        pts.append((100 + i, xyz, rgb, float(rng.random()), track))
    return pts


def write_text_model(d: Path, cameras, images, points) -> None:
    d.mkdir(parents=True, exist_ok=True)
    with open(d / "cameras.txt", "w") as f:
        f.write("# Camera list with one line of data per camera:\n")
        f.write("#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        f.write(f"# Number of cameras: {len(cameras)}\n")
        for cid, model, _, w, h, params in cameras:
            f.write(f"{cid} {model} {w} {h} " + " ".join(repr(p) for p in params) + "\n")
    with open(d / "images.txt", "w") as f:
        f.write("# Image list with two lines of data per image:\n")
        f.write("#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n")
        f.write("#   POINTS2D[] as (X, Y, POINT3D_ID)\n")
        for k, (iid, q, t, cid, name) in enumerate(images):
            f.write(f"{iid} " + " ".join(repr(v) for v in (*q, *t)) + f" {cid} {name}\n")
            if k % 2 == 0:
                f.write("1.5 2.5 100 3.5 4.5 -1\n")
            else:
                f.write("\n")  # an image without 2D points has an empty line
    with open(d / "points3D.txt", "w") as f:
        f.write("# 3D point list with one line of data per point:\n")
        for pid, xyz, rgb, err, track in points:
            tr = " ".join(f"{a} {b}" for a, b in track)
            f.write(
                f"{pid} {xyz[0]!r} {xyz[1]!r} {xyz[2]!r} {rgb[0]} {rgb[1]} {rgb[2]} {err} {tr}\n"
            )


def write_binary_model(d: Path, cameras, images, points) -> None:
    """Exactly COLMAP's binary layout (little endian), as its read_write_model.py writes it."""
    d.mkdir(parents=True, exist_ok=True)
    with open(d / "cameras.bin", "wb") as f:
        f.write(struct.pack("<Q", len(cameras)))
        for cid, _, mid, w, h, params in cameras:
            f.write(struct.pack("<iiQQ", cid, mid, w, h))
            f.write(struct.pack("<" + "d" * len(params), *params))
    with open(d / "images.bin", "wb") as f:
        f.write(struct.pack("<Q", len(images)))
        for k, (iid, q, t, cid, name) in enumerate(images):
            f.write(struct.pack("<idddddddi", iid, *q, *t, cid))
            f.write(name.encode("utf-8") + b"\x00")
            pts2d = [(1.5, 2.5, 100), (3.5, 4.5, -1)] if k % 2 == 0 else []
            f.write(struct.pack("<Q", len(pts2d)))
            for x, y, pid in pts2d:
                f.write(struct.pack("<ddq", x, y, pid))
    with open(d / "points3D.bin", "wb") as f:
        f.write(struct.pack("<Q", len(points)))
        for pid, xyz, rgb, err, track in points:
            f.write(struct.pack("<QdddBBBd", pid, *xyz, *rgb, err))
            f.write(struct.pack("<Q", len(track)))
            for a, b in track:
                f.write(struct.pack("<ii", a, b))


def _expected_c2w(q, t) -> np.ndarray:
    # scipy's quaternion order is (x, y, z, w): an independent check of COLMAP's (w, x, y, z)
    r = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
    w2c = np.eye(4)
    w2c[:3, :3] = r
    w2c[:3, 3] = t
    return np.linalg.inv(w2c)


def _check_model(views: list[View], points, colors, images, pts) -> None:
    by_name = {v.name: v for v in views}
    assert [v.name for v in views] == sorted(by_name)
    cams = {c[0]: c for c in CAMERAS}
    for _iid, q, t, cid, name in images:
        v = by_name[name]
        np.testing.assert_allclose(v.camera.c2w.numpy(), _expected_c2w(q, t), atol=1e-5)
        assert v.camera.c2w.dtype == torch.float32
        _, model, _, w, h, params = cams[cid]
        assert (v.camera.width, v.camera.height) == (w, h)
        if model in ("PINHOLE", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE"):
            fx, fy, cx, cy = params[:4]
        else:
            fx, fy, cx, cy = params[0], params[0], params[1], params[2]
        if cid in DISTORTED:  # undistorted to a pinhole camera: focal lengths scaled alike
            s = v.camera.fx / fx
            assert s != pytest.approx(1.0, abs=1e-4) and 0.5 < s < 2.0
            assert v.camera.fy == pytest.approx(fy * s)
        else:
            assert v.camera.fx == pytest.approx(fx)
            assert v.camera.fy == pytest.approx(fy)
        assert (v.camera.cx, v.camera.cy) == (pytest.approx(cx), pytest.approx(cy))
        assert v.image is None and v.depth is None
    np.testing.assert_allclose(points.numpy(), np.array([p[1] for p in pts]), atol=1e-6)
    np.testing.assert_allclose(colors.numpy(), np.array([p[2] for p in pts]) / 255.0, atol=1e-6)
    assert points.dtype == torch.float32 and colors.dtype == torch.float32


@pytest.mark.parametrize("fmt", ["text", "binary"])
def test_colmap_model_poses_intrinsics_points(tmp_path: Path, fmt: str, caplog) -> None:
    images, pts = _random_images(), _random_points()
    writer = write_text_model if fmt == "text" else write_binary_model
    writer(tmp_path / "sparse", CAMERAS, images, pts)
    with caplog.at_level(logging.INFO):
        views, points, colors = load_colmap(tmp_path / "sparse")
    _check_model(views, points, colors, images, pts)
    # each distorted camera says it is undistorted; zero distortion says nothing
    said = [r.getMessage() for r in caplog.records if "undistorted" in r.getMessage()]
    assert len(said) == len(DISTORTED)
    for cid, model, *_ in CAMERAS:
        assert any(f"camera {cid} ({model}," in m for m in said) == (cid in DISTORTED)
    model = read_colmap_model(tmp_path / "sparse")
    assert model.images[10].num_points2d == 2 and model.images[11].num_points2d == 0


def test_colmap_text_equals_binary(tmp_path: Path) -> None:
    images, pts = _random_images(seed=5), _random_points(seed=6)
    write_text_model(tmp_path / "t", CAMERAS, images, pts)
    write_binary_model(tmp_path / "b", CAMERAS, images, pts)
    vt, pt, ct = load_colmap(tmp_path / "t")
    vb, pb, cb = load_colmap(tmp_path / "b")
    for a, b in zip(vt, vb, strict=True):
        assert a.name == b.name and a.camera.intrinsics == b.camera.intrinsics
        torch.testing.assert_close(a.camera.c2w, b.camera.c2w)
    torch.testing.assert_close(pt, pb)
    torch.testing.assert_close(ct, cb)


def test_colmap_pose_projects_points_like_colmap(tmp_path: Path) -> None:
    """A world point seen by COLMAP at R X + t has camera coordinates inv(c2w) X."""
    images, pts = _random_images(seed=2), _random_points(seed=3)
    write_binary_model(tmp_path / "m", CAMERAS, images, pts)
    views, points, _ = load_colmap(tmp_path / "m")
    by_name = {v.name: v for v in views}
    x = np.array([0.3, -0.2, 1.7])
    for _, q, t, _, name in images:
        r = qvec_to_rotmat(q)
        cam_colmap = r @ x + np.asarray(t)
        w2c = by_name[name].camera.w2c.double().numpy()
        np.testing.assert_allclose(w2c[:3, :3] @ x + w2c[:3, 3], cam_colmap, atol=1e-5)
        np.testing.assert_allclose(
            np.abs(rotmat_to_qvec(r)), np.abs(np.asarray(q) / np.linalg.norm(q)), atol=1e-9
        )


def test_colmap_images_and_downscale(tmp_path: Path, caplog) -> None:
    cams = [(1, "PINHOLE", 1, 40, 30, (50.0, 52.0, 20.0, 15.0))]
    images = [
        (1, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1, "a.png"),
        (2, (1.0, 0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 1, "sub/b.png"),
    ]
    write_text_model(tmp_path / "sparse", cams, images, _random_points(2))
    img_dir = tmp_path / "images"
    (img_dir / "sub").mkdir(parents=True)
    rng = np.random.default_rng(0)
    raw = {}
    for _, _, _, _, name in images:
        a = rng.integers(0, 256, size=(30, 40, 3), dtype=np.uint8)
        Image.fromarray(a).save(img_dir / name)
        raw[name] = a
    # full resolution: exact pixels
    views, _, _ = load_colmap(tmp_path / "sparse", img_dir)
    for v in views:
        assert v.image is not None and v.image.shape == (30, 40, 3)
        assert v.image.dtype == torch.float32
        np.testing.assert_allclose(v.image.numpy(), raw[v.name] / 255.0, atol=1e-6)
    # downscale 2: PIL resize and halved intrinsics
    views2, _, _ = load_colmap(tmp_path / "sparse", img_dir, downscale=2)
    for v in views2:
        assert v.image is not None and v.image.shape == (15, 20, 3)
        assert (v.camera.fx, v.camera.fy, v.camera.cx, v.camera.cy) == (25.0, 26.0, 10.0, 7.5)
        expect = Image.fromarray(raw[v.name]).resize((20, 15), Image.Resampling.LANCZOS)
        np.testing.assert_allclose(v.image.numpy(), np.asarray(expect) / 255.0, atol=1e-6)
    # a missing image file is skipped, with one warning that counts it
    (img_dir / "a.png").unlink()
    with caplog.at_level(logging.WARNING):
        views3, _, _ = load_colmap(tmp_path / "sparse", img_dir)
    assert [v.name for v in views3] == ["sub/b.png"]
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and "1 of 2 images" in warned[0] and "a.png" in warned[0]
    # none left: an error naming the first
    (img_dir / "sub" / "b.png").unlink()
    with pytest.raises(FileNotFoundError, match="none of the model's 2 images.*a.png"):
        load_colmap(tmp_path / "sparse", img_dir)


def test_colmap_malformed_text(tmp_path: Path) -> None:
    d = tmp_path / "m"
    write_text_model(d, CAMERAS, _random_images(), _random_points())
    lines = (d / "cameras.txt").read_text().splitlines()
    good = list(lines)
    lines[4] = "2 SIMPLE_RADIAL 32 24 40.0 16.0"  # too few params, file line 5
    (d / "cameras.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"cameras\.txt:5: .*SIMPLE_RADIAL takes 4"):
        load_colmap(d)
    lines = list(good)
    lines[3] = "1 WEIRD 40 30 1 2 3"
    (d / "cameras.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"cameras\.txt:4: unknown camera model 'WEIRD'"):
        load_colmap(d)
    lines = list(good)
    lines[3] = "1 PINHOLE forty 30 1 2 3 4"
    (d / "cameras.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"cameras\.txt:4: .*'forty'"):
        load_colmap(d)
    (d / "cameras.txt").write_text("\n".join(good) + "\n")
    img_lines = (d / "images.txt").read_text().splitlines()
    img_lines[3] = "10 1 0 0 0 0.0 0.0"
    (d / "images.txt").write_text("\n".join(img_lines) + "\n")
    with pytest.raises(ValueError, match=r"images\.txt:4: image needs at least 9 fields"):
        load_colmap(d)


def test_colmap_unsupported_and_missing_camera(tmp_path: Path) -> None:
    cams = [(1, "FOV", 7, 20, 20, (10.0, 10.0, 10.0, 10.0, 0.1))]
    images = [(1, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1, "a.png")]
    write_binary_model(tmp_path / "m", cams, images, [])
    with pytest.raises(ValueError, match="camera 1: camera model FOV is not supported"):
        load_colmap(tmp_path / "m")
    images = [(1, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 7, "a.png")]
    write_binary_model(tmp_path / "n", CAMERAS[:1], images, [])
    with pytest.raises(ValueError, match="refers to camera 7"):
        load_colmap(tmp_path / "n")


def test_colmap_malformed_binary(tmp_path: Path) -> None:
    d = tmp_path / "m"
    write_binary_model(d, CAMERAS, _random_images(), _random_points())
    data = (d / "images.bin").read_bytes()
    (d / "images.bin").write_bytes(data[:-30])
    with pytest.raises(ValueError, match=r"images\.bin: image record 8.*truncated"):
        load_colmap(d)
    (d / "images.bin").write_bytes(data)
    cam = bytearray((d / "cameras.bin").read_bytes())
    struct.pack_into("<i", cam, 8 + 4, 42)  # model id of camera record 0
    (d / "cameras.bin").write_bytes(bytes(cam))
    with pytest.raises(ValueError, match=r"cameras\.bin: camera record 0: unknown camera model"):
        load_colmap(d)
    write_binary_model(d, CAMERAS, _random_images(), _random_points())
    (d / "points3D.bin").write_bytes((d / "points3D.bin").read_bytes() + b"\x00")
    with pytest.raises(ValueError, match=r"points3D\.bin: 1 trailing bytes"):
        load_colmap(d)
    (d / "cameras.bin").write_bytes(struct.pack("<Q", 10**12))
    with pytest.raises(ValueError, match=r"cameras\.bin: camera count says"):
        load_colmap(d)


def test_colmap_missing_model(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no COLMAP model"):
        load_colmap(tmp_path / "empty")


# ----------------------------------------------------------------------------- transforms.json
def _blender_c2w(eye: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world looking from ``eye`` at the origin, world up +z (Blender)."""
    back = eye / np.linalg.norm(eye)  # camera +z points away from the target
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, back, eye
    return m


def _write_synthetic(tmp_path: Path, w: int = 16, h: int = 12):
    (tmp_path / "train").mkdir()
    eyes = [np.array([4.0, 0.0, 1.0]), np.array([0.0, 3.0, 2.0]), np.array([-2.0, -2.0, 0.5])]
    frames, raws = [], []
    rng = np.random.default_rng(0)
    for i, eye in enumerate(eyes):
        rgba = rng.integers(0, 256, size=(h, w, 4), dtype=np.uint8)
        rgba[0, 0, 3] = 0
        rgba[0, 1, 3] = 255
        Image.fromarray(rgba, mode="RGBA").save(tmp_path / "train" / f"r_{i}.png")
        raws.append(rgba)
        fp = f"./train/r_{i}" if i != 1 else f"./train/r_{i}.png"
        frames.append(
            {"file_path": fp, "rotation": 0.0, "transform_matrix": _blender_c2w(eye).tolist()}
        )
    angle = 0.6911112070083618
    (tmp_path / "transforms_train.json").write_text(
        json.dumps({"camera_angle_x": angle, "frames": frames})
    )
    return tmp_path / "transforms_train.json", eyes, raws, angle


def test_transforms_json(tmp_path: Path) -> None:
    path, eyes, raws, angle = _write_synthetic(tmp_path)
    bg = (0.2, 0.4, 0.6)
    views = load_transforms_json(path, background=bg)
    assert len(views) == 3
    fx = 0.5 * 16 / math.tan(0.5 * angle)
    for v, eye, raw in zip(views, eyes, raws, strict=True):
        cam = v.camera
        assert (cam.width, cam.height) == (16, 12)
        assert cam.fx == pytest.approx(fx) and cam.fy == pytest.approx(fx)
        assert (cam.cx, cam.cy) == (8.0, 6.0)
        # OpenCV forward (+z) looks at the origin; image down (+y) points away from world up
        np.testing.assert_allclose(cam.position.numpy(), eye, atol=1e-6)
        fwd = cam.forward.numpy()
        np.testing.assert_allclose(fwd, -eye / np.linalg.norm(eye), atol=1e-6)
        assert float(cam.c2w[2, 1]) < 0
        # the origin projects to the principal point
        pc = cam.w2c.double().numpy() @ np.array([0.0, 0.0, 0.0, 1.0])
        assert pc[2] > 0
        np.testing.assert_allclose(pc[:2] / pc[2], [0.0, 0.0], atol=1e-6)
        # the c2w is the Blender one with camera y and z negated
        gl = _blender_c2w(eye)
        np.testing.assert_allclose(cam.c2w.numpy()[:3, 0], gl[:3, 0], atol=1e-6)
        np.testing.assert_allclose(cam.c2w.numpy()[:3, 1:3], -gl[:3, 1:3], atol=1e-6)
        # alpha compositing on the background
        assert v.image is not None and v.image.shape == (12, 16, 3)
        a = raw[..., 3:4] / 255.0
        expect = raw[..., :3] / 255.0 * a + np.asarray(bg) * (1 - a)
        np.testing.assert_allclose(v.image.numpy(), expect, atol=1e-6)
        np.testing.assert_allclose(v.image[0, 0].numpy(), bg, atol=1e-6)
        np.testing.assert_allclose(v.image[0, 1].numpy(), raw[0, 1, :3] / 255.0, atol=1e-6)
    assert views[0].name == "./train/r_0"


def test_transforms_json_downscale_and_no_images(tmp_path: Path) -> None:
    path, _, _, angle = _write_synthetic(tmp_path)
    views = load_transforms_json(path, downscale=2)
    fx = 0.5 * 8 / math.tan(0.5 * angle)
    for v in views:
        assert v.image is not None and v.image.shape == (6, 8, 3)
        assert v.camera.fx == pytest.approx(fx) and (v.camera.cx, v.camera.cy) == (4.0, 3.0)
    lazy = load_transforms_json(path, load_images=False)
    assert all(v.image is None for v in lazy) and lazy[0].camera.width == 16


def test_a_missing_depth_file_is_skipped_like_a_missing_image(tmp_path: Path, caplog) -> None:
    path, _, _, _ = _write_synthetic(tmp_path)
    meta = json.loads(path.read_text())
    for i, fr in enumerate(meta["frames"]):
        fr["depth_file_path"] = f"train/d_{i}.png"
        if i != 1:  # frame 1's depth file is missing
            Image.fromarray(np.full((12, 16), 1500, dtype=np.uint16)).save(
                tmp_path / "train" / f"d_{i}.png")
    meta["frames"].append({"file_path": "./train/gone", "transform_matrix":
                           meta["frames"][0]["transform_matrix"]})  # its image is missing
    path.write_text(json.dumps(meta))
    with caplog.at_level("WARNING"):
        views = load_transforms_json(path)
    assert [v.name for v in views] == ["./train/r_0", "./train/r_2"]
    assert all(float(v.depth[0, 0]) == pytest.approx(1.5) for v in views)
    warned = [r.getMessage() for r in caplog.records if "skipped" in r.getMessage()]
    assert len(warned) == 1 and "2 of 4 frames" in warned[0] and "d_1.png" in warned[0]


def test_transforms_json_errors(tmp_path: Path) -> None:
    path, _, _, _ = _write_synthetic(tmp_path)
    meta = json.loads(path.read_text())
    bad = json.loads(json.dumps(meta))
    bad["frames"][1]["transform_matrix"] = [[1, 0, 0], [0, 1, 0]]
    path.write_text(json.dumps(bad))
    with pytest.raises(ValueError, match=r"frames\[1\]: transform_matrix must be 4x4"):
        load_transforms_json(path)
    bad = json.loads(json.dumps(meta))
    m = np.asarray(bad["frames"][2]["transform_matrix"])
    m[:3, 0] *= -1  # a reflection
    bad["frames"][2]["transform_matrix"] = m.tolist()
    path.write_text(json.dumps(bad))
    with pytest.raises(ValueError, match=r"frames\[2\]: .*determinant"):
        load_transforms_json(path)
    bad = json.loads(json.dumps(meta))
    del bad["camera_angle_x"]
    path.write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="camera_angle_x"):
        load_transforms_json(path)
    bad = json.loads(json.dumps(meta))
    for fr in bad["frames"]:
        fr["file_path"] = "./train/missing"
    path.write_text(json.dumps(bad))
    with pytest.raises(FileNotFoundError, match="none of the 3 frames.*missing"):
        load_transforms_json(path)
    path.write_text("{not json")
    with pytest.raises(ValueError, match="invalid JSON at line 1"):
        load_transforms_json(path)
