"""``transforms.json`` captures: NeRF-synthetic (Blender), instant-ngp (colmap2nerf) and
nerfstudio (ns-process-data) dialects.

- Intrinsics: ``camera_angle_x`` (and ``camera_angle_y``), or ``fl_x``, ``fl_y``, ``cx``,
  ``cy``, ``w``, ``h``; each key per frame or at the top (a frame's own value wins).
- Distortion: nerfstudio's ``camera_model`` (``OPENCV``, the default, with ``k1 k2 k3 p1 p2``;
  ``OPENCV_FISHEYE`` with ``k1 k2 k3 k4``; ``PINHOLE``), instant-ngp's ``k1 k2 k3 p1 p2`` and
  ``is_fisheye``. Distorted images are undistorted to a pinhole camera
  (:mod:`agilegs.service.data.distortion`); the view's camera is that pinhole camera.
- ``transform_matrix`` is camera-to-world in OpenGL axes (x right, y up, z backward); it is
  converted to the project's OpenCV axes (x right, y down, z forward) by flipping the camera's
  y and z axes (negating columns 1 and 2 of the rotation).
- Frames whose image file, or named depth file, is missing are skipped, with one warning that
  counts them (colmap2nerf users delete blurred frames).
- ``mask_path`` (nerfstudio; 0 = not the scene) and an image's alpha channel make
  ``View.alpha``; the image is composited on ``background`` by it.
- ``depth_file_path``: a depth map per frame; ``ply_file_path``: the capture's
  structure-from-motion points (in the frames' world); ``train_filenames`` /
  ``val_filenames`` / ``test_filenames`` (nerfstudio): the capture's own split.
- Keys the loader has no use for (``aabb_scale``, ``scale``, ``offset``, ``sharpness``,
  ``applied_transform``, ...) are ignored.

Malformed files raise ``ValueError`` naming the file and the frame.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

from agilegs.service.nbv import Camera, Intrinsics

from .distortion import NO_DISTORTION, Distortion, pinhole_for
from .images import PathLike, View, image_size, load_capture_image, load_depth, target_size

log = logging.getLogger(__name__)

__all__ = ["TransformsCapture", "load_transforms", "load_transforms_json",
           "opengl_to_opencv_c2w", "read_ply_points"]

Split = Literal["train", "test"]


@dataclass
class TransformsCapture:
    """A loaded ``transforms.json``.

    Attributes:
        views: one per frame with an image, in file order, c2w in OpenCV axes.
        split: per view, ``"train"`` / ``"test"`` when the file names a split, else None.
        points: the ``ply_file_path`` points [P, 3] float32, or None.
        colors: their colours [P, 3] float32 in [0, 1], or None.
        skipped: file paths of the frames skipped for a missing image.
        distortions: the distinct lens distortions undistorted (described).
    """

    views: list[View]
    split: list[Split | None]
    points: Tensor | None = None
    colors: Tensor | None = None
    skipped: list[str] = field(default_factory=list)
    distortions: list[str] = field(default_factory=list)

    @property
    def has_split(self) -> bool:
        return any(s is not None for s in self.split)

    @property
    def has_alpha(self) -> bool:
        return any(v.alpha is not None for v in self.views)


def opengl_to_opencv_c2w(c2w: Tensor) -> Tensor:
    """Camera-to-world [..., 4, 4] in OpenGL/Blender camera axes to OpenCV camera axes."""
    out = c2w.clone()
    out[..., :3, 1:3] = -out[..., :3, 1:3]
    return out


def _find_frame_image(base: Path, file_path: str) -> Path | None:
    p = (base / file_path).resolve() if not os.path.isabs(file_path) else Path(file_path)
    if p.suffix and p.is_file():
        return p
    for ext in (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG", ".exr"):
        q = p.with_name(p.name + ext)
        if q.is_file():
            return q
    if p.is_file():
        return p
    return None


def _num(value: Any, what: str, where: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: {what} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{where}: {what} must be finite, got {v}")
    return v


def _distortion(get: Any, where: str) -> Distortion:
    """The frame's lens distortion from nerfstudio's / instant-ngp's keys."""
    def coef(key: str) -> float:
        v = get(key)
        return 0.0 if v is None else _num(v, key, where)

    model = get("camera_model")
    model = "OPENCV_FISHEYE" if model is None and get("is_fisheye") else model
    model = str(model).upper() if model is not None else "OPENCV"
    if model in ("PINHOLE", "SIMPLE_PINHOLE"):
        return NO_DISTORTION
    if model == "OPENCV":
        if coef("k4") != 0.0:
            raise ValueError(f"{where}: k4 (an r^8 term) is not supported for camera_model "
                             "OPENCV")
        d = Distortion("opencv", (coef("k1"), coef("k2"), coef("p1"), coef("p2"), coef("k3")))
    elif model == "OPENCV_FISHEYE":
        if coef("p1") != 0.0 or coef("p2") != 0.0:
            raise ValueError(f"{where}: p1/p2 (tangential) are not part of camera_model "
                             "OPENCV_FISHEYE")
        d = Distortion("fisheye", (coef("k1"), coef("k2"), coef("k3"), coef("k4")))
    else:
        raise ValueError(f"{where}: camera_model {model!r} is not supported (OPENCV, "
                         "OPENCV_FISHEYE, PINHOLE)")
    return NO_DISTORTION if d.is_identity else d


