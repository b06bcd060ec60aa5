"""What the viewer draws, as numpy (no viser, no torch): Gaussians as splat parameters or
points, poses as viser transforms, scores as colours, the scene's size and up direction.

Conventions are the service's (``docs/conventions.md``): poses camera-to-world with OpenCV
axes, which viser's frustums share; Gaussians ``means [N,3]``, ``log_scales [N,3]``,
``quats [N,4]`` (w, x, y, z), ``opacity_logits [N]``, ``sh [N,K,3]`` (DC first).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

__all__ = [
    "C0",
    "GREY",
    "colormap",
    "frustum_fov",
    "map_colors",
    "pose_wxyz_position",
    "scene_extent",
    "score_colors",
    "splat_parameters",
    "up_direction",
]

C0 = 0.28209479177387814
"""The degree-0 spherical harmonic (colour = 0.5 + C0 * DC)."""

GREY = (185, 185, 185)
"""A candidate without a score."""

# viridis at 0, 1/4, 1/2, 3/4, 1 (colour-blind safe, dark = low, yellow = high)
_STOPS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]],
                  dtype=np.float64)


def colormap(t: np.ndarray) -> np.ndarray:
    """Colours uint8 [..., 3] of values ``t`` in [0, 1] (clipped), dark to yellow."""
    x = np.clip(np.asarray(t, dtype=np.float64), 0.0, 1.0) * (len(_STOPS) - 1)
    i = np.minimum(np.floor(x).astype(np.int64), len(_STOPS) - 2)
    f = (x - i)[..., None]
    return np.rint(_STOPS[i] * (1 - f) + _STOPS[i + 1] * f).astype(np.uint8)


def score_colors(scores: Mapping[int, float | None]) -> dict[int, tuple[int, int, int]]:
    """Each scored candidate's colour, its score scaled between the lowest and the highest
    of ``scores`` (a candidate with score None is :data:`GREY`)."""
    ids = [k for k, v in scores.items() if v is not None and math.isfinite(v)]
    out: dict[int, tuple[int, int, int]] = {k: GREY for k in scores}
    if not ids:
        return out
    vals = np.array([float(scores[k]) for k in ids])  # type: ignore[arg-type]
    lo, hi = float(vals.min()), float(vals.max())
    t = (vals - lo) / (hi - lo) if hi > lo else np.ones_like(vals)
    for k, c in zip(ids, colormap(t), strict=True):
        out[k] = (int(c[0]), int(c[1]), int(c[2]))
    return out


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.clip(x, -60.0, 60.0)))


def map_colors(sh: np.ndarray) -> np.ndarray:
    """RGB in [0, 1] [N, 3] from the DC band of ``sh [N, K, 3]``."""
    return np.clip(0.5 + C0 * np.asarray(sh, dtype=np.float64)[:, 0, :], 0.0, 1.0)


def splat_parameters(arrays: Mapping[str, np.ndarray]
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """viser's splat inputs from the five Gaussian arrays.

    Returns:
        centers [N, 3], covariances [N, 3, 3] (R diag(s²) Rᵀ), rgbs [N, 3] in [0, 1],
        opacities [N, 1] in [0, 1].
    """
    means = np.asarray(arrays["means"], dtype=np.float64)
    scales = np.exp(np.asarray(arrays["log_scales"], dtype=np.float64))
    q = np.asarray(arrays["quats"], dtype=np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    rot = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)
    m = rot * scales[:, None, :]
    cov = m @ np.transpose(m, (0, 2, 1))
    opacity = _sigmoid(np.asarray(arrays["opacity_logits"], dtype=np.float64))[:, None]
    return means, cov, map_colors(arrays["sh"]), opacity


def pose_wxyz_position(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A camera-to-world pose [4, 4] as viser's (wxyz [4], position [3])."""
    c2w = np.asarray(c2w, dtype=np.float64)
    r = c2w[:3, :3]
    tr = float(np.trace(r))
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1e-12, 1.0 + r[i, i] - r[j, j] - r[k, k]))
        q = [0.0] * 4
        q[0] = (r[k, j] - r[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (r[j, i] + r[i, j]) / s
        q[1 + k] = (r[k, i] + r[i, k]) / s
    wxyz = np.asarray(q)
    return wxyz / np.linalg.norm(wxyz), c2w[:3, 3].copy()


def frustum_fov(intrinsics: Mapping[str, float]) -> tuple[float, float]:
    """(vertical field of view in radians, width / height) of pinhole intrinsics."""
    h, w, fy = float(intrinsics["height"]), float(intrinsics["width"]), float(intrinsics["fy"])
    return 2.0 * math.atan2(h / 2.0, fy), w / h


def scene_extent(*points: np.ndarray) -> tuple[np.ndarray, float]:
    """(centre [3], radius) of the points given (camera centres, means); (0, 1) for none."""
    pts = [np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in points if np.size(p)]
    if not pts:
        return np.zeros(3), 1.0
    allp = np.concatenate(pts)
    centre = np.median(allp, axis=0)
    radius = float(np.percentile(np.linalg.norm(allp - centre, axis=1), 95))
    return centre, radius if radius > 1e-9 else 1.0


def up_direction(poses: np.ndarray) -> np.ndarray | None:
    """The world's up direction as the cameras see it: the mean of their -y axes (OpenCV
    y points down), unit length; None without cameras or when they disagree."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if not len(poses):
        return None
    up = -poses[:, :3, 1].mean(axis=0)
    n = float(np.linalg.norm(up))
    return up / n if n > 0.3 else None
