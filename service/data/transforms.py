"""NeRF-synthetic ``transforms.json`` image sets (Blender; also the instant-ngp variant with
``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``).

``transform_matrix`` is camera-to-world in OpenGL axes (x right, y up, z backward); it is
converted to the project's OpenCV axes (x right, y down, z forward) by flipping the camera's y
and z axes (negating columns 1 and 2 of the rotation). RGBA images are composited on
``background``. Malformed files raise ``ValueError`` naming the file and the frame.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from agilegs.service.nbv.camera import Camera, Intrinsics

from .images import PathLike, View, image_size, load_depth, load_image, target_size

log = logging.getLogger(__name__)

__all__ = ["load_transforms_json", "opengl_to_opencv_c2w"]


def opengl_to_opencv_c2w(c2w: Tensor) -> Tensor:
    """Camera-to-world [..., 4, 4] in OpenGL/Blender camera axes to OpenCV camera axes."""
    out = c2w.clone()
    out[..., :3, 1:3] = -out[..., :3, 1:3]
    return out


def _find_frame_image(base: Path, file_path: str) -> Path:
    p = (base / file_path).resolve() if not os.path.isabs(file_path) else Path(file_path)
    if p.suffix and p.is_file():
        return p
    for ext in (".png", ".jpg", ".jpeg", ".JPG", ".PNG", ".exr"):
        q = p.with_name(p.name + ext)
        if q.is_file():
            return q
    if p.is_file():
        return p
    raise FileNotFoundError(f"image {file_path!r} not found under {base} (tried common extensions)")


def _num(value: Any, what: str, where: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: {what} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{where}: {what} must be finite, got {v}")
    return v


def load_transforms_json(
    path: PathLike,
    *,
    background: Sequence[float] = (1.0, 1.0, 1.0),
    downscale: float = 1,
    load_images: bool = True,
    depth_scale: float = 1000.0,
) -> list[View]:
    """Read a NeRF-synthetic ``transforms_*.json`` file.

    Args:
        path: the JSON file; ``frames[].file_path`` is relative to its folder, with or without
            an extension (``.png`` is tried first).
        background: RGB in [0, 1] on which RGBA images are composited (NeRF-synthetic
            convention: white).
        downscale: divide the image size by this factor (intrinsics follow).
        load_images: read the pixels (else ``View.image`` is None; the size still comes from
            the JSON's ``w``/``h`` or the image header).
        depth_scale: a frame's optional ``depth_file_path`` image is divided by this to give
            depth in scene units (``.npy`` depth files are taken as is).

    Returns:
        One :class:`View` per frame, in file order, c2w in OpenCV axes.

    Raises:
        ValueError: malformed JSON, missing keys, a non-4x4 or non-rigid transform (naming the
            file and frame index).
        FileNotFoundError: a frame's image is missing.
    """
    p = Path(path)
    try:
        meta = json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{p}: invalid JSON at line {exc.lineno}: {exc.msg}") from exc
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise ValueError(f"{p}: expected an object with a 'frames' list")
    base = p.parent
    views: list[View] = []
    for i, fr in enumerate(meta["frames"]):
        where = f"{p}: frames[{i}]"
        if not isinstance(fr, dict):
            raise ValueError(f"{where}: expected an object")
        if "file_path" not in fr or "transform_matrix" not in fr:
            raise ValueError(f"{where}: needs 'file_path' and 'transform_matrix'")

        def get(key: str, fr: dict[str, Any] = fr) -> Any:
            return fr.get(key, meta.get(key))

        try:
            m = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{where}: transform_matrix is not numeric") from None
        if m.shape == (3, 4):
            m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
        if m.shape != (4, 4):
            raise ValueError(f"{where}: transform_matrix must be 4x4, got shape {list(m.shape)}")
        if not np.isfinite(m).all():
            raise ValueError(f"{where}: transform_matrix has non-finite values")
        c2w = opengl_to_opencv_c2w(torch.from_numpy(m)).float()
        img_path = _find_frame_image(base, str(fr["file_path"]))
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
            cam = Camera.from_intrinsics(c2w, Intrinsics(fx, fy, cx, cy, width, height))
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from exc
        tw, th = target_size(width, height, downscale)
        if (tw, th) != (width, height):
            cam = cam.with_resolution(tw, th)
        image = None
        if load_images:
            image = load_image(img_path, background=background, size=(tw, th))
        depth = None
        if fr.get("depth_file_path"):
            dpath = base / str(fr["depth_file_path"])
            if not dpath.is_file():
                raise FileNotFoundError(f"{where}: depth file {dpath} not found")
            depth = load_depth(dpath, depth_scale, (tw, th))
        name = str(fr["file_path"])
        views.append(View(name=name, camera=cam, image=image, depth=depth))
    return views
