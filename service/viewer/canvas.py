"""The viewer's 3D scene on a viser server: the map, the candidate pool, the chosen view,
the anchor and the path of acquired views (shared by the live view and the replay).

Scene tree::

    /map/splats        the Gaussians as splats          (map mode: splats, both)
    /map/points        their means as a point cloud     (map mode: points, both)
    /pool/<id>         one frustum per candidate, coloured by the last selection's score
                       (dark to yellow, grey: no score); the shortlist filled and larger
    /chosen            the chosen view (red, filled)
    /anchor            the anchor pose (orange, filled) and /anchor/to_chosen, a line to it
    /path/views/<k>    the acquired views in order (blue), /path/line through their centres

Every method is thread-safe (the follow loop and viser's GUI callbacks both draw).
"""

from __future__ import annotations

import threading
from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np

from .scene import (
    frustum_fov,
    map_colors,
    pose_wxyz_position,
    scene_extent,
    score_colors,
    splat_parameters,
    up_direction,
)

__all__ = ["ANCHOR", "CHOSEN", "MAP_MODES", "PATH", "PATH_FIRST", "MapMode", "SceneCanvas"]

MapMode = Literal["splats", "points", "splats + points", "hidden"]
MAP_MODES: tuple[MapMode, ...] = ("splats", "points", "splats + points", "hidden")
CHOSEN = (230, 40, 40)
ANCHOR = (255, 140, 0)
PATH = (40, 90, 220)
PATH_FIRST = (160, 190, 250)


