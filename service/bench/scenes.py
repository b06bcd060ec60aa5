"""Scene sources of ``agilegs bench run``: what a progressive NBV run acquires and is scored on.

Three kinds of scene, detected from the path (:func:`detect_scene_kind`):

- ``splat``: a ground-truth Gaussian splat (a ``.splat`` / ``.ply`` file, or a folder holding
  such files, e.g. ``../shared/data/scenes/spot``; with several files in the folder the
  smallest is used). It is loaded with ``load_scene`` (a seeded subsample to
  ``SceneOptions.max_gaussians``) and every reference image is rendered from it at the
  profile's resolution on ``SceneOptions.background``, together with its ground-truth depth
  (expected depth where the rendered alpha exceeds 0.5, else 0). The candidate pool mimics a
  human capture (``capture_pool``: orbits at ``pool_elevations_deg`` around the object's
  centre, at ``orbit_scale`` times its 98% radius, with near-duplicates and jitter); the
  held-out test cameras lie on exact orbits at ``test_elevations_deg`` (between the pool's
  rings), at evenly spaced azimuths, looking at the centre: no test camera is in the pool.
- ``transforms``: a posed image set in the NeRF-synthetic layout. A folder (or file) with one
  ``transforms.json``: the pool is every frame but every 8th, the test set every 8th frame
  (the Mip-NeRF 360 convention, ``i % 8 == 0``). A folder with ``transforms_train.json`` and
  ``transforms_test.json``: the given split. Initial points are random, uniform in a ball
  around the point the cameras look at (the least-squares crossing of their optical axes) of
  ``random_init_radius`` times the cameras' median distance to it (3DGS initialises
  NeRF-synthetic scenes with random points in a cube, too).
- ``colmap``: a COLMAP model, text or binary (``PATH/sparse/0``, ``PATH/sparse`` or ``PATH``
  itself), with its images (``PATH/images`` or the smallest ``PATH/images_<k>`` that is at
  least the target width): Mip-NeRF 360, Tanks & Temples and Deep Blending come this way.
  Views are sorted by name (capture order), the test set is every 8th, the pool the rest;
  initial points are the sparse cloud.

For posed image sets the images are resized to ``SceneOptions.width`` (aspect kept) and, when
the set is larger than the profile allows, the pool and the test set are thinned evenly
(capture order kept). The selectors need one set of intrinsics for the whole pool: the first
pool view's are used (a warning is logged when the others differ).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
from torch import Tensor

from agilegs.service.nbv.camera import Camera, Intrinsics, look_at
from agilegs.service.nbv.candidates import capture_pool, scene_center_radius
from agilegs.service.nbv.gaussians import SUFFIXES, load_scene
from agilegs.service.nbv.rasterize import render

log = logging.getLogger(__name__)

PathLike = str | os.PathLike[str]
SceneKind = Literal["splat", "transforms", "colmap"]

__all__ = [
    "BenchScene",
    "SceneOptions",
    "detect_scene_kind",
    "load_bench_scene",
    "scene_name",
    "orbit_cameras",
    "axes_crossing",
    "evenly_spaced",
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
        background: RGB in [0, 1] behind splat renders and of RGBA images (white).
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
        kind: "splat", "transforms" or "colmap".
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


# ----------------------------------------------------------------------------- detection
def _splat_files(folder: Path) -> list[Path]:
    return sorted(f for f in folder.iterdir() if f.is_file() and f.suffix.lower() in SUFFIXES)


def _colmap_model_dir(path: Path) -> Path | None:
    for d in (path / "sparse" / "0", path / "sparse", path):
        if d.is_dir() and any((d / f"cameras.{e}").is_file() for e in ("bin", "txt")) and any(
            (d / f"images.{e}").is_file() for e in ("bin", "txt")
        ):
            return d
    return None


def detect_scene_kind(path: PathLike) -> SceneKind:
    """"splat", "transforms" or "colmap" for a scene path (see the module docstring).

    Raises:
        FileNotFoundError: the path does not exist.
        ValueError: the path holds no recognisable scene.
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"scene {p} not found")
    if p.is_file():
        if p.suffix.lower() in SUFFIXES:
            return "splat"
        if p.suffix.lower() == ".json":
            return "transforms"
        raise ValueError(f"scene {p}: a file must be a .splat / .ply splat or a "
                         "transforms.json")
    if (p / "transforms.json").is_file() or (p / "transforms_train.json").is_file():
        return "transforms"
    if _colmap_model_dir(p) is not None:
        return "colmap"
    if _splat_files(p):
        return "splat"
    raise ValueError(
        f"scene {p}: found no .splat/.ply file, no transforms.json / transforms_train.json "
        "and no COLMAP model (sparse/0, sparse or the folder itself with cameras and images)"
    )


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


