"""Gaussians from points: depth maps back-projected, and isotropic scales from neighbours."""

from __future__ import annotations

import torch
from torch import Tensor

from agilegs.service.nbv import Camera

__all__ = ["backproject_depth", "nearest_neighbour_scales"]


def backproject_depth(
    camera: Camera,
    depth: Tensor,
    image: Tensor | None = None,
    *,
    stride: int = 1,
    mask: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """World points of the pixels of a depth map (depth along the optical axis, camera z).

    Pixel (row v, column u) is back-projected through its centre (u + 0.5, v + 0.5):
    X_cam = ((u + 0.5 - cx) / fx · d, (v + 0.5 - cy) / fy · d, d), X = c2w X_cam.

    Args:
        camera: the view (OpenCV axes).
        depth: [H, W]; pixels with depth ≤ 0 or non-finite are skipped.
        image: colours [H, W, 3] in [0, 1] (None: grey 0.5).
        stride: take every ``stride``-th pixel in each direction (grid starting at
            ``stride // 2``).
        mask: optional bool [H, W]: only these pixels.

    Returns:
        (points [M, 3], colors [M, 3]) in the dtype/device of ``depth``.
    """
    h, w = camera.height, camera.width
    if depth.shape != (h, w):
        raise ValueError(
            f"depth must have shape [{h}, {w}] (the camera's), got {list(depth.shape)}"
        )
    if image is not None and image.shape != (h, w, 3):
        raise ValueError(f"image must have shape [{h}, {w}, 3], got {list(image.shape)}")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    dt = depth.dtype if depth.dtype.is_floating_point else torch.float32
    dev = depth.device
    vs = torch.arange(stride // 2, h, stride, device=dev)
    us = torch.arange(stride // 2, w, stride, device=dev)
    vv, uu = torch.meshgrid(vs, us, indexing="ij")
    d = depth.to(dt)[vv, uu]
    ok = torch.isfinite(d) & (d > 0)
    if mask is not None:
        if mask.shape != (h, w):
            raise ValueError(f"mask must have shape [{h}, {w}], got {list(mask.shape)}")
        ok = ok & mask.to(dev)[vv, uu]
    d, uu, vv = d[ok], uu[ok], vv[ok]
    x = (uu.to(dt) + 0.5 - camera.cx) / camera.fx * d
    y = (vv.to(dt) + 0.5 - camera.cy) / camera.fy * d
    pc = torch.stack([x, y, d], dim=-1)
    c2w = camera.c2w.detach().to(device=dev, dtype=dt)
    pts = pc @ c2w[:3, :3].T + c2w[:3, 3]
    if image is None:
        cols = torch.full_like(pts, 0.5)
    else:
        cols = image.detach().to(device=dev, dtype=dt)[vv, uu]
    return pts, cols


def nearest_neighbour_scales(points: Tensor, k: int = 3, *, min_scale: float = 1e-7) -> Tensor:
    """Initial Gaussian scale per point [P]: sqrt of the mean squared distance to its ``k``
    nearest neighbours (the reference's ``distCUDA2`` rule), at least ``min_scale``."""
    p = points.shape[0]
    if p == 0:
        return points.new_zeros(0)
    if p == 1:
        return points.new_full((1,), 0.01)
    kk = min(k, p - 1)
    d2: Tensor
    try:
        from scipy.spatial import cKDTree

        arr = points.detach().cpu().double().numpy()
        dist, _ = cKDTree(arr).query(arr, k=kk + 1)
        d2 = torch.as_tensor(dist[:, 1:] ** 2, dtype=points.dtype, device=points.device)
    except ImportError:  # pragma: no cover - scipy comes with scikit-image
        chunk = max(1, (1 << 24) // p)
        parts = []
        pts = points.detach()
        for s in range(0, p, chunk):
            dd = torch.cdist(pts[s : s + chunk], pts).pow(2)
            dd[torch.arange(dd.shape[0]), torch.arange(s, s + dd.shape[0])] = float("inf")
            parts.append(dd.topk(kk, dim=1, largest=False).values)
        d2 = torch.cat(parts)
    return d2.reshape(p, -1).mean(dim=1).clamp_min(min_scale**2).sqrt()


# ----------------------------------------------------------------------------- the mapper
