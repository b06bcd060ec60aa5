"""What a benchmark scene is: its options, the loaded scene, and the camera geometry the
loaders share (:mod:`agilegs.lab.bench.scenes` loads them)."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
from torch import Tensor

from agilegs.service.nbv import Camera, Intrinsics, look_at

PathLike = str | os.PathLike[str]
SceneKind = Literal["splat", "transforms", "colmap", "rosbag"]

__all__ = [
    "BenchScene",
    "PathLike",
    "SceneKind",
    "SceneOptions",
    "axes_crossing",
    "colmap_model_dir",
    "evenly_spaced",
    "orbit_cameras",
    "scene_name",
    "up_from_poses",
]


@dataclass(frozen=True)
class SceneOptions:
    """How a scene is turned into a pool, test views and references.

    Args:
        width: image width in pixels (64). Splat references are rendered at this size;
            posed image sets are resized to it (height from the aspect ratio).
        height: image height of splat references (64).
        fov_deg: horizontal field of view of splat scenes' cameras, degrees (50).
        max_gaussians: splat scenes are subsampled (seeded) to at most this many Gaussians
            (None: all).
        pool_size: splat scenes: cameras in the pool; posed sets: at most this many pool
            frames, thinned evenly (180).
        test_count: splat scenes: held-out test cameras; posed sets: at most this many test
            frames, thinned evenly (8).
        orbit_scale: splat scenes: pool and test orbit radius / the object's 98% radius
            (2.6, the object fills most of a 50 degree view).
        pool_elevations_deg: splat scenes: elevations of the pool's orbits (10, 30, 50).
        test_elevations_deg: splat scenes: elevations of the test orbits (20, 40: between
            the pool's rings, so no test camera is in the pool).
        background: RGB in [0, 1] behind splat renders and of RGBA or masked images (white);
            a posed set whose images have neither alpha nor masks renders on black instead
            (a photograph is composited on nothing).
        test_every: posed sets without a given split: every this-th frame is a test frame (8).
        random_init_points: transforms.json scenes: random initial points (5000).
        random_init_radius: transforms.json scenes: radius of the initial-point ball, times
            the cameras' median distance to the point they look at (0.35).
        max_init_points: COLMAP sparse clouds are subsampled (seeded) to at most this many
            points (20000; None: all).
        seed: seed of the pool, the ground-truth subsample and random initial points (0).
    """

    width: int = 64
    height: int = 64
    fov_deg: float = 50.0
    max_gaussians: int | None = 3000
    pool_size: int = 180
    test_count: int = 8
    orbit_scale: float = 2.6
    pool_elevations_deg: tuple[float, ...] = (10.0, 30.0, 50.0)
    test_elevations_deg: tuple[float, ...] = (20.0, 40.0)
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    test_every: int = 8
    random_init_points: int = 5000
    random_init_radius: float = 0.35
    max_init_points: int | None = 20000
    seed: int = 0

    def validate(self) -> None:
        for name in ("width", "height", "pool_size", "test_count", "test_every",
                     "random_init_points"):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v or int(v) < 1:
                raise ValueError(f"scene option {name} must be an integer >= 1, got {v!r}")
        if not 0 < self.fov_deg < 180:
            raise ValueError(f"scene option fov_deg must be in (0, 180), got {self.fov_deg}")
        if not self.orbit_scale > 0:
            raise ValueError(f"scene option orbit_scale must be > 0, got {self.orbit_scale}")
        if not self.pool_elevations_deg or not self.test_elevations_deg:
            raise ValueError("scene options pool_elevations_deg and test_elevations_deg must "
                             "name at least one orbit each")
        if len(self.background) != 3 or not all(0 <= c <= 1 for c in self.background):
            raise ValueError(f"scene option background must be 3 values in [0, 1], got "
                             f"{self.background}")


@dataclass
class BenchScene:
    """A scene ready for the progressive protocol.

    Attributes:
        name: short name (folder or file stem).
        kind: "splat", "transforms", "colmap" or "rosbag".
        source: the path it was loaded from.
        intrinsics: shared by every pool (and test) camera.
        pool_poses: candidate camera-to-world poses [D, 4, 4] (OpenCV axes), capture order.
        pool_images: reference images [D, H, W, 3] in [0, 1].
        pool_depths: ground-truth depth [D, H, W] (0 where unknown), or None.
        test_poses: held-out camera-to-world poses [T, 4, 4].
        test_images: held-out references [T, H, W, 3].
        test_intrinsics: intrinsics of each test view (len T).
        background: RGB the references were composited on.
        init_points: initial points [P, 3] (COLMAP sparse cloud / random), or None (depth).
        init_colors: their colours [P, 3] in [0, 1], or None.
        center: the point the capture looks at [3].
        radius: typical camera distance from ``center``.
        up: world up direction [3].
        info: facts for the report (Gaussian count, frame counts, ...).
    """

    name: str
    kind: SceneKind
    source: str
    intrinsics: Intrinsics
    pool_poses: Tensor
    pool_images: Tensor
    pool_depths: Tensor | None
    test_poses: Tensor
    test_images: Tensor
    test_intrinsics: list[Intrinsics]
    background: tuple[float, float, float]
    init_points: Tensor | None
    init_colors: Tensor | None
    center: Tensor
    radius: float
    up: Tensor
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def pool_size(self) -> int:
        return int(self.pool_poses.shape[0])

    def pool_camera(self, i: int) -> Camera:
        """The camera of pool entry ``i``."""
        return Camera(c2w=self.pool_poses[i], intrinsics=self.intrinsics)

    def test_camera(self, i: int) -> Camera:
        """The camera of test view ``i``."""
        return Camera(c2w=self.test_poses[i], intrinsics=self.test_intrinsics[i])

def scene_name(path: PathLike) -> str:
    """A short name: the folder's name, or the file's stem (``transforms*.json``: its folder)."""
    p = Path(path).resolve()
    if p.is_file():
        return p.parent.name if p.suffix.lower() == ".json" else p.stem
    return p.name

# ----------------------------------------------------------------------------- geometry
def evenly_spaced(n: int, k: int) -> list[int]:
    """``min(k, n)`` indices spread evenly over ``range(n)``, in increasing order."""
    if k >= n:
        return list(range(n))
    return sorted({int(math.floor((i + 0.5) * n / k)) for i in range(k)})


def orbit_cameras(
    center: Tensor,
    radius: float,
    elevations_deg: Sequence[float],
    count: int,
    *,
    up: Sequence[float] = (0.0, -1.0, 0.0),
    azimuth_offset: float = 0.0,
) -> Tensor:
    """``count`` cameras [count, 4, 4] on exact orbits, looking at ``center`` [3].

    The cameras are split over the elevations (the first ones get one more when ``count``
    does not divide); on each orbit the azimuths are evenly spaced, offset by half a step
    plus ``azimuth_offset`` radians and by a quarter step more per orbit.
    """
    from agilegs.service.nbv.candidates import orbit_frame

    f64 = torch.float64
    c, upv, e1, e2 = orbit_frame(center, up)
    rings = len(elevations_deg)
    eyes = []
    for r, elev in enumerate(elevations_deg):
        n = count // rings + (1 if r < count % rings else 0)
        if n == 0:
            continue
        e = math.radians(float(elev))
        az = (torch.arange(n, dtype=f64) + 0.5 + 0.25 * r) / n * 2 * math.pi + azimuth_offset
        horiz = torch.cos(az)[:, None] * e1 + torch.sin(az)[:, None] * e2
        d = math.cos(e) * horiz + math.sin(e) * upv
        eyes.append(c + radius * d)
    eye = torch.cat(eyes)
    return look_at(eye, c.expand_as(eye), up=upv).float()


def axes_crossing(c2w: Tensor) -> Tensor:
    """Least-squares point nearest to every optical axis (camera z) of poses [N, 4, 4] -> [3]."""
    p = c2w[:, :3, 3].double()
    d = c2w[:, :3, 2].double()
    d = d / d.norm(dim=1, keepdim=True).clamp_min(1e-12)
    eye = torch.eye(3, dtype=torch.float64)
    proj = eye - d[:, :, None] * d[:, None, :]
    a = proj.sum(0)
    b = (proj @ p[:, :, None]).sum(0)[:, 0]
    if float(torch.linalg.matrix_rank(a)) < 3:
        return p.mean(0).float()
    return torch.linalg.solve(a, b).float()


def up_from_poses(c2w: Tensor) -> Tensor:
    """World up as the mean of the cameras' -y axes (OpenCV: y points down in the image)."""
    u = -c2w[:, :3, 1].double().mean(0)
    n = float(u.norm())
    if n < 1e-6:
        return torch.tensor([0.0, -1.0, 0.0])
    return (u / n).float()


def colmap_model_dir(path: Path) -> Path | None:
    """The folder holding a COLMAP model (cameras and images files) under ``path``, or None."""
    for d in (path / "sparse" / "0", path / "sparse", path):
        if d.is_dir() and any((d / f"cameras.{e}").is_file() for e in ("bin", "txt")) and any(
            (d / f"images.{e}").is_file() for e in ("bin", "txt")
        ):
            return d
    return None