def _up_from_poses(c2w: Tensor) -> Tensor:
    """World up as the mean of the cameras' -y axes (OpenCV: y points down in the image)."""
    u = -c2w[:, :3, 1].double().mean(0)
    n = float(u.norm())
    if n < 1e-6:
        return torch.tensor([0.0, -1.0, 0.0])
    return (u / n).float()


# ----------------------------------------------------------------------------- splat scenes
def _splat_file(path: Path) -> Path:
    if path.is_file():
        return path
    files = _splat_files(path)
    if not files:
        raise ValueError(f"scene {path}: no .splat / .ply file")
    if len(files) > 1:
        smallest = min(files, key=lambda f: (f.stat().st_size, f.name))
        log.info("scene %s holds %d splat files; using the smallest, %s", path, len(files),
                 smallest.name)
        return smallest
    return files[0]


@torch.no_grad()
def render_references(
    gt: Any, poses: Tensor, intrinsics: Intrinsics, background: Sequence[float]
) -> tuple[Tensor, Tensor]:
    """Render ground-truth RGB [V, H, W, 3] and depth [V, H, W] (0 where alpha <= 0.5)."""
    bg = torch.tensor(list(background), dtype=gt.dtype)
    rgbs, depths = [], []
    for pose in poses:
        out = render(gt, Camera(c2w=pose.to(gt.dtype), intrinsics=intrinsics), background=bg)
        rgbs.append(out.rgb.clamp(0, 1).float())
        depths.append(torch.where(out.alpha > 0.5, out.depth, torch.zeros_like(out.depth))
                      .float())
    return torch.stack(rgbs), torch.stack(depths)


def _load_splat_scene(path: Path, opt: SceneOptions) -> BenchScene:
    file = _splat_file(path)
    gt = load_scene(file, max_gaussians=opt.max_gaussians, seed=opt.seed)
    center, r98 = scene_center_radius(gt.means)
    radius = opt.orbit_scale * r98
    intr = Intrinsics.from_fov(opt.fov_deg, opt.width, opt.height)
    up = (0.0, -1.0, 0.0)
    pool = capture_pool(center, radius, opt.pool_size, elevations_deg=opt.pool_elevations_deg,
                        up=up, seed=opt.seed)
    test = orbit_cameras(center, radius, opt.test_elevations_deg, opt.test_count, up=up)
    pool_rgb, pool_depth = render_references(gt, pool, intr, opt.background)
    test_rgb, _ = render_references(gt, test, intr, opt.background)
    return BenchScene(
        name=scene_name(path),
        kind="splat",
        source=str(file),
        intrinsics=intr,
        pool_poses=pool,
        pool_images=pool_rgb,
        pool_depths=pool_depth,
        test_poses=test,
        test_images=test_rgb,
        test_intrinsics=[intr] * int(test.shape[0]),
        background=opt.background,
        init_points=None,
        init_colors=None,
        center=center.float(),
        radius=float(radius),
        up=torch.tensor(up),
        info={"gaussians": gt.num_gaussians, "object_radius": float(r98)},
    )


# ----------------------------------------------------------------------------- posed sets
def _split_views(views: list[Any], opt: SceneOptions) -> tuple[list[Any], list[Any]]:
    test = [v for i, v in enumerate(views) if i % opt.test_every == 0]
    pool = [v for i, v in enumerate(views) if i % opt.test_every != 0]
    return pool, test


