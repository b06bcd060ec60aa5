"""COLMAP models (``cameras``, ``images``, ``points3D`` as ``.txt`` or ``.bin``) as posed views.

An image stores the world-to-camera rotation as a quaternion (w, x, y, z) and translation t,
already in OpenCV axes; c2w = [Rᵀ | -Rᵀ t]. Camera models SIMPLE_PINHOLE, PINHOLE,
SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV, SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE and
OPENCV_FISHEYE are read; images of a distorted camera are undistorted to a pinhole camera
(:mod:`agilegs.service.data.distortion`), FOV and THIN_PRISM_FISHEYE are refused. Images the
model lists but the folder lacks are skipped, with one warning that counts them. Malformed
files raise ``ValueError`` naming the file and the line (text) or record (binary).
"""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from agilegs.schemas.geometry import matrix_to_quaternion_xyzw, quaternion_xyzw_to_matrix
from agilegs.service.nbv import Camera, Intrinsics

from .distortion import Distortion, colmap_distortion, pinhole_for
from .images import PathLike, View, load_capture_image, target_size

log = logging.getLogger(__name__)

__all__ = [
    "COLMAP_CAMERA_MODELS",
    "ColmapCamera",
    "ColmapImage",
    "ColmapModel",
    "colmap_to_c2w",
    "load_colmap",
    "qvec_to_rotmat",
    "read_cameras_binary",
    "read_cameras_text",
    "read_colmap_model",
    "read_images_binary",
    "read_images_text",
    "read_points3d_binary",
    "read_points3d_text",
    "rotmat_to_qvec",
]


def qvec_to_rotmat(qvec: Sequence[float] | np.ndarray) -> np.ndarray:
    """Rotation matrix [3, 3] (float64) of COLMAP's quaternion (w, x, y, z), normalised first."""
    return quaternion_xyzw_to_matrix(np.roll(np.asarray(qvec, dtype=np.float64), -1))


def rotmat_to_qvec(r: np.ndarray) -> np.ndarray:
    """COLMAP's unit quaternion (w, x, y, z), w >= 0, of a rotation matrix [3, 3]."""
    return np.roll(matrix_to_quaternion_xyzw(r), 1)


def colmap_to_c2w(qvec: Sequence[float] | np.ndarray, tvec: Sequence[float] | np.ndarray) -> Tensor:
    """Camera-to-world [4, 4] float64 from COLMAP's world-to-camera (qvec (w,x,y,z), tvec)."""
    r = qvec_to_rotmat(qvec)
    t = np.asarray(tvec, dtype=np.float64).reshape(3)
    c2w = np.eye(4)
    c2w[:3, :3] = r.T
    c2w[:3, 3] = -r.T @ t
    return torch.from_numpy(c2w)


@dataclass(frozen=True)
class _CameraModelSpec:
    model_id: int
    name: str
    num_params: int


#: COLMAP's camera models (id, name, parameter count), as in its ``read_write_model.py``.
COLMAP_CAMERA_MODELS: dict[int, _CameraModelSpec] = {
    s.model_id: s
    for s in (
        _CameraModelSpec(0, "SIMPLE_PINHOLE", 3),
        _CameraModelSpec(1, "PINHOLE", 4),
        _CameraModelSpec(2, "SIMPLE_RADIAL", 4),
        _CameraModelSpec(3, "RADIAL", 5),
        _CameraModelSpec(4, "OPENCV", 8),
        _CameraModelSpec(5, "OPENCV_FISHEYE", 8),
        _CameraModelSpec(6, "FULL_OPENCV", 12),
        _CameraModelSpec(7, "FOV", 5),
        _CameraModelSpec(8, "SIMPLE_RADIAL_FISHEYE", 4),
        _CameraModelSpec(9, "RADIAL_FISHEYE", 5),
        _CameraModelSpec(10, "THIN_PRISM_FISHEYE", 12),
    )
}
_MODEL_BY_NAME = {s.name: s for s in COLMAP_CAMERA_MODELS.values()}
_SUPPORTED = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV",
              "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "OPENCV_FISHEYE")
_ONE_FOCAL = ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE",
              "RADIAL_FISHEYE")


