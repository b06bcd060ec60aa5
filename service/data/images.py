"""A posed view of an image set (:class:`View`) and reading its image and depth files.

``downscale`` divides the image size (rounded to the nearest integer, at least 1) and scales
the intrinsics to match; an image whose file already has the reduced size (e.g. Mip-NeRF 360's
``images_4``) is used as is, any other size is resized with PIL.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from agilegs.service.nbv import Camera, Intrinsics

from .distortion import Distortion

log = logging.getLogger(__name__)

PathLike = str | os.PathLike[str]

__all__ = [
    "PathLike",
    "View",
    "image_size",
    "load_capture_image",
    "load_depth",
    "load_image",
    "target_size",
]


@dataclass
class View:
    """One posed image.

    Attributes:
        name: image name (file name relative to the image folder, or the frame's file_path).
        camera: pinhole camera, c2w in OpenCV axes.
        image: RGB [H, W, 3] float32 in [0, 1], or None when images were not loaded.
        depth: depth along the optical axis (camera z) [H, W], 0 where unknown, or None.
        alpha: coverage [H, W] in [0, 1] of the image's alpha channel and/or its mask (1: the
            pixel shows the scene; the image is composited on the background by it), or None
            when the image has neither.
    """

    name: str
    camera: Camera
    image: Tensor | None = None
    depth: Tensor | None = None
    alpha: Tensor | None = None


# ----------------------------------------------------------------------------- images
def target_size(width: int, height: int, downscale: float) -> tuple[int, int]:
    if not (downscale > 0 and math.isfinite(downscale)):
        raise ValueError(f"downscale must be a positive finite number, got {downscale}")
    return max(1, int(round(width / downscale))), max(1, int(round(height / downscale)))


def load_image(
    path: PathLike,
    *,
    background: Sequence[float] = (1.0, 1.0, 1.0),
    size: tuple[int, int] | None = None,
) -> Tensor:
    """Read an image with PIL as RGB float32 [H, W, 3] in [0, 1].

    Args:
        path: image file.
        background: RGB in [0, 1] an alpha channel is composited on.
        size: (width, height) to resize to when the file has another size.
    """
    from PIL import Image

    p = Path(path)
    try:
        img = _decoded(p)
        if size is not None and img.size != (size[0], size[1]):
            img = img.resize((size[0], size[1]), Image.Resampling.LANCZOS)
        arr = np.asarray(img, dtype=np.float32) / 255.0
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise ValueError(f"{p}: cannot read image ({exc})") from exc
    has_alpha = arr.shape[-1] == 4
    if has_alpha:
        bg = np.asarray(background, dtype=np.float32).reshape(1, 1, 3)
        a = arr[..., 3:4]
        arr = arr[..., :3] * a + bg * (1.0 - a)
    return torch.from_numpy(np.ascontiguousarray(arr[..., :3]))


def _decoded(path: Path) -> Any:
    """An image file decoded with PIL as an "RGB" image, or "RGBA" where it has an alpha
    channel (16-bit grey scaled to 8 bits)."""
    from PIL import Image

    with Image.open(path) as im:
        im.load()
        has_alpha = im.mode in ("RGBA", "LA", "PA") or (
            im.mode == "P" and "transparency" in im.info
        )
        img: Image.Image = im
        if im.mode in ("I;16", "I;16B", "I;16L", "I"):  # 16-bit grey
            grey = np.asarray(im, dtype=np.float32) / 65535.0
            img = Image.fromarray(np.clip(grey * 255.0 + 0.5, 0, 255).astype(np.uint8))
        return img.convert("RGBA" if has_alpha else "RGB")


def _read_u8(path: Path) -> np.ndarray:
    """An image file as uint8 [H, W, 3] or [H, W, 4] (with its alpha channel)."""
    try:
        return np.asarray(_decoded(path), dtype=np.uint8)
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise ValueError(f"{path}: cannot read image ({exc})") from exc


def _read_mask_u8(path: Path, size: tuple[int, int]) -> np.ndarray:
    """A mask file (0: ignore, non-zero: keep; the first channel of a colour file) as uint8
    [H, W] in {0, 255} at ``size`` = (width, height) (nearest neighbour)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            m = np.asarray(im.convert("L").resize(size, Image.Resampling.NEAREST)
                           if im.size != size else im.convert("L"))
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise ValueError(f"{path}: cannot read mask ({exc})") from exc
    return np.where(m > 127, 255, 0).astype(np.uint8)


