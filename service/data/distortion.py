"""Lens distortion of captured images, and their undistortion to a pinhole camera.

Two families cover the camera models of COLMAP, instant-ngp and nerfstudio:

- ``opencv``: OpenCV's rational model on normalised coordinates (x, y) = (X/Z, Y/Z),
  r² = x² + y², coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]):
  x_d = x·(1 + k1 r² + k2 r⁴ + k3 r⁶)/(1 + k4 r² + k5 r⁴ + k6 r⁶) + 2 p1 x y + p2 (r² + 2x²),
  y_d = y·(same) + p1 (r² + 2y²) + 2 p2 x y.
- ``fisheye``: OpenCV's fisheye (equidistant) model, coefficients (k1, k2, k3, k4):
  θ = atan(r), θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸), (x_d, y_d) = (θ_d / r) (x, y).

A pixel is u = fx·x_d + cx, v = fy·y_d + cy (pixel centres at integer + 0.5 in the project's
convention; the maps below use OpenCV's integer-centred grid, shifted by half a pixel).

:func:`undistort_image` resamples an image to a pinhole camera with the same principal point
and the focal length scaled by the smallest factor that keeps every pixel of the new image
inside the photograph (no blank border, like ``colmap image_undistorter``), using OpenCV's
undistortion maps (``cv2.initUndistortRectifyMap`` / ``cv2.fisheye.initUndistortRectifyMap``).
:func:`distort_normalized` is the reference formula, in float64, that the maps are tested
against.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from agilegs.service.nbv import Intrinsics

__all__ = [
    "Distortion",
    "colmap_distortion",
    "distort_normalized",
    "pinhole_for",
    "undistort_image",
]

DistortionKind = Literal["none", "opencv", "fisheye"]


@dataclass(frozen=True)
class Distortion:
    """A lens distortion: ``kind`` and its coefficients (see the module docstring)."""

    kind: DistortionKind = "none"
    coeffs: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        n = len(self.coeffs)
        if self.kind == "opencv" and n not in (4, 5, 8):
            raise ValueError(f"opencv distortion takes 4, 5 or 8 coefficients, got {n}")
        if self.kind == "fisheye" and n != 4:
            raise ValueError(f"fisheye distortion takes 4 coefficients, got {n}")
        if self.kind == "none" and n:
            raise ValueError("'none' distortion takes no coefficients")
        if not all(math.isfinite(c) for c in self.coeffs):
            raise ValueError(f"distortion coefficients must be finite, got {self.coeffs}")

    @property
    def is_identity(self) -> bool:
        return self.kind == "none" or all(c == 0.0 for c in self.coeffs)

    def describe(self) -> str:
        return "none" if self.is_identity else f"{self.kind} {[round(c, 6) for c in self.coeffs]}"


NO_DISTORTION = Distortion()


def colmap_distortion(model: str, params: tuple[float, ...]) -> Distortion:
    """The distortion of a COLMAP camera (``params`` in COLMAP's order for ``model``).

    Raises:
        ValueError: a model without an equivalent here (FOV, THIN_PRISM_FISHEYE), naming it.
    """
    p = tuple(float(v) for v in params)
    if model in ("SIMPLE_PINHOLE", "PINHOLE"):
        return NO_DISTORTION
    if model == "SIMPLE_RADIAL":
        return Distortion("opencv", (p[3], 0.0, 0.0, 0.0))
    if model == "RADIAL":
        return Distortion("opencv", (p[3], p[4], 0.0, 0.0))
    if model == "OPENCV":
        return Distortion("opencv", p[4:8])
    if model == "FULL_OPENCV":  # k1 k2 p1 p2 k3 k4 k5 k6: OpenCV's own order
        return Distortion("opencv", p[4:12])
    if model == "SIMPLE_RADIAL_FISHEYE":
        return Distortion("fisheye", (p[3], 0.0, 0.0, 0.0))
    if model == "RADIAL_FISHEYE":
        return Distortion("fisheye", (p[3], p[4], 0.0, 0.0))
    if model == "OPENCV_FISHEYE":
        return Distortion("fisheye", p[4:8])
    raise ValueError(
        f"camera model {model} is not supported (supported: SIMPLE_PINHOLE, PINHOLE, "
        "SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV, SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE, "
        "OPENCV_FISHEYE); undistort the images first (colmap image_undistorter)"
    )


def distort_normalized(x: np.ndarray, y: np.ndarray, dist: Distortion) -> tuple[np.ndarray,
                                                                                np.ndarray]:
    """Reference formula (float64): distorted normalised coordinates of (x, y), same shape."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if dist.is_identity:
        return x.copy(), y.copy()
    c = list(dist.coeffs)
    r2 = x * x + y * y
    if dist.kind == "opencv":
        k1, k2, p1, p2 = c[:4]
        k3 = c[4] if len(c) > 4 else 0.0
        k4, k5, k6 = c[5:8] if len(c) == 8 else (0.0, 0.0, 0.0)
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return xd, yd
    k1, k2, k3, k4 = c
    r = np.sqrt(r2)
    theta = np.arctan(r)
    t2 = theta * theta
    theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    scale = np.where(r > 1e-12, theta_d / np.maximum(r, 1e-12), 1.0)
    return x * scale, y * scale


def _border_inside(intr: Intrinsics, dist: Distortion, s: float, n: int = 64) -> bool:
    """Whether every border pixel of the pinhole image with focal × ``s`` comes from inside
    the photograph, along rays on which the distortion is monotonic (no fold: a polynomial
    model turns back beyond its valid radius, and a folded ray lands inside again)."""
    w, h = intr.width, intr.height
    t = np.linspace(0.0, 1.0, n)
    us = np.concatenate([t * w, t * w, np.zeros(n), np.full(n, w)])
    vs = np.concatenate([np.zeros(n), np.full(n, h), t * h, t * h])
    x = (us - intr.cx) / (intr.fx * s)
    y = (vs - intr.cy) / (intr.fy * s)
    xd, yd = distort_normalized(x, y, dist)
    ud = intr.fx * xd + intr.cx
    vd = intr.fy * yd + intr.cy
    tol = 1e-6
    if not np.all((ud >= -tol) & (ud <= w + tol) & (vd >= -tol) & (vd <= h + tol)):
        return False
    # from the principal point out to each border point: the distorted radius must grow
    frac = np.linspace(0.0, 1.0, 4 * n)[:, None]
    rx, ry = frac * x[None], frac * y[None]
    rxd, ryd = distort_normalized(rx, ry, dist)
    radius = np.hypot(rxd, ryd)
    rays = np.hypot(x, y) > 0  # a border point at the principal point has no ray
    return bool(np.all(np.diff(radius[:, rays], axis=0) > 0.0))


@functools.lru_cache(maxsize=64)
def pinhole_for(intr: Intrinsics, dist: Distortion) -> Intrinsics:
    """The pinhole camera an image of ``intr`` with ``dist`` is undistorted to: same size and
    principal point, focal lengths × the smallest factor s (bisection to 1e-4) for which the
    whole new image lies inside the photograph. ``intr`` itself when there is no distortion."""
    if dist.is_identity:
        return intr
    lo, hi = 0.05, 1.0
    while not _border_inside(intr, dist, hi):
        lo, hi = hi, hi * 2.0
        if hi > 64:
            raise ValueError(f"distortion {dist.describe()}: no pinhole view of the image "
                             "lies inside it")
    if _border_inside(intr, dist, lo):
        hi = lo
    for _ in range(60):
        if hi - lo < 1e-4 * hi:
            break
        mid = 0.5 * (lo + hi)
        if _border_inside(intr, dist, mid):
            hi = mid
        else:
            lo = mid
    return Intrinsics(intr.fx * hi, intr.fy * hi, intr.cx, intr.cy, intr.width, intr.height)


@functools.lru_cache(maxsize=2)
def _maps(intr: Intrinsics, dist: Distortion) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's undistortion maps (2 × [H, W] float32, 100 MB for a 12-megapixel photograph:
    the last two are kept, enough for a capture with one camera)."""
    import cv2

    new = pinhole_for(intr, dist)
    # OpenCV's pixel centres are integers; the project's are at +0.5
    k = np.array([[intr.fx, 0, intr.cx - 0.5], [0, intr.fy, intr.cy - 0.5], [0, 0, 1]])
    nk = np.array([[new.fx, 0, new.cx - 0.5], [0, new.fy, new.cy - 0.5], [0, 0, 1]])
    d = np.asarray(dist.coeffs, dtype=np.float64)
    size = (intr.width, intr.height)
    if dist.kind == "fisheye":
        m1, m2 = cv2.fisheye.initUndistortRectifyMap(k, d.reshape(4, 1), np.eye(3), nk, size,
                                                     cv2.CV_32FC1)
    else:
        m1, m2 = cv2.initUndistortRectifyMap(k, d, np.eye(3), nk, size, cv2.CV_32FC1)
    return m1, m2


def undistort_image(image: np.ndarray, intr: Intrinsics,
                    dist: Distortion) -> tuple[np.ndarray, Intrinsics]:
    """Resample a photograph of ``intr`` with ``dist`` to :func:`pinhole_for`'s camera.

    Args:
        image: [H, W, C] uint8 or float32 (C = 1, 3 or 4), H and W the camera's.
        intr: the photograph's intrinsics (pinhole part).
        dist: its distortion.

    Returns:
        (the undistorted image [H, W, C], same dtype, bilinear; its pinhole intrinsics).
    """
    import cv2

    if image.shape[0] != intr.height or image.shape[1] != intr.width:
        raise ValueError(f"image of {image.shape[1]}x{image.shape[0]} for a camera of "
                         f"{intr.width}x{intr.height}")
    if dist.is_identity:
        return image, intr
    m1, m2 = _maps(intr, dist)
    out = cv2.remap(image, m1, m2, interpolation=cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    if out.ndim == 2 and image.ndim == 3:
        out = out[..., None]
    return out, pinhole_for(intr, dist)
