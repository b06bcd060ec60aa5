"""Rotations in torch: quaternions, axis-angle, rotating vectors (batched, float32 or float64).

Quaternions here are (w, x, y, z), the order of the Gaussians' ``quats``; the wire's
(x, y, z, w) quaternions and COLMAP's are converted with numpy in
:mod:`agilegs.schemas.geometry`. The exponential map of SO(3) and SE(3) is in
:mod:`agilegs.service.nbv.se3`.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["axis_angle_to_matrix", "quat_to_rotmat", "rotate_about_axis"]


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices [..., 3, 3] from quaternions (w, x, y, z) [..., 4], normalised first."""
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def axis_angle_to_matrix(axis: Tensor, angle: Tensor) -> Tensor:
    """Rotation matrices [B, 3, 3] from unit axes [B, 3] and angles [B] (Rodrigues)."""
    b = axis.shape[0]
    k = torch.zeros(b, 3, 3, dtype=axis.dtype, device=axis.device)
    k[:, 0, 1], k[:, 0, 2] = -axis[:, 2], axis[:, 1]
    k[:, 1, 0], k[:, 1, 2] = axis[:, 2], -axis[:, 0]
    k[:, 2, 0], k[:, 2, 1] = -axis[:, 1], axis[:, 0]
    s = torch.sin(angle)[:, None, None]
    c = torch.cos(angle)[:, None, None]
    eye = torch.eye(3, dtype=axis.dtype, device=axis.device).expand(b, 3, 3)
    return eye + s * k + (1 - c) * (k @ k)


def rotate_about_axis(vectors: Tensor, axis: Tensor, angle: Tensor) -> Tensor:
    """Rotate ``vectors`` [..., 3] about unit ``axis`` [..., 3] by ``angle`` [...] (Rodrigues)."""
    a = angle.unsqueeze(-1)
    return (
        vectors * torch.cos(a)
        + torch.cross(axis, vectors, dim=-1) * torch.sin(a)
        + axis * (axis * vectors).sum(-1, keepdim=True) * (1 - torch.cos(a))
    )