def read_ply_points(path: PathLike) -> tuple[Tensor, Tensor]:
    """Points of a ``.ply`` point cloud: (xyz [P, 3] float32, rgb [P, 3] float32 in [0, 1];
    grey 0.5 when the file has no colours)."""
    from plyfile import PlyData

    p = Path(path)
    try:
        ply = PlyData.read(str(p))
        v = ply["vertex"]
        xyz = np.stack([np.asarray(v[k], dtype=np.float64) for k in ("x", "y", "z")], axis=1)
    except (KeyError, ValueError, OSError) as exc:
        raise ValueError(f"{p}: not a point cloud with x, y, z vertices ({exc})") from exc
    names = set(v.data.dtype.names or ())
    if {"red", "green", "blue"} <= names:
        rgb = np.stack([np.asarray(v[k], dtype=np.float64) for k in ("red", "green", "blue")],
                       axis=1) / 255.0
    else:
        rgb = np.full_like(xyz, 0.5)
    ok = np.isfinite(xyz).all(axis=1)
    return (torch.from_numpy(xyz[ok].astype(np.float32)),
            torch.from_numpy(np.clip(rgb[ok], 0, 1).astype(np.float32)))


def _norm_name(name: str) -> str:
    return os.path.normpath(name.removeprefix("./"))


def _split_names(meta: dict[str, Any], p: Path) -> dict[str, Split]:
    """The split of each file named by the file's ``*_filenames`` lists (nerfstudio's): a
    named test split wins over the validation one."""
    out: dict[str, Split] = {}
    for key, tag in (("train_filenames", "train"), ("val_filenames", "test"),
                     ("test_filenames", "test")):
        names = meta.get(key)
        if names is None:
            continue
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise ValueError(f"{p}: {key} must be a list of file paths")
        if key == "val_filenames" and meta.get("test_filenames"):
            continue
        for n in names:
            out[_norm_name(n)] = tag  # type: ignore[assignment]
    return out


def _frame_pose(matrix: Any, where: str) -> Tensor:
    """A frame's ``transform_matrix`` (3x4 or 4x4, OpenGL axes) as a camera-to-world pose in
    OpenCV axes [4, 4] (float32)."""
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: transform_matrix is not numeric") from None
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        raise ValueError(f"{where}: transform_matrix must be 4x4, got shape {list(m.shape)}")
    if not np.isfinite(m).all():
        raise ValueError(f"{where}: transform_matrix has non-finite values")
    return opengl_to_opencv_c2w(torch.from_numpy(m)).float()


def _frame_intrinsics(get: Callable[[str], Any], where: str, img_path: Path) -> Intrinsics:
    """A frame's intrinsics as the file gives them (``get``: the frame's key, else the
    file's): the size from ``w``/``h`` or the image, the focal length from ``fl_x``/``fl_y``
    or the field of view, the principal point from ``cx``/``cy`` or the centre."""
    w, h = get("w"), get("h")
    if w is None or h is None:
        width, height = image_size(img_path)
    else:
        width, height = int(_num(w, "w", where)), int(_num(h, "h", where))
    if get("fl_x") is not None:
        fx = _num(get("fl_x"), "fl_x", where)
        fy = _num(get("fl_y") if get("fl_y") is not None else fx, "fl_y", where)
    elif get("camera_angle_x") is not None:
        ax = _num(get("camera_angle_x"), "camera_angle_x", where)
        if not 0 < ax < math.pi:
            raise ValueError(f"{where}: camera_angle_x must be in (0, pi) radians, got {ax}")
        fx = 0.5 * width / math.tan(0.5 * ax)
        if get("camera_angle_y") is not None:
            ay = _num(get("camera_angle_y"), "camera_angle_y", where)
            fy = 0.5 * height / math.tan(0.5 * ay)
        else:
            fy = fx
    else:
        raise ValueError(f"{where}: no 'camera_angle_x' (or 'fl_x') for the focal length")
    cx = _num(get("cx"), "cx", where) if get("cx") is not None else width / 2.0
    cy = _num(get("cy"), "cy", where) if get("cy") is not None else height / 2.0
    try:
        return Intrinsics(fx, fy, cx, cy, width, height)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from exc