def _thin(views: list[Any], k: int) -> list[Any]:
    return [views[i] for i in evenly_spaced(len(views), k)]


def _posed_scene(
    name: str,
    kind: SceneKind,
    source: str,
    pool_views: list[Any],
    test_views: list[Any],
    opt: SceneOptions,
    init_points: Tensor | None,
    init_colors: Tensor | None,
    info: dict[str, Any],
) -> BenchScene:
    total_pool, total_test = len(pool_views), len(test_views)
    pool_views = _thin(pool_views, opt.pool_size)
    test_views = _thin(test_views, opt.test_count)
    if not pool_views or not test_views:
        raise ValueError(f"scene {source}: needs at least one pool and one test frame, got "
                         f"{len(pool_views)} and {len(test_views)}")
    intr = pool_views[0].camera.intrinsics
    for v in pool_views[1:]:
        o = v.camera.intrinsics
        if (o.width, o.height) != (intr.width, intr.height) or abs(o.fx - intr.fx) > 0.01 * intr.fx:
            log.warning("scene %s: pool cameras differ in intrinsics; the selectors use the "
                        "first one's (%s)", source, intr)
            break
    pool_poses = torch.stack([v.camera.c2w.float() for v in pool_views])
    test_poses = torch.stack([v.camera.c2w.float() for v in test_views])
    h, w = intr.height, intr.width

    def image_of(v: Any) -> Tensor:
        img = v.image
        if img.shape[:2] != (h, w):
            img = torch.nn.functional.interpolate(
                img.permute(2, 0, 1)[None], size=(h, w), mode="bilinear", align_corners=False
            )[0].permute(1, 2, 0)
        return img.float().clamp(0, 1)

    pool_images = torch.stack([image_of(v) for v in pool_views])
    test_images = torch.stack([v.image.float().clamp(0, 1) for v in test_views]) if all(
        v.image.shape[:2] == test_views[0].image.shape[:2] for v in test_views
    ) else None
    test_intr = [v.camera.intrinsics for v in test_views]
    if test_images is None:  # mixed sizes: bring every test view to the pool's size
        test_images = torch.stack([image_of(v) for v in test_views])
        test_intr = [v.camera.intrinsics.scaled(w, h) for v in test_views]
    center = axes_crossing(torch.cat([pool_poses, test_poses]))
    radius = float((pool_poses[:, :3, 3] - center).norm(dim=1).median())
    info = dict(info, pool_frames=total_pool, test_frames=total_test,
                pool_used=len(pool_views), test_used=len(test_views))
    return BenchScene(
        name=name,
        kind=kind,
        source=source,
        intrinsics=intr,
        pool_poses=pool_poses,
        pool_images=pool_images,
        pool_depths=None,
        test_poses=test_poses,
        test_images=test_images,
        test_intrinsics=test_intr,
        background=opt.background,
        init_points=init_points,
        init_colors=init_colors,
        center=center,
        radius=radius,
        up=_up_from_poses(pool_poses),
        info=info,
    )


def _random_points(poses: Tensor, opt: SceneOptions) -> tuple[Tensor, Tensor]:
    """Uniform random points in a ball around the cameras' aim (see the module docstring)."""
    center = axes_crossing(poses)
    r = opt.random_init_radius * float((poses[:, :3, 3] - center).norm(dim=1).median())
    g = torch.Generator().manual_seed(opt.seed)
    n = opt.random_init_points
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=1, keepdim=True).clamp_min(1e-12)
    rad = r * torch.rand(n, 1, generator=g, dtype=torch.float64) ** (1.0 / 3.0)
    pts = (center.double() + d * rad).float()
    cols = torch.rand(n, 3, generator=g)
    return pts, cols