@dataclass
class ColmapCamera:
    """A COLMAP camera: ``params`` in COLMAP's order for ``model``."""

    camera_id: int
    model: str
    width: int
    height: int
    params: tuple[float, ...]

    def pinhole(self, where: str = "") -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) of a supported model (the photograph's pinhole part)."""
        p = self.params
        if self.model not in _SUPPORTED:
            raise ValueError(
                f"{where}camera {self.camera_id}: unsupported camera model {self.model} "
                f"(supported: {', '.join(_SUPPORTED)}; undistort the images first)"
            )
        if self.model in _ONE_FOCAL:
            return p[0], p[0], p[1], p[2]
        return p[0], p[1], p[2], p[3]

    def distortion(self, where: str = "") -> Distortion:
        """The model's lens distortion."""
        try:
            return colmap_distortion(self.model, self.params)
        except ValueError as exc:
            raise ValueError(f"{where}camera {self.camera_id}: {exc}") from exc

    def raw_intrinsics(self, where: str = "") -> Intrinsics:
        """The photograph's pinhole part at the model's size (before undistortion)."""
        fx, fy, cx, cy = self.pinhole(where)
        try:
            return Intrinsics(fx, fy, cx, cy, self.width, self.height)
        except ValueError as exc:
            raise ValueError(f"{where}camera {self.camera_id}: {exc}") from exc

    def intrinsics(self, where: str = "") -> Intrinsics:
        """The pinhole camera its images are undistorted to (the raw one without distortion)."""
        return pinhole_for(self.raw_intrinsics(where), self.distortion(where))


@dataclass
class ColmapImage:
    """A registered COLMAP image: world-to-camera ``qvec`` (w, x, y, z) and ``tvec``."""

    image_id: int
    qvec: tuple[float, float, float, float]
    tvec: tuple[float, float, float]
    camera_id: int
    name: str
    num_points2d: int = 0

    def c2w(self) -> Tensor:
        """Camera-to-world [4, 4] float64, OpenCV axes."""
        return colmap_to_c2w(self.qvec, self.tvec)


@dataclass
class ColmapModel:
    """A COLMAP sparse model: cameras and images by id, points [P, 3] and colours [P, 3]."""

    cameras: dict[int, ColmapCamera]
    images: dict[int, ColmapImage]
    points: np.ndarray  # [P, 3] float64
    colors: np.ndarray  # [P, 3] uint8
    point_ids: np.ndarray  # [P] int64


def _text_records(path: Path) -> list[tuple[int, str]]:
    """(1-based line number, stripped line) of the non-comment lines, empty lines kept."""
    try:
        text = path.read_text()
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a text file ({exc})") from exc
    return [
        (i + 1, line.strip())
        for i, line in enumerate(text.splitlines())
        if not line.lstrip().startswith("#")
    ]


def _parse_fields(path: Path, lineno: int, elems: list[str], types: str, what: str) -> list[Any]:
    if len(elems) < len(types):
        raise ValueError(
            f"{path}:{lineno}: {what} needs at least {len(types)} fields, got {len(elems)}"
        )
    out: list[Any] = []
    for e, t in zip(elems, types, strict=False):
        try:
            v: Any = int(e) if t == "i" else float(e) if t == "f" else e
        except ValueError:
            raise ValueError(f"{path}:{lineno}: {what}: cannot parse {e!r}") from None
        if t == "f" and not math.isfinite(v):
            raise ValueError(f"{path}:{lineno}: {what}: non-finite value {e!r}")
        out.append(v)
    return out


def read_cameras_text(path: PathLike) -> dict[int, ColmapCamera]:
    """Parse COLMAP ``cameras.txt``: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`` per line."""
    p = Path(path)
    cams: dict[int, ColmapCamera] = {}
    for lineno, line in _text_records(p):
        if not line:
            continue
        elems = line.split()
        cid, model, w, h = _parse_fields(p, lineno, elems, "isii", "camera")
        spec = _MODEL_BY_NAME.get(model)
        if spec is None:
            raise ValueError(f"{p}:{lineno}: unknown camera model {model!r}")
        params = _parse_fields(p, lineno, elems[4:], "f" * len(elems[4:]), "camera params")
        if len(params) != spec.num_params:
            raise ValueError(
                f"{p}:{lineno}: camera model {model} takes {spec.num_params} parameters, "
                f"got {len(params)}"
            )
        cams[cid] = ColmapCamera(cid, model, w, h, tuple(params))
    return cams


def read_images_text(path: PathLike) -> dict[int, ColmapImage]:
    """Parse COLMAP ``images.txt``: two lines per image, the pose line
    ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` then the (possibly empty) points line."""
    p = Path(path)
    images: dict[int, ColmapImage] = {}
    recs = _text_records(p)
    k = 0
    while k < len(recs):
        lineno, line = recs[k]
        k += 1
        if not line:
            continue
        elems = line.split()
        f = _parse_fields(p, lineno, elems, "ifffffffi", "image")
        if len(elems) < 10:
            raise ValueError(f"{p}:{lineno}: image line has no NAME field")
        name = " ".join(elems[9:])  # names may contain spaces
        # the next line holds the 2D points (X Y POINT3D_ID triplets), possibly empty
        n2d = 0
        if k < len(recs):
            pl, pline = recs[k]
            k += 1
            pts = pline.split()
            if len(pts) % 3 != 0:
                raise ValueError(
                    f"{p}:{pl}: POINTS2D line must hold X Y POINT3D_ID triplets, "
                    f"got {len(pts)} fields"
                )
            n2d = len(pts) // 3
        images[f[0]] = ColmapImage(
            image_id=f[0],
            qvec=(f[1], f[2], f[3], f[4]),
            tvec=(f[5], f[6], f[7]),
            camera_id=f[8],
            name=name,
            num_points2d=n2d,
        )
    return images


def read_points3d_text(path: PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Parse COLMAP ``points3D.txt``: ``POINT3D_ID X Y Z R G B ERROR TRACK[]`` per line.

    Returns:
        (ids [P] int64, xyz [P, 3] float64, rgb [P, 3] uint8).
    """
    p = Path(path)
    ids: list[int] = []
    xyz: list[list[float]] = []
    rgb: list[list[int]] = []
    for lineno, line in _text_records(p):
        if not line:
            continue
        elems = line.split()
        f = _parse_fields(p, lineno, elems, "ifffiiif", "point")
        if (len(elems) - 8) % 2 != 0:
            raise ValueError(
                f"{p}:{lineno}: TRACK must hold IMAGE_ID POINT2D_IDX pairs, "
                f"got {len(elems) - 8} fields"
            )
        if not all(0 <= c <= 255 for c in f[4:7]):
            raise ValueError(f"{p}:{lineno}: colour {f[4:7]} outside 0..255")
        ids.append(f[0])
        xyz.append(f[1:4])
        rgb.append(f[4:7])
    return (
        np.asarray(ids, dtype=np.int64).reshape(-1),
        np.asarray(xyz, dtype=np.float64).reshape(-1, 3),
        np.asarray(rgb, dtype=np.uint8).reshape(-1, 3),
    )


class _BinReader:
    """Little-endian struct reader that reports the file, record and byte offset on errors."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    def read(self, fmt: str, what: str) -> tuple[Any, ...]:
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise ValueError(
                f"{self.path}: {what}: truncated at byte {self.pos} "
                f"(needs {size} bytes, {len(self.data) - self.pos} left)"
            )
        out = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return out

    def skip(self, nbytes: int, what: str) -> None:
        if nbytes < 0 or self.pos + nbytes > len(self.data):
            raise ValueError(
                f"{self.path}: {what}: truncated at byte {self.pos} "
                f"(needs {nbytes} bytes, {len(self.data) - self.pos} left)"
            )
        self.pos += nbytes

    def cstring(self, what: str) -> str:
        end = self.data.find(b"\x00", self.pos)
        if end < 0:
            raise ValueError(f"{self.path}: {what}: unterminated name at byte {self.pos}")
        raw = self.data[self.pos : end]
        self.pos = end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ValueError(f"{self.path}: {what}: name is not UTF-8 ({exc})") from exc

    def count(self, what: str, per_item_min: int) -> int:
        (n,) = self.read("Q", what)
        if n * per_item_min > len(self.data) - self.pos:
            raise ValueError(
                f"{self.path}: {what} says {n} entries, more than the "
                f"{len(self.data) - self.pos} bytes left can hold"
            )
        return int(n)

    def finish(self) -> None:
        if self.pos != len(self.data):
            raise ValueError(
                f"{self.path}: {len(self.data) - self.pos} trailing bytes after the last record"
            )


def read_cameras_binary(path: PathLike) -> dict[int, ColmapCamera]:
    """Parse COLMAP ``cameras.bin``: uint64 count, then per camera int32 id, int32 model id,
    uint64 width, uint64 height and the model's float64 parameters."""
    r = _BinReader(Path(path))
    n = r.count("camera count", 24)
    cams: dict[int, ColmapCamera] = {}
    for i in range(n):
        what = f"camera record {i}"
        cid, mid, w, h = r.read("iiQQ", what)
        spec = COLMAP_CAMERA_MODELS.get(mid)
        if spec is None:
            raise ValueError(f"{r.path}: {what}: unknown camera model id {mid}")
        params = r.read("d" * spec.num_params, what)
        if not all(math.isfinite(v) for v in params):
            raise ValueError(f"{r.path}: {what}: non-finite camera parameters")
        cams[cid] = ColmapCamera(cid, spec.name, int(w), int(h), tuple(params))
    r.finish()
    return cams


def read_images_binary(path: PathLike) -> dict[int, ColmapImage]:
    """Parse COLMAP ``images.bin``: uint64 count, then per image int32 id, 4 float64 qvec,
    3 float64 tvec, int32 camera id, NUL-terminated name, uint64 number of 2D points and that
    many (float64 x, float64 y, int64 point3D id)."""
    r = _BinReader(Path(path))
    n = r.count("image count", 64)
    images: dict[int, ColmapImage] = {}
    for i in range(n):
        what = f"image record {i}"
        f = r.read("idddddddi", what)
        if not all(math.isfinite(v) for v in f[1:8]):
            raise ValueError(f"{r.path}: {what}: non-finite pose")
        name = r.cstring(what)
        (n2d,) = r.read("Q", what)
        r.skip(24 * int(n2d), f"{what} points2D")
        images[f[0]] = ColmapImage(
            image_id=f[0],
            qvec=(f[1], f[2], f[3], f[4]),
            tvec=(f[5], f[6], f[7]),
            camera_id=f[8],
            name=name,
            num_points2d=int(n2d),
        )
    r.finish()
    return images


def read_points3d_binary(path: PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Parse COLMAP ``points3D.bin``: uint64 count, then per point uint64 id, 3 float64 xyz,
    3 uint8 rgb, float64 error, uint64 track length and that many (int32 image id,
    int32 point2D index). Returns (ids [P], xyz [P, 3] float64, rgb [P, 3] uint8)."""
    r = _BinReader(Path(path))
    n = r.count("point count", 43 + 8)
    ids = np.empty(n, dtype=np.int64)
    xyz = np.empty((n, 3), dtype=np.float64)
    rgb = np.empty((n, 3), dtype=np.uint8)
    for i in range(n):
        what = f"point record {i}"
        f = r.read("QdddBBBd", what)
        (tl,) = r.read("Q", what)
        r.skip(8 * int(tl), f"{what} track")
        ids[i] = f[0]
        xyz[i] = f[1:4]
        rgb[i] = f[4:7]
    if not np.isfinite(xyz).all():
        bad = int(np.flatnonzero(~np.isfinite(xyz).all(axis=1))[0])
        raise ValueError(f"{r.path}: point record {bad}: non-finite position")
    r.finish()
    return ids, xyz, rgb


def read_colmap_model(model_dir: PathLike, *, quiet: bool = False) -> ColmapModel:
    """Read a COLMAP sparse model folder (``.bin`` files preferred, else ``.txt``).

    ``points3D`` may be missing (the model then has no points; a warning is logged unless
    ``quiet``).
    """
    d = Path(model_dir)
    if not d.is_dir():
        raise FileNotFoundError(f"COLMAP model folder {d} not found")
    if (d / "cameras.bin").is_file() and (d / "images.bin").is_file():
        cams = read_cameras_binary(d / "cameras.bin")
        imgs = read_images_binary(d / "images.bin")
        pfile = d / "points3D.bin"
        reader = read_points3d_binary
    elif (d / "cameras.txt").is_file() and (d / "images.txt").is_file():
        cams = read_cameras_text(d / "cameras.txt")
        imgs = read_images_text(d / "images.txt")
        pfile = d / "points3D.txt"
        reader = read_points3d_text
    else:
        raise FileNotFoundError(
            f"{d}: no COLMAP model (needs cameras.bin + images.bin or cameras.txt + images.txt)"
        )
    if pfile.is_file():
        ids, xyz, rgb = reader(pfile)
    else:
        if not quiet:
            log.warning("%s: no %s, the model has no 3D points", d, pfile.name)
        ids = np.zeros(0, dtype=np.int64)
        xyz = np.zeros((0, 3))
        rgb = np.zeros((0, 3), dtype=np.uint8)
    for im in imgs.values():
        if im.camera_id not in cams:
            raise ValueError(
                f"{d}: image {im.image_id} ({im.name}) refers to camera {im.camera_id}, "
                "which is not in the cameras file"
            )
    return ColmapModel(cameras=cams, images=imgs, points=xyz, colors=rgb, point_ids=ids)


def load_colmap(
    model_dir: PathLike,
    images_dir: PathLike | None = None,
    *,
    downscale: float = 1,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    quiet: bool = False,
) -> tuple[list[View], Tensor, Tensor]:
    """Read a COLMAP model as views, sorted by image name, and its sparse point cloud.

    Each view's camera is the pinhole camera its image was undistorted to; images the model
    lists but ``images_dir`` lacks are skipped (one warning counts them).

    Args:
        model_dir: folder with cameras/images/points3D as ``.bin`` or ``.txt``
            (e.g. ``scene/sparse/0``).
        images_dir: folder holding the images named in the model; None leaves
            ``View.image`` as None (poses and intrinsics only).
        downscale: divide the camera size by this factor (rounded); intrinsics follow and
            images of another size are resized.
        background: RGB an alpha channel (if any) is composited on (``View.alpha`` keeps it).
        quiet: log nothing (a probe before the real load).

    Returns:
        (views, points [P, 3] float32, colors [P, 3] float32 in [0, 1]).

    Raises:
        FileNotFoundError: no model, or none of its images in ``images_dir``.
        ValueError: malformed files or an unsupported camera model.
    """
    model = read_colmap_model(model_dir, quiet=quiet)
    d = Path(model_dir)
    for cam in model.cameras.values() if not quiet else ():
        dist = cam.distortion(f"{d}: ")
        if not dist.is_identity:
            raw, new = cam.raw_intrinsics(f"{d}: "), cam.intrinsics(f"{d}: ")
            log.info("%s: camera %d (%s, distortion %s): images undistorted to a pinhole "
                     "camera, focal length x%.4f", d, cam.camera_id, cam.model,
                     dist.describe(), new.fx / raw.fx)
    views: list[View] = []
    missing: list[str] = []
    for im in sorted(model.images.values(), key=lambda m: m.name):
        where = f"{d}: image {im.image_id} ({im.name}): "
        cam = model.cameras[im.camera_id]
        intr = cam.intrinsics(f"{d}: ")
        try:
            c2w = im.c2w().float()
            camera = Camera.from_intrinsics(c2w, intr)
        except ValueError as exc:
            raise ValueError(f"{where}{exc}") from exc
        tw, th = target_size(cam.width, cam.height, downscale)
        if (tw, th) != (cam.width, cam.height):
            camera = camera.with_resolution(tw, th)
        image = alpha = None
        if images_dir is not None:
            ipath = Path(images_dir) / im.name
            if not ipath.is_file():
                missing.append(im.name)
                continue
            image, alpha = load_capture_image(
                ipath, cam.raw_intrinsics(), cam.distortion(), (tw, th), background=background)
        views.append(View(name=im.name, camera=camera, image=image, alpha=alpha))
    if missing:
        if not quiet:
            log.warning("%s: %d of %d images are not in %s and were skipped (first: %s)", d,
                        len(missing), len(model.images), images_dir, missing[0])
        if not views:
            raise FileNotFoundError(f"{d}: none of the model's {len(missing)} images is in "
                                    f"{images_dir} (first: {missing[0]})")
    points = torch.from_numpy(model.points.astype(np.float32)).reshape(-1, 3)
    colors = torch.from_numpy(model.colors.astype(np.float32) / 255.0).reshape(-1, 3)
    return views, points, colors