class SceneCanvas:
    """The 3D scene of one viewer (see the module docstring).

    Args:
        server: the ``viser.ViserServer`` to draw on.
        max_frustums: most candidate frustums drawn (the rest are counted, not drawn).
    """

    def __init__(self, server: Any, *, max_frustums: int = 2000) -> None:
        self.server = server
        self.scene = server.scene
        self.max_frustums = max_frustums
        self.lock = threading.RLock()
        self.fov, self.aspect = 0.9, 1.0
        self.size = 0.1  # frustum scale (scene units), from the scene's extent
        self.point_size = 0.01
        self.map_mode: MapMode = "splats"
        self.map_count = 0
        self.splats: Any = None
        self.points: Any = None
        self.pool: dict[int, Any] = {}
        self.pool_poses: dict[int, np.ndarray] = {}
        self.pool_hidden = 0  # candidates beyond max_frustums
        self.colors: dict[int, tuple[int, int, int]] = {}
        self.shortlist: set[int] = set()
        self.chosen: Any = None
        self.anchor: Any = None
        self.anchor_line: Any = None
        self.views: list[Any] = []
        self.path_line: Any = None
        self.show_pool = True
        self.show_path = True
        self._arrays: Mapping[str, np.ndarray] | None = None
        self._up_set = False

    # ------------------------------------------------------------------ geometry
    def set_camera(self, intrinsics: Mapping[str, float]) -> None:
        """The frustums' field of view and aspect, from the session's intrinsics."""
        with self.lock:
            self.fov, self.aspect = frustum_fov(intrinsics)

    def fit(self, poses: np.ndarray, means: np.ndarray | None = None, *, orient: bool = True
            ) -> None:
        """Size frustums and points to the scene (the cameras' spread, or the map's when
        larger); with ``orient``, set the world's up direction from the cameras' orientations
        and the initial view to take in the cameras and the map (once)."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        pts = np.zeros((0, 3)) if means is None else np.asarray(means, np.float64).reshape(-1, 3)
        c_centre, c_radius = scene_extent(poses[:, :3, 3])
        m_centre, m_radius = scene_extent(pts)
        centre = m_centre if len(pts) else c_centre
        radius = max(c_radius if len(poses) else 0.0, m_radius if len(pts) else 0.0, 1e-6)
        if not len(poses) and not len(pts):
            radius = 1.0
        with self.lock:
            self.size = 0.06 * radius
            self.point_size = 0.008 * radius
            if orient and not self._up_set and len(poses):
                up = up_direction(poses)
                if up is not None:
                    self.scene.set_up_direction(up)
                    side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else
                                    [0.0, 0.0, 1.0])
                    side /= np.linalg.norm(side)
                    eye = centre + radius * (1.5 * side + 1.0 * up)  # above, the ring in view
                    self.server.initial_camera.position = tuple(float(x) for x in eye)
                    self.server.initial_camera.look_at = tuple(float(x) for x in centre)
                    self._up_set = True

    def _frustum(self, name: str, pose: np.ndarray, color: tuple[int, int, int],
                 scale: float, filled: bool = False, visible: bool = True) -> Any:
        wxyz, pos = pose_wxyz_position(pose)
        return self.scene.add_camera_frustum(
            name, fov=self.fov, aspect=self.aspect, scale=scale, color=color,
            thickness=0.06 * scale, wxyz=wxyz, position=pos, visible=visible,
            variant="filled" if filled else "wireframe", cast_shadow=False,
            receive_shadow=False)

    # ------------------------------------------------------------------ the map
    def set_map(self, arrays: Mapping[str, np.ndarray] | None) -> None:
        """Replace the map (None: remove it); drawn as the map mode says."""
        with self.lock:
            self._arrays = arrays
            self.map_count = 0 if arrays is None else int(np.asarray(arrays["means"]).shape[0])
            self._draw_map()

    def set_map_mode(self, mode: MapMode) -> None:
        if mode not in MAP_MODES:
            raise ValueError(f"map mode must be one of {MAP_MODES}, got {mode!r}")
        with self.lock:
            self.map_mode = mode
            self._draw_map()

    def _draw_map(self) -> None:
        for h in (self.splats, self.points):
            if h is not None:
                h.remove()
        self.splats = self.points = None
        arrays = self._arrays
        if arrays is None or self.map_count == 0 or self.map_mode == "hidden":
            return
        if self.map_mode in ("splats", "splats + points"):
            centers, cov, rgb, opacity = splat_parameters(arrays)
            self.splats = self.scene.add_gaussian_splats(
                "/map/splats", centers=centers.astype(np.float32), covariances=cov,
                rgbs=rgb, opacities=opacity)
        if self.map_mode in ("points", "splats + points"):
            means = np.asarray(arrays["means"], dtype=np.float32)
            colors = (map_colors(arrays["sh"]) * 255 + 0.5).astype(np.uint8)
            self.points = self.scene.add_point_cloud(
                "/map/points", points=means, colors=colors, point_size=self.point_size,
                point_shape="circle", precision="float32")

    # ------------------------------------------------------------------ the pool
    def set_pool(self, ids: Sequence[int], poses: np.ndarray) -> None:
        """The candidate pool (ids, poses [D, 4, 4]): frustums added and removed to match."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        with self.lock:
            want = {int(i): poses[k] for k, i in enumerate(ids)}
            keep = list(want)[: self.max_frustums]
            self.pool_hidden = len(want) - len(keep)
            for cid in [c for c in self.pool if c not in want or c not in keep]:
                self.pool.pop(cid).remove()
                self.pool_poses.pop(cid, None)
            for cid in keep:
                old = self.pool_poses.get(cid)
                if old is not None and np.array_equal(old, want[cid]):
                    continue
                if cid in self.pool:
                    self.pool.pop(cid).remove()
                self.pool[cid] = self._frustum(f"/pool/{cid}", want[cid], self._color(cid),
                                               self._scale(cid), cid in self.shortlist,
                                               self.show_pool)
                self.pool_poses[cid] = want[cid]

    def color_pool(self, scores: Mapping[int, float | None], shortlist: Sequence[int]) -> None:
        """Colour the candidates by ``scores`` (id -> score) and highlight ``shortlist``."""
        with self.lock:
            self.colors = score_colors(scores)
            self.shortlist = {int(i) for i in shortlist}
            for cid, h in self.pool.items():
                h.color = self._color(cid)
                h.scale = self._scale(cid)
                h.variant = "filled" if cid in self.shortlist else "wireframe"

    def _color(self, cid: int) -> tuple[int, int, int]:
        return self.colors.get(cid, (185, 185, 185))

    def _scale(self, cid: int) -> float:
        return self.size * (1.5 if cid in self.shortlist else 1.0)

    def set_pool_visible(self, visible: bool) -> None:
        with self.lock:
            self.show_pool = visible
            for h in self.pool.values():
                h.visible = visible

    # ------------------------------------------------------------------ the decision
    def set_decision(self, chosen: np.ndarray | None, anchor: np.ndarray | None) -> None:
        """The chosen view's pose [4, 4] and the anchor's (None: not shown)."""
        with self.lock:
            for h in (self.chosen, self.anchor, self.anchor_line):
                if h is not None:
                    h.remove()
            self.chosen = self.anchor = self.anchor_line = None
            if chosen is not None:
                self.chosen = self._frustum("/chosen", chosen, CHOSEN, self.size * 2.0, True)
            if anchor is not None:
                self.anchor = self._frustum("/anchor", anchor, ANCHOR, self.size * 1.6, True)
                if chosen is not None:
                    seg = np.stack([np.asarray(anchor)[:3, 3], np.asarray(chosen)[:3, 3]])[None]
                    self.anchor_line = self.scene.add_line_segments(
                        "/anchor_to_chosen", points=seg.astype(np.float32), colors=ANCHOR,
                        thickness=2.0, thickness_units="screen")

    # ------------------------------------------------------------------ the path
    def set_path(self, poses: Sequence[np.ndarray]) -> None:
        """The acquired views in order (poses [4, 4]): frustums and a line through them."""
        with self.lock:
            for h in self.views:
                h.remove()
            if self.path_line is not None:
                self.path_line.remove()
            self.views, self.path_line = [], None
            n = len(poses)
            for k, pose in enumerate(poses):
                t = (k + 1) / n  # the first views light, the latest PATH blue
                c = np.rint(np.multiply(PATH_FIRST, 1 - t) + np.multiply(PATH, t)).astype(int)
                self.views.append(self._frustum(
                    f"/path/views/{k}", pose, (int(c[0]), int(c[1]), int(c[2])),
                    self.size * 1.1, visible=self.show_path))
            if n >= 2:
                centres = np.stack([np.asarray(p)[:3, 3] for p in poses]).astype(np.float32)
                seg = np.stack([centres[:-1], centres[1:]], axis=1)
                self.path_line = self.scene.add_line_segments(
                    "/path/line", points=seg, colors=PATH, thickness=2.0,
                    thickness_units="screen", visible=self.show_path)

    def set_path_visible(self, visible: bool) -> None:
        with self.lock:
            self.show_path = visible
            for h in [*self.views, self.path_line]:
                if h is not None:
                    h.visible = visible
