"""The demo's robot on a real capture: it replays the capture.

``agilegs demo --scene PATH`` with a posed capture (a COLMAP model, a ``transforms.json`` or a
rosbag2, as ``agilegs bench run`` loads them, :func:`agilegs.lab.bench.scenes.load_bench_scene`)
drives the sessions with a :class:`CaptureRobot`: the candidate pool is the capture's own
frames in capture order (every 8th frame held out for the test PSNR, or the capture's own
split), and moving to a chosen candidate returns that frame's photograph (RGB, with its depth
map where the capture has one). The map starts from the capture's structure-from-motion points
(COLMAP ``points3D``, nerfstudio ``ply_file_path``) or, without them, random points around the
point the cameras look at; it renders on black (a photograph is composited on nothing).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np

    from agilegs.lab.bench.scene_model import BenchScene

__all__ = ["CaptureRobot", "is_capture", "load_capture"]

log = logging.getLogger(__name__)


def is_capture(scene: str) -> bool:
    """Whether ``--scene`` names a posed capture (COLMAP, transforms.json, rosbag2) rather
    than a bundled or a splat scene."""
    if scene in ("spot", "teapot"):
        return False
    p = Path(scene)
    if not p.exists():
        return False
    from agilegs.lab.bench.scenes import detect_scene_kind

    try:
        return detect_scene_kind(p) != "splat"
    except ValueError:
        return False


class CaptureRobot:
    """A robot that replays a capture (module docstring); the demo's ``Robot`` interface.

    Attributes:
        scene: the loaded capture.
        intrinsics: the pool's pinhole camera (the images' size).
        pool: the pool frames' camera-to-world poses [D, 4, 4] (OpenCV axes), capture order.
        background: what the maps render on (black for photographs).
        initial_gaussians: the starting map (a ``.ply`` path) every session is created from.
        summary: one line for the demo's banner.
    """

    def __init__(self, scene: BenchScene, work_dir: Path, init_gaussians: int, seed: int) -> None:
        import torch

        self.scene = scene
        self.intrinsics = scene.intrinsics
        self.pool = scene.pool_poses.double()
        self.test_poses = scene.test_poses
        self.background = tuple(float(c) for c in scene.background)
        self._torch = torch
        self.initial_gaussians = self._initial_map(work_dir, init_gaussians, seed)
        start = scene.info.get("init", "random")
        self.summary = (f"a capture of {scene.pool_size + int(scene.test_poses.shape[0])} "
                        f"photographs ({scene.kind}), the map starting from "
                        f"{self._start_points} {'random' if start == 'random' else start} points")

    def _initial_map(self, work_dir: Path, count: int, seed: int) -> Path:
        """The capture's initial points (at most ``count``, seeded) as isotropic Gaussians
        (nearest-neighbour scales, opacity 0.1), written to ``work_dir/initial.ply``."""
        from agilegs.lab.bench.posed_scenes import random_init_points
        from agilegs.lab.bench.scene_model import SceneOptions
        from agilegs.service.mapper.points import nearest_neighbour_scales
        from agilegs.service.nbv import GaussianMap

        torch = self._torch
        sc = self.scene
        if sc.init_points is not None and sc.init_colors is not None:
            pts, cols = sc.init_points.double(), sc.init_colors.double()
        else:  # depth-only captures: random points as well (the frames carry the depth)
            p, c = random_init_points(torch.cat([sc.pool_poses, sc.test_poses]),
                                  SceneOptions(random_init_points=count, seed=seed))
            pts, cols = p.double(), c.double()
        if pts.shape[0] > count:
            g = torch.Generator().manual_seed(seed)
            idx = torch.randperm(pts.shape[0], generator=g)[:count].sort().values
            pts, cols = pts[idx], cols[idx]
        self._start_points = int(pts.shape[0])
        gmap = GaussianMap.from_points(pts, cols, scale=nearest_neighbour_scales(pts),
                                       opacity=0.1)
        work_dir.mkdir(parents=True, exist_ok=True)
        path = work_dir / "initial.ply"
        gmap.save(path)
        return path

    def frame_of(self, pose: np.ndarray) -> int:
        """The pool frame whose pose is nearest ``pose`` [4, 4] (the robot drove there)."""
        import numpy as np

        d = np.abs(self.pool.numpy() - np.asarray(pose, dtype=np.float64)[None]).sum(axis=(1, 2))
        return int(np.argmin(d))

    def capture(self, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The photograph (RGB uint8 [H, W, 3]) and depth ([H, W] or None) of the frame at
        ``pose``."""
        import numpy as np

        i = self.frame_of(pose)
        img = (self.scene.pool_images[i].clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
        depth = None
        if self.scene.pool_depths is not None:
            depth = self.scene.pool_depths[i].numpy().astype(np.float32)
        return img, depth

    def observation(self, pose: np.ndarray, **where: Any) -> Any:
        from agilegs.schemas import ObservationIn

        img, depth = self.capture(pose)
        i = self.frame_of(pose)
        exact = self.pool[i].numpy()
        return ObservationIn.from_numpy(None if where else exact, image=img, depth=depth,
                                        image_encoding="png", **where)

    def psnr(self, arrays: dict[str, np.ndarray]) -> float:
        """Mean PSNR (dB) of a downloaded map on the capture's held-out photographs."""
        from agilegs.service.mapper.quality import psnr
        from agilegs.service.nbv import GaussianMap, render

        torch = self._torch
        gmap = GaussianMap(**{k: torch.from_numpy(v.copy()) for k, v in arrays.items()})
        bg = torch.tensor(self.background, dtype=gmap.dtype)
        vals = []
        with torch.no_grad():
            for i in range(self.test_poses.shape[0]):
                out = render(gmap, self.scene.test_camera(i), background=bg)
                vals.append(psnr(out.rgb.clamp(0, 1).float(), self.scene.test_images[i]))
        return float(sum(vals) / len(vals))


def load_capture(scene: str, width: int, test_count: int, seed: int,
                 init_points: int = 5000) -> BenchScene:
    """The capture at ``scene`` as the demo sees it: images ``width`` pixels wide, every pool
    frame kept in capture order, at most ``test_count`` test frames, ``init_points`` random
    points where the capture has none of its own."""
    from agilegs.lab.bench.scene_model import SceneOptions
    from agilegs.lab.bench.scenes import load_bench_scene

    opts = SceneOptions(width=width, height=width, pool_size=100_000, test_count=test_count,
                        seed=seed, random_init_points=init_points)
    return load_bench_scene(scene, opts)
