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
- ``transforms``: a posed image set, ``transforms.json`` in the NeRF-synthetic, instant-ngp or
  nerfstudio dialect (:mod:`agilegs.service.data.transforms`). A folder (or file) with one
  ``transforms.json``: the capture's own split when it names one (``test_filenames``),
  else the pool is every frame but every 8th, the test set every 8th frame (the Mip-NeRF
  360 convention, ``i % 8 == 0``). A folder with ``transforms_train.json`` and
  ``transforms_test.json``: the given split. Initial points are the capture's
  ``ply_file_path`` points where it has them, else random, uniform in a ball around the
  point the cameras look at (the least-squares crossing of their optical axes) of
  ``random_init_radius`` times the cameras' median distance to it (3DGS initialises
  NeRF-synthetic scenes with random points in a cube, too), unless every pool frame has a
  depth map (``depth_file_path``): then the depth maps go to the mapper like the splat
  scenes' rendered depth (initialisation by back-projection, and by the profile's ``depth``).
- ``colmap``: a COLMAP model, text or binary (``PATH/sparse/0``, ``PATH/sparse`` or ``PATH``
  itself), with its images (``PATH/images`` or the smallest ``PATH/images_<k>`` that is at
  least the target width): Mip-NeRF 360, Tanks & Temples and Deep Blending come this way.
  Views are sorted by name (capture order), the test set is every 8th, the pool the rest;
  initial points are the sparse cloud.
- ``rosbag``: a rosbag2 recording (a folder with ``metadata.yaml``, or an ``.mcap`` / ``.db3``
  file) of a camera's colour images, camera info, optional registered depth, and poses from
  ``/tf`` + ``/tf_static`` or a PoseStamped topic (:mod:`agilegs.client.ros2.bag`; the topics
  are found by type unless ``bag_topics`` names them). Frames in stamp order, the test set
  every 8th, the pool the rest; random initial points as for ``transforms`` (the depth when
  every pool frame has one).

Distorted photographs are undistorted to a pinhole camera, frames without an image skipped (one
warning), and the log says what the map starts from. A posed set renders on black unless its
images have an alpha channel or a mask (then on ``SceneOptions.background``).
For posed image sets the images are resized to ``SceneOptions.width`` (aspect kept) and, when
the set is larger than the profile allows, the pool and the test set are thinned evenly
(capture order kept). The selectors need one set of intrinsics for the whole pool: the first
pool view's are used (a warning is logged when the others differ).

Each scene's ``info["type"]`` groups the figures: ``object`` (a splat of a scanned object),
``capture`` (a splat whose meta.json says ``"source_method": "capture"``: a real capture)
or ``posed`` (a posed image set: a scene with its background).
"""
from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from agilegs.client.ros2 import BagTopics, is_bag
from agilegs.service.nbv import Camera, GaussianMap, Intrinsics, load_scene, look_at, render
from agilegs.service.nbv.candidates import capture_pool, scene_center_radius
from agilegs.service.nbv.gaussians import SUFFIXES

from .posed_scenes import load_bag_scene, load_colmap_scene, load_transforms_scene
from .scene_model import (
    BenchScene,
    PathLike,
    SceneKind,
    SceneOptions,
    axes_crossing,
    colmap_model_dir,
    evenly_spaced,
    orbit_cameras,
    scene_name,
)

log = logging.getLogger(__name__)

MAX_SPLAT_POOL = 5000
"""Most cameras a splat scene's pool renders (a larger ``pool_size`` means "every frame" of a
posed capture, as in the capture profile)."""

__all__ = [
    "BenchScene",
    "SceneOptions",
    "detect_scene_kind",
    "load_bench_scene",
    "scene_name",
    "orbit_cameras",
    "axes_crossing",
    "evenly_spaced",
    "random_cube",
]


# ----------------------------------------------------------------------------- detection
def _splat_files(folder: Path) -> list[Path]:
    return sorted(f for f in folder.iterdir() if f.is_file() and f.suffix.lower() in SUFFIXES)


def detect_scene_kind(path: PathLike) -> SceneKind:
    """"splat", "transforms", "colmap" or "rosbag" for a scene path (see the module
    docstring).

    Raises:
        FileNotFoundError: the path does not exist.
        ValueError: the path holds no recognisable scene.
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"scene {p} not found")
    if is_bag(p):
        return "rosbag"
    if p.is_file():
        if p.suffix.lower() in SUFFIXES:
            return "splat"
        if p.suffix.lower() == ".json":
            return "transforms"
        raise ValueError(f"scene {p}: a file must be a .splat / .ply splat, a "
                         "transforms.json or a rosbag2 .mcap / .db3")
    if (p / "transforms.json").is_file() or (p / "transforms_train.json").is_file():
        return "transforms"
    if colmap_model_dir(p) is not None:
        return "colmap"
    if _splat_files(p):
        return "splat"
    raise ValueError(
        f"scene {p}: found no .splat/.ply file, no transforms.json / transforms_train.json, "
        "no COLMAP model (sparse/0, sparse or the folder itself with cameras and images) "
        "and no rosbag2 metadata.yaml"
    )

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
        info={"gaussians": gt.num_gaussians, "object_radius": float(r98),
              "type": _splat_type(file)},
    )