def _load_transforms_scene(path: Path, opt: SceneOptions) -> BenchScene:
    from agilegs.service.data.transforms import load_transforms_json

    folder = path.parent if path.is_file() else path
    if path.is_file():
        files = {"all": path}
    elif (folder / "transforms.json").is_file():
        files = {"all": folder / "transforms.json"}
    else:
        files = {"train": folder / "transforms_train.json"}
        if (folder / "transforms_test.json").is_file():
            files["test"] = folder / "transforms_test.json"
    first = next(iter(files.values()))
    # the downscale that brings the first frame to the target width
    probe = load_transforms_json(first, background=opt.background, load_images=False)
    if not probe:
        raise ValueError(f"scene {first}: no frames")
    scale = probe[0].camera.width / opt.width
    load = {k: load_transforms_json(f, background=opt.background, downscale=scale)
            for k, f in files.items()}
    if "all" in load:
        pool_views, test_views = _split_views(load["all"], opt)
    elif "test" in load:
        pool_views, test_views = load["train"], load["test"]
    else:
        pool_views, test_views = _split_views(load["train"], opt)
    poses = torch.stack([v.camera.c2w.float() for v in pool_views + test_views])
    pts, cols = _random_points(poses, opt)
    return _posed_scene(scene_name(folder), "transforms", str(first), pool_views, test_views,
                        opt, pts, cols, {"init": "random"})


def _images_dir(root: Path, target_width: int) -> Path | None:
    from PIL import Image

    cands = []
    for d in sorted(root.glob("images*")):
        if not d.is_dir():
            continue
        first = next((f for f in sorted(d.iterdir()) if f.is_file()), None)
        if first is None:
            continue
        try:
            with Image.open(first) as im:
                cands.append((im.size[0], d))
        except OSError:
            continue
    if not cands:
        return None
    big_enough = [c for c in cands if c[0] >= target_width]
    return (min(big_enough, key=lambda c: c[0]) if big_enough else max(cands,
                                                                        key=lambda c: c[0]))[1]


def _load_colmap_scene(path: Path, opt: SceneOptions) -> BenchScene:
    from agilegs.service.data.colmap import load_colmap

    model = _colmap_model_dir(path)
    assert model is not None
    images = _images_dir(path, opt.width)
    if images is None and model == path:  # the model folder itself: images beside it
        images = _images_dir(path.parent, opt.width)
    if images is None:
        raise ValueError(f"scene {path}: no images folder (images, images_2, ...) next to the "
                         f"COLMAP model {model}")
    probe, _, _ = load_colmap(model, None)
    if not probe:
        raise ValueError(f"scene {path}: the COLMAP model has no images")
    scale = probe[0].camera.width / opt.width
    views, points, colors = load_colmap(model, images, downscale=scale,
                                        background=opt.background)
    pool_views, test_views = _split_views(views, opt)
    if points.shape[0] == 0:
        log.warning("scene %s: the COLMAP model has no 3D points; random initial points",
                    path)
        points, colors = _random_points(
            torch.stack([v.camera.c2w.float() for v in views]), opt)
    elif opt.max_init_points is not None and points.shape[0] > opt.max_init_points:
        g = torch.Generator().manual_seed(opt.seed)
        idx = torch.randperm(points.shape[0], generator=g)[: opt.max_init_points].sort().values
        points, colors = points[idx], colors[idx]
    return _posed_scene(scene_name(path), "colmap", str(model), pool_views, test_views, opt,
                        points, colors, {"init": "sparse", "images_dir": str(images),
                                         "sparse_points": int(points.shape[0])})


def load_bench_scene(path: PathLike, options: SceneOptions | None = None) -> BenchScene:
    """Load a scene of any kind (see the module docstring) for the progressive protocol.

    Raises:
        FileNotFoundError: the path does not exist.
        ValueError: unrecognisable or malformed scene, naming the path.
    """
    opt = options or SceneOptions()
    opt.validate()
    p = Path(path)
    kind = detect_scene_kind(p)
    if kind == "splat":
        scene = _load_splat_scene(p, opt)
    elif kind == "transforms":
        scene = _load_transforms_scene(p, opt)
    else:
        scene = _load_colmap_scene(p, opt)
    log.info("scene %s (%s): pool %d, test %d, %dx%d", scene.name, kind, scene.pool_size,
             scene.test_poses.shape[0], scene.intrinsics.width, scene.intrinsics.height)
    return scene
