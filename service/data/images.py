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

import numpy as np
import torch
from torch import Tensor

from agilegs.service.nbv.camera import Camera

log = logging.getLogger(__name__)

PathLike = str | os.PathLike[str]

__all__ = ["PathLike", "View", "image_size", "load_depth", "load_image", "target_size"]


@dataclass
class View:
    """One posed image.

    Attributes:
        name: image name (file name relative to the image folder, or the frame's file_path).
        camera: pinhole camera, c2w in OpenCV axes.
        image: RGB [H, W, 3] float32 in [0, 1], or None when images were not loaded.
        depth: depth along the optical axis (camera z) [H, W], 0 where unknown, or None.
    """

    name: str
    camera: Camera
    image: Tensor | None = None
    depth: Tensor | None = None


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
        with Image.open(p) as im:
            im.load()
            has_alpha = im.mode in ("RGBA", "LA", "PA") or (
                im.mode == "P" and "transparency" in im.info
            )
            img: Image.Image = im
            if im.mode in ("I;16", "I;16B", "I;16L", "I"):  # 16-bit grey
                grey = np.asarray(im, dtype=np.float32) / 65535.0
                img = Image.fromarray(np.clip(grey * 255.0 + 0.5, 0, 255).astype(np.uint8))
            img = img.convert("RGBA" if has_alpha else "RGB")
            if size is not None and img.size != (size[0], size[1]):
                img = img.resize((size[0], size[1]), Image.Resampling.LANCZOS)
            arr = np.asarray(img, dtype=np.float32) / 255.0
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise ValueError(f"{p}: cannot read image ({exc})") from exc
    if has_alpha:
        bg = np.asarray(background, dtype=np.float32).reshape(1, 1, 3)
        a = arr[..., 3:4]
        arr = arr[..., :3] * a + bg * (1.0 - a)
    return torch.from_numpy(np.ascontiguousarray(arr[..., :3]))


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