def load_transforms(
    path: PathLike,
    *,
    background: Sequence[float] = (1.0, 1.0, 1.0),
    downscale: float = 1,
    load_images: bool = True,
    depth_scale: float = 1000.0,
    quiet: bool = False,
) -> TransformsCapture:
    """Read a ``transforms*.json`` file of any of the three dialects (module docstring).

    Args:
        path: the JSON file; ``frames[].file_path`` is relative to its folder, with or without
            an extension (``.png`` is tried first).
        background: RGB in [0, 1] on which images with an alpha channel or a mask are
            composited (NeRF-synthetic convention: white).
        downscale: divide the image size by this factor (intrinsics follow).
        load_images: read the pixels (else ``View.image`` is None; the size still comes from
            the JSON's ``w``/``h`` or the image header).
        depth_scale: a frame's optional ``depth_file_path`` image is divided by this to give
            depth in scene units (``.npy`` depth files are taken as is).
        quiet: log nothing (a probe before the real load).

    Raises:
        ValueError: malformed JSON, missing keys, a non-4x4 or non-rigid transform, an
            unsupported camera model (naming the file and frame index).
        FileNotFoundError: no frame has its image (and depth); a named mask or ply file is
            missing.
    """
    p = Path(path)
    try:
        meta = json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{p}: invalid JSON at line {exc.lineno}: {exc.msg}") from exc
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise ValueError(f"{p}: expected an object with a 'frames' list")
    base = p.parent
    split_names = _split_names(meta, p)
    views: list[View] = []
    split: list[Split | None] = []
    skipped: list[str] = []
    dists: dict[Distortion, None] = {}
    for i, fr in enumerate(meta["frames"]):
        where = f"{p}: frames[{i}]"
        if not isinstance(fr, dict):
            raise ValueError(f"{where}: expected an object")
        if "file_path" not in fr or "transform_matrix" not in fr:
            raise ValueError(f"{where}: needs 'file_path' and 'transform_matrix'")

        def get(key: str, fr: dict[str, Any] = fr) -> Any:
            return fr.get(key, meta.get(key))

        c2w = _frame_pose(fr["transform_matrix"], where)
        dist = _distortion(get, where)
        img_path = _find_frame_image(base, str(fr["file_path"]))
        dpath = base / str(fr["depth_file_path"]) if fr.get("depth_file_path") else None
        if img_path is None or (dpath is not None and not dpath.is_file()):
            skipped.append(str(fr["file_path"]) if img_path is None else str(dpath))
            continue
        raw = _frame_intrinsics(get, where, img_path)
        width, height = raw.width, raw.height
        try:
            cam = Camera.from_intrinsics(c2w, pinhole_for(raw, dist))
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from exc
        if not dist.is_identity:
            dists[dist] = None
        tw, th = target_size(width, height, downscale)
        if (tw, th) != (width, height):
            cam = cam.with_resolution(tw, th)
        mask_path = None
        if fr.get("mask_path"):
            mask_path = base / str(fr["mask_path"])
            if not mask_path.is_file():
                raise FileNotFoundError(f"{where}: mask {mask_path} not found")
        image = alpha = None
        if load_images:
            image, alpha = load_capture_image(img_path, raw, dist, (tw, th),
                                              background=background, mask_path=mask_path)
        depth = None
        if dpath is not None:
            if not dist.is_identity:
                raise ValueError(f"{where}: depth maps of a distorted camera are not supported "
                                 "(undistort the capture first)")
            depth = load_depth(dpath, depth_scale, (tw, th))
        name = str(fr["file_path"])
        views.append(View(name=name, camera=cam, image=image, depth=depth, alpha=alpha))
        split.append(split_names.get(_norm_name(name)) if split_names else None)
    if skipped and not quiet:
        log.warning("%s: %d of %d frames have no image (or no depth file, where they name one) "
                    "and were skipped (first missing: %s)", p, len(skipped), len(meta["frames"]),
                    skipped[0])
    if not views and skipped:
        raise FileNotFoundError(f"{p}: none of the {len(skipped)} frames has its image (and "
                                f"depth) (first missing: {skipped[0]!r}, under {base})")
    points = colors = None
    if meta.get("ply_file_path"):
        ply = base / str(meta["ply_file_path"])
        if not ply.is_file():
            raise FileNotFoundError(f"{p}: ply_file_path {ply} not found")
        points, colors = read_ply_points(ply)
    for d in dists if not quiet else ():
        log.info("%s: images with distortion %s undistorted to a pinhole camera", p,
                 d.describe())
    return TransformsCapture(views=views, split=split, points=points, colors=colors,
                             skipped=skipped, distortions=[d.describe() for d in dists])


def load_transforms_json(
    path: PathLike,
    *,
    background: Sequence[float] = (1.0, 1.0, 1.0),
    downscale: float = 1,
    load_images: bool = True,
    depth_scale: float = 1000.0,
) -> list[View]:
    """The views of :func:`load_transforms` (same arguments), in file order."""
    return load_transforms(path, background=background, downscale=downscale,
                           load_images=load_images, depth_scale=depth_scale).views