def load_capture_image(
    path: PathLike,
    intrinsics: Intrinsics,
    distortion: Distortion,
    size: tuple[int, int],
    *,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    mask_path: PathLike | None = None,
) -> tuple[Tensor, Tensor | None]:
    """Read a captured photograph as the pinhole image of :func:`pinhole_for` at ``size``.

    The file may be smaller than ``intrinsics`` say (e.g. Mip-NeRF 360's ``images_4``): the
    intrinsics are scaled to the file's size first. The image (and its alpha channel and
    mask) is undistorted at the file's resolution, then resized to ``size`` (PIL LANCZOS) and
    composited on ``background`` by its alpha × mask.

    Args:
        path: image file.
        intrinsics: the photograph's pinhole part (the size the poses were solved at).
        distortion: its lens distortion.
        size: (width, height) of the result.
        background: RGB in [0, 1] where alpha × mask < 1.
        mask_path: optional mask file (0: not the scene).

    Returns:
        (RGB [H, W, 3] float32 in [0, 1], alpha × mask [H, W] float32 or None when the image
        has neither).
    """
    from PIL import Image

    from .distortion import undistort_image

    p = Path(path)
    arr = _read_u8(p)
    fh, fw = arr.shape[:2]
    intr = intrinsics
    if (fw, fh) != (intr.width, intr.height):
        intr = intr.scaled(fw, fh)
    if mask_path is not None:
        m = _read_mask_u8(Path(mask_path), (fw, fh))
        if arr.shape[2] == 4:
            m = ((arr[..., 3].astype(np.uint16) * m) // 255).astype(np.uint8)
        arr = np.concatenate([arr[..., :3], m[..., None]], axis=2)
    has_alpha = arr.shape[2] == 4
    arr, _ = undistort_image(np.ascontiguousarray(arr), intr, distortion)
    img = Image.fromarray(arr, "RGBA" if has_alpha else "RGB")
    if img.size != (size[0], size[1]):
        img = img.resize((size[0], size[1]), Image.Resampling.LANCZOS)
    out = np.asarray(img, dtype=np.float32) / 255.0
    alpha = None
    if has_alpha:
        bg = np.asarray(background, dtype=np.float32).reshape(1, 1, 3)
        a = out[..., 3:4]
        out = out[..., :3] * a + bg * (1.0 - a)
        alpha = torch.from_numpy(np.ascontiguousarray(a[..., 0]))
    return torch.from_numpy(np.ascontiguousarray(out[..., :3])), alpha


def image_size(path: Path) -> tuple[int, int]:
    from PIL import Image

    try:
        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except OSError as exc:
        raise ValueError(f"{path}: cannot read image ({exc})") from exc


def load_depth(path: Path, scale: float, size: tuple[int, int] | None) -> Tensor:
    """Depth map [H, W] from .npy (float, in scene units) or an image divided by ``scale``."""
    if path.suffix.lower() == ".npy":
        arr = np.load(path).astype(np.float32)
        if arr.ndim == 3 and arr.shape[-1] == 1:
            arr = arr[..., 0]
        if arr.ndim != 2:
            raise ValueError(f"{path}: depth must be a 2D array, got shape {arr.shape}")
    else:
        from PIL import Image

        with Image.open(path) as im:
            arr = np.asarray(im, dtype=np.float32)
        if arr.ndim == 3:
            arr = arr[..., 0]
        arr = arr / float(scale)
    t = torch.from_numpy(np.ascontiguousarray(arr))
    if size is not None and (t.shape[1], t.shape[0]) != tuple(size):
        # nearest neighbour: depth must not be blended across edges
        t = torch.nn.functional.interpolate(t[None, None], size=(size[1], size[0]), mode="nearest")[
            0, 0
        ]
    return t
