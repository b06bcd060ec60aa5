"""Posed image sets as benchmark scenes: NeRF-synthetic ``transforms.json`` folders, COLMAP
models and rosbag2 recordings (see :mod:`agilegs.lab.bench.scenes` for the
conventions)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from .scene_model import (
    BenchScene,
    SceneKind,
    SceneOptions,
    axes_crossing,
    colmap_model_dir,
    evenly_spaced,
    scene_name,
    up_from_poses,
)

log = logging.getLogger(__name__)

__all__ = ["load_bag_scene", "load_colmap_scene", "load_transforms_scene", "random_init_points"]


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
    background: tuple[float, float, float] | None = None,
) -> BenchScene:
    """``background``: what the map renders on; None: the profile's when an image has an
    alpha channel or a mask, else black (a photograph is composited on nothing)."""
    total_pool, total_test = len(pool_views), len(test_views)
    if background is None:
        has_alpha = any(getattr(v, "alpha", None) is not None for v in pool_views + test_views)
        background = opt.background if has_alpha else (0.0, 0.0, 0.0)
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
    pool_depths = None
    if all(getattr(v, "depth", None) is not None for v in pool_views):
        pool_depths = torch.stack([_resized_depth(v.depth, h, w) for v in pool_views])
        init_points = init_colors = None  # the mapper back-projects the depth maps
        info = dict(info, init="depth")
    _log_start(source, info, init_points, background)
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
                pool_used=len(pool_views), test_used=len(test_views), type="posed")
    return BenchScene(
        name=name,
        kind=kind,
        source=source,
        intrinsics=intr,
        pool_poses=pool_poses,
        pool_images=pool_images,
        pool_depths=pool_depths,
        test_poses=test_poses,
        test_images=test_images,
        test_intrinsics=test_intr,
        background=background,
        init_points=init_points,
        init_colors=init_colors,
        center=center,
        radius=radius,
        up=up_from_poses(pool_poses),
        info=info,
    )


_STARTS = {
    "sparse": "the capture's {n} structure-from-motion points (COLMAP points3D)",
    "ply": "the capture's {n} structure-from-motion points (ply_file_path)",
    "random": "{n} random points in a ball around the point the cameras look at (the capture "
              "has no structure-from-motion points and no depth)",
    "depth": "the depth maps of the acquired views (back-projected)",
}


def _log_start(source: str, info: dict[str, Any], points: Tensor | None,
               background: tuple[float, float, float]) -> None:
    n = 0 if points is None else int(points.shape[0])
    log.info("scene %s: the map starts from %s; background %s", source,
             _STARTS[str(info.get("init", "random"))].format(n=n),
             "black (photographs: composited on nothing)" if tuple(background) == (0, 0, 0)
             else list(background))


def _resized_depth(depth: Tensor, h: int, w: int) -> Tensor:
    """A depth map [H', W'] at [h, w] (nearest: no depth is blended across an edge)."""
    d = depth.float()
    if d.shape == (h, w):
        return d
    return torch.nn.functional.interpolate(d[None, None], size=(h, w), mode="nearest")[0, 0]


def random_init_points(poses: Tensor, opt: SceneOptions) -> tuple[Tensor, Tensor]:
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


def load_transforms_scene(path: Path, opt: SceneOptions) -> BenchScene:
    from agilegs.service.data.transforms import load_transforms

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
    probe = load_transforms(first, background=opt.background, load_images=False, quiet=True)
    if not probe.views:
        raise ValueError(f"scene {first}: no frames")
    scale = probe.views[0].camera.width / opt.width
    load = {k: load_transforms(f, background=opt.background, downscale=scale)
            for k, f in files.items()}
    split_from = "every 8th frame"
    if "all" in load and load["all"].has_split:
        cap = load["all"]
        pool_views = [v for v, s in zip(cap.views, cap.split, strict=True) if s != "test"]
        test_views = [v for v, s in zip(cap.views, cap.split, strict=True) if s == "test"]
        split_from = "the capture's test_filenames"
    elif "all" in load:
        pool_views, test_views = _split_views(load["all"].views, opt)
    elif "test" in load:
        pool_views, test_views = load["train"].views, load["test"].views
        split_from = "transforms_test.json"
    else:
        pool_views, test_views = _split_views(load["train"].views, opt)
    log.info("scene %s: test views from %s (%d), pool %d frames in capture order", folder,
             split_from, len(test_views), len(pool_views))
    ply = next((c for c in load.values() if c.points is not None and c.points.shape[0]), None)
    info: dict[str, Any] = {"split": split_from,
                            "skipped_frames": sum(len(c.skipped) for c in load.values()),
                            "distortion": sorted({d for c in load.values()
                                                  for d in c.distortions})}
    if ply is not None:
        assert ply.points is not None and ply.colors is not None
        pts, cols = _subsample(ply.points, ply.colors, opt)
        info.update(init="ply", sparse_points=int(pts.shape[0]))
    else:
        poses = torch.stack([v.camera.c2w.float() for v in pool_views + test_views])
        pts, cols = random_init_points(poses, opt)
        info.update(init="random")
    return _posed_scene(scene_name(folder), "transforms", str(first), pool_views, test_views,
                        opt, pts, cols, info)


def _subsample(points: Tensor, colors: Tensor, opt: SceneOptions) -> tuple[Tensor, Tensor]:
    """At most ``opt.max_init_points`` of the points (seeded, order kept)."""
    if opt.max_init_points is not None and points.shape[0] > opt.max_init_points:
        g = torch.Generator().manual_seed(opt.seed)
        idx = torch.randperm(points.shape[0], generator=g)[: opt.max_init_points].sort().values
        points, colors = points[idx], colors[idx]
    return points, colors


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


def load_colmap_scene(path: Path, opt: SceneOptions) -> BenchScene:
    from agilegs.service.data.colmap import load_colmap

    model = colmap_model_dir(path)
    assert model is not None
    images = _images_dir(path, opt.width)
    if images is None and model == path:  # the model folder itself: images beside it
        images = _images_dir(path.parent, opt.width)
    if images is None:
        raise ValueError(f"scene {path}: no images folder (images, images_2, ...) next to the "
                         f"COLMAP model {model}")
    probe, _, _ = load_colmap(model, None, quiet=True)
    if not probe:
        raise ValueError(f"scene {path}: the COLMAP model has no images")
    scale = probe[0].camera.width / opt.width
    views, points, colors = load_colmap(model, images, downscale=scale,
                                        background=opt.background)
    pool_views, test_views = _split_views(views, opt)
    if points.shape[0] == 0:
        points, colors = random_init_points(
            torch.stack([v.camera.c2w.float() for v in views]), opt)
        init = "random"
    else:
        points, colors = _subsample(points, colors, opt)
        init = "sparse"
    info: dict[str, Any] = {"init": init, "images_dir": str(images), "split": "every 8th frame"}
    if init == "sparse":
        info["sparse_points"] = int(points.shape[0])
    return _posed_scene(scene_name(path), "colmap", str(model), pool_views, test_views, opt,
                        points, colors, info)


def load_bag_scene(path: Path, opt: SceneOptions, topics: Any = None) -> BenchScene:
    """A rosbag2 (folder or .mcap / .db3 file) read by
    :func:`agilegs.client.ros2.bag.read_bag` with ``topics`` (a ``BagTopics``; None: found
    by type); at most twice the profile's pool and test views are decoded, evenly spaced."""
    import numpy as np

    from agilegs.client.ros2 import read_bag
    from agilegs.service.data.images import View, target_size
    from agilegs.service.nbv import Camera, Intrinsics

    frames = read_bag(path, topics, max_frames=2 * (opt.pool_size + opt.test_count))
    if not frames:
        raise ValueError(f"scene {path}: the bag gives no posed frame")
    k0 = frames[0].intrinsics
    w, h = target_size(k0["width"], k0["height"], k0["width"] / opt.width)
    views = []
    for f in frames:
        intr = Intrinsics(**f.intrinsics)
        img = torch.from_numpy(f.rgb.astype(np.float32) / 255.0)
        if img.shape[:2] != (h, w):
            img = torch.nn.functional.interpolate(img.permute(2, 0, 1)[None], size=(h, w),
                                                  mode="area")[0].permute(1, 2, 0)
        depth_m = f.depth_m()
        depth = _resized_depth(torch.from_numpy(depth_m), h, w) if depth_m is not None else None
        views.append(View(name=str(f.stamp_ns), image=img, depth=depth,
                          camera=Camera.from_intrinsics(torch.from_numpy(f.c2w),
                                                        intr.scaled(w, h))))
    pool_views, test_views = _split_views(views, opt)
    pts, cols = random_init_points(torch.stack([v.camera.c2w.float() for v in views]), opt)
    described = topics.describe() if topics is not None else ""
    source = f"{path}?{described}" if described else str(path)
    return _posed_scene(scene_name(path), "rosbag", source, pool_views, test_views, opt, pts,
                        cols, {"init": "random", "bag_frames": len(frames)})
