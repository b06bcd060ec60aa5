"""Pinhole cameras with OpenCV axes (x right, y down, z forward).

A camera holds its intrinsics (fx, fy, cx, cy, width, height, in pixels; pixel centres at
+0.5, so the centre of pixel (0, 0) is (0.5, 0.5)) and its camera-to-world pose ``c2w`` [4,4].
A ``c2w`` that requires grad makes every render through this camera differentiable in the pose.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor

from agilegs.config.geometry import ORTHONORMAL_ATOL

from .errors import InputError


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        for name in ("fx", "fy"):
            v = float(getattr(self, name))
            if not (v > 0 and v < float("inf")):
                raise ValueError(f"{name} must be a positive finite focal length, got {v}")
        for name in ("cx", "cy"):
            v = float(getattr(self, name))
            if v != v or abs(v) == float("inf"):
                raise ValueError(f"{name} must be finite, got {v}")
        for name in ("width", "height"):
            v = getattr(self, name)
            if int(v) != v or int(v) < 1:
                raise ValueError(f"{name} must be a positive integer, got {v}")

    @classmethod
    def from_fov(cls, fov_x_deg: float, width: int, height: int) -> Intrinsics:
        """Square pixels, principal point at the image centre, horizontal field of view."""
        import math

        fx = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
        return cls(fx=fx, fy=fx, cx=width / 2, cy=height / 2, width=width, height=height)

    def scaled(self, width: int, height: int) -> Intrinsics:
        """The same field of view at another resolution."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, width, height)


ORTHONORMAL_TOL = ORTHONORMAL_ATOL + 1e-5
"""Largest ``max |R^T R - I|`` :func:`check_pose` accepts: the wire's tolerance
(:data:`agilegs.config.geometry.ORTHONORMAL_ATOL`) plus the rounding of such a pose to float32,
so that a pose the wire accepted is never refused here."""


def check_pose(c2w: Tensor, name: str = "c2w", atol: float = 1e-4) -> None:
    """Raise :class:`InputError` (a ValueError naming ``name``) unless ``c2w`` [..., 4, 4] is
    a finite rigid transform: last row [0, 0, 0, 1] within ``atol``, rotation orthonormal
    within :data:`ORTHONORMAL_TOL` (or ``atol`` if larger), ``det R > 0``."""
    if c2w.shape[-2:] != (4, 4):
        raise InputError(name, f"{name} must have shape [..., 4, 4], got {list(c2w.shape)}")
    c = c2w.detach()
    if not torch.isfinite(c).all():
        raise InputError(name, f"{name} contains NaN or infinite values")
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=c.dtype, device=c.device)
    if not torch.allclose(c[..., 3, :], bottom.expand_as(c[..., 3, :]), atol=atol):
        raise InputError(name, f"{name} last row must be [0, 0, 0, 1]")
    r = c[..., :3, :3]
    eye = torch.eye(3, dtype=c.dtype, device=c.device)
    err = (r.transpose(-1, -2) @ r - eye).abs().amax() if r.numel() else torch.tensor(0.0)
    tol = max(atol, ORTHONORMAL_TOL)
    if float(err) > tol:
        raise InputError(name, f"{name} rotation is not orthonormal (max |R^T R - I| = "
                               f"{float(err):.3g})")
    if r.numel() and (torch.linalg.det(r) < 0).any():
        raise InputError(name, f"{name} rotation has determinant -1 (a reflection), not a rotation")


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: intrinsics plus a camera-to-world pose ``c2w`` [4, 4]."""

    c2w: Tensor
    intrinsics: Intrinsics

    @classmethod
    def from_c2w(
        cls,
        c2w: Tensor,
        *,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        width: int,
        height: int,
        validate: bool = True,
    ) -> Camera:
        """Camera from a camera-to-world matrix [4, 4] (OpenCV axes) and pixel intrinsics."""
        if validate:
            check_pose(c2w)
        return cls(c2w=c2w, intrinsics=Intrinsics(fx, fy, cx, cy, int(width), int(height)))

    @classmethod
    def from_intrinsics(cls, c2w: Tensor, intrinsics: Intrinsics, validate: bool = True) -> Camera:
        if validate:
            check_pose(c2w)
        return cls(c2w=c2w, intrinsics=intrinsics)

    # convenience accessors
    @property
    def fx(self) -> float:
        return self.intrinsics.fx

    @property
    def fy(self) -> float:
        return self.intrinsics.fy

    @property
    def cx(self) -> float:
        return self.intrinsics.cx

    @property
    def cy(self) -> float:
        return self.intrinsics.cy

    @property
    def width(self) -> int:
        return self.intrinsics.width

    @property
    def height(self) -> int:
        return self.intrinsics.height

    @property
    def rotation(self) -> Tensor:
        """Camera-to-world rotation [3, 3]; its columns are the camera axes in world."""
        return self.c2w[:3, :3]

    @property
    def position(self) -> Tensor:
        """Camera centre in world [3]."""
        return self.c2w[:3, 3]

    @property
    def forward(self) -> Tensor:
        """Optical axis (camera +z) in world [3]."""
        return self.c2w[:3, 2]

    @property
    def w2c(self) -> Tensor:
        """World-to-camera [4, 4], differentiable in ``c2w`` (R^T, -R^T t)."""
        r = self.c2w[:3, :3]
        t = self.c2w[:3, 3]
        rt = r.transpose(0, 1)
        top = torch.cat([rt, -(rt @ t)[:, None]], dim=1)
        bottom = torch.zeros(1, 4, dtype=self.c2w.dtype, device=self.c2w.device)
        bottom[0, 3] = 1.0
        return torch.cat([top, bottom], dim=0)

    def with_pose(self, c2w: Tensor) -> Camera:
        return replace(self, c2w=c2w)

    def with_resolution(self, width: int, height: int) -> Camera:
        return replace(self, intrinsics=self.intrinsics.scaled(width, height))

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> Camera:
        return replace(self, c2w=self.c2w.to(device=device, dtype=dtype))


def look_at(
    eye: Tensor,
    target: Tensor,
    up: Tensor | None = None,
) -> Tensor:
    """Camera-to-world [..., 4, 4] with OpenCV axes looking from ``eye`` [...,3] at ``target``.

    ``up`` [3] is the world up direction (default -y, the Inria / COLMAP convention); the
    camera's y axis (down in the image) points away from it.
    """
    eye = torch.as_tensor(eye)
    target = torch.as_tensor(target, dtype=eye.dtype, device=eye.device)
    if up is None:
        up = torch.tensor([0.0, -1.0, 0.0], dtype=eye.dtype, device=eye.device)
    up = torch.as_tensor(up, dtype=eye.dtype, device=eye.device)
    z = target - eye
    z = z / z.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    up_b = up.expand_as(z)
    x = torch.cross(-up_b, z, dim=-1)
    xn = x.norm(dim=-1, keepdim=True)
    # when looking along up, pick any perpendicular axis (avoids a NaN pose)
    alt = torch.cross(
        z, torch.tensor([1.0, 0.0, 0.0], dtype=eye.dtype, device=eye.device).expand_as(z), dim=-1
    )
    x = torch.where(xn > 1e-8, x, alt)
    x = x / x.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    y = torch.cross(z, x, dim=-1)
    shape = eye.shape[:-1]
    out = torch.zeros(*shape, 4, 4, dtype=eye.dtype, device=eye.device)
    out[..., :3, 0] = x
    out[..., :3, 1] = y
    out[..., :3, 2] = z
    out[..., :3, 3] = eye
    out[..., 3, 3] = 1.0
    return out