def _splat_type(file: Path) -> str:
    """``capture`` when the splat's meta.json says it was captured, else ``object``."""
    meta = file.parent / "meta.json"
    try:
        method = json.loads(meta.read_text()).get("source_method") if meta.is_file() else None
    except (OSError, ValueError):
        method = None
    return "capture" if method == "capture" else "object"

def load_bench_scene(path: PathLike, options: SceneOptions | None = None, *,
                     bag_topics: BagTopics | None = None) -> BenchScene:
    """Load a scene of any kind (see the module docstring) for the progressive protocol
    (``bag_topics``: the topics of a rosbag2 scene).

    Raises:
        FileNotFoundError: the path does not exist.
        ValueError: unrecognisable or malformed scene, naming the path.
    """
    opt = options or SceneOptions()
    opt.validate()
    p = Path(path)
    kind = detect_scene_kind(p)
    if kind == "splat":
        if opt.pool_size > MAX_SPLAT_POOL:
            raise ValueError(f"scene {p} is a splat: its pool is rendered, and {opt.pool_size} "
                             f"cameras (more than {MAX_SPLAT_POOL}) is a posed capture's "
                             "setting (the capture profile); use cpu_long or --pool-size")
        scene = _load_splat_scene(p, opt)
    elif kind == "transforms":
        scene = load_transforms_scene(p, opt)
    elif kind == "rosbag":
        scene = load_bag_scene(p, opt, bag_topics)
    else:
        scene = load_colmap_scene(p, opt)
    log.info("scene %s (%s): pool %d, test %d, %dx%d", scene.name, kind, scene.pool_size,
             scene.test_poses.shape[0], scene.intrinsics.width, scene.intrinsics.height)
    return scene


def random_cube(n: int, sh_coeffs: int = 1) -> tuple[GaussianMap, Tensor]:
    """``n`` seeded random Gaussians in the unit cube (``sh_coeffs`` SH coefficients each) and
    a camera-to-world pose [4, 4] two units in front of it, looking at its centre."""
    g = torch.Generator().manual_seed(0)
    gm = GaussianMap(
        means=torch.rand(n, 3, generator=g) - 0.5,
        log_scales=torch.log(torch.rand(n, 3, generator=g) * 0.02 + 0.005),
        quats=torch.randn(n, 4, generator=g),
        opacity_logits=torch.randn(n, generator=g),
        sh=torch.randn(n, sh_coeffs, 3, generator=g) * 0.3,
    )
    return gm, look_at(torch.tensor([0.0, 0.0, -2.0]), torch.zeros(3))
