"""EWA projection of 3D Gaussians into a pinhole camera (the first stage of the rasterizer).

As the reference 3D Gaussian Splatting rasterizer (Kerbl et al. 2023): 2D covariance
J W Σ Wᵀ Jᵀ + 0.3 I (the low-pass filter), with the reference's clamp of x/z and y/z to 1.3
times the half field of view when forming J; Gaussians with camera depth ≤ ``near`` (default
0.01 scene units; the reference uses 0.2 m) or a singular 2D covariance are culled; screen
radius = ceil(3 sqrt(λ_max)) pixels; colour from spherical harmonics up to degree 3.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from agilegs.service.nbv.camera import Camera
from agilegs.service.nbv.gaussians import GaussianMap
from agilegs.service.nbv.rotations import quat_to_rotmat
from agilegs.service.nbv.sh import eval_sh_colors

__all__ = ["LOWPASS", "Projected", "covariance_3d", "project_gaussians", "project_map"]

LOWPASS = 0.3


@dataclass
class Projected:
    """Per-Gaussian screen-space quantities for one camera.

    Attributes:
        means2d: pixel-space centres [N, 2].
        conics: inverse 2D covariance as (a, b, c) = (Σ⁻¹₀₀, Σ⁻¹₀₁, Σ⁻¹₁₁) [N, 3].
        depths: camera-space z [N].
        radii: screen radius in pixels, 0 where culled [N] (int).
        colors: view-dependent colours [N, 3].
        opacities: sigmoid(opacity_logits) [N].
        cov2d: 2D covariance (with the low-pass) as (Σ₀₀, Σ₀₁, Σ₁₁) [N, 3].
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    radii: Tensor
    colors: Tensor
    opacities: Tensor
    cov2d: Tensor



def covariance_3d(log_scales: Tensor, quats: Tensor) -> Tensor:
    """World covariance R diag(s²) Rᵀ [N, 3, 3]."""
    r = quat_to_rotmat(quats)
    m = r * torch.exp(log_scales)[..., None, :]
    return m @ m.transpose(-1, -2)


def project_gaussians(
    means: Tensor,
    log_scales: Tensor,
    quats: Tensor,
    opacity_logits: Tensor,
    sh: Tensor,
    camera: Camera,
    *,
    near: float = 0.01,
) -> Projected:
    """EWA-project every Gaussian into ``camera`` (differentiable in all inputs and the pose).

    Args:
        means: [N, 3]; log_scales: [N, 3]; quats: [N, 4] (w, x, y, z); opacity_logits: [N];
        sh: [N, K, 3]; camera: the view (its ``c2w`` may require grad).
        near: Gaussians with camera depth ≤ near are culled.
    """
    w2c = camera.w2c.to(means.dtype)
    rot = w2c[:3, :3]
    p = means @ rot.transpose(0, 1) + w2c[:3, 3]
    z = p[:, 2]
    in_front = z > near
    zs = torch.where(in_front, z, torch.ones_like(z))  # safe depth: avoids NaN/inf gradients
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    width, height = camera.width, camera.height
    x_over_z = p[:, 0] / zs
    y_over_z = p[:, 1] / zs
    means2d = torch.stack([fx * x_over_z + cx, fy * y_over_z + cy], dim=-1)
    # the reference clamps the Jacobian's x/z, y/z to 1.3 x the half field of view
    lim_x_lo, lim_x_hi = (-cx - 0.15 * width) / fx, (width - cx + 0.15 * width) / fx
    lim_y_lo, lim_y_hi = (-cy - 0.15 * height) / fy, (height - cy + 0.15 * height) / fy
    tx = x_over_z.clamp(lim_x_lo, lim_x_hi) * zs
    ty = y_over_z.clamp(lim_y_lo, lim_y_hi) * zs
    zero = torch.zeros_like(zs)
    jac = torch.stack(
        [
            torch.stack([fx / zs, zero, -fx * tx / (zs * zs)], dim=-1),
            torch.stack([zero, fy / zs, -fy * ty / (zs * zs)], dim=-1),
        ],
        dim=-2,
    )  # [N, 2, 3]
    cov3 = covariance_3d(log_scales, quats)
    t = jac @ rot
    cov2 = t @ cov3 @ t.transpose(-1, -2)
    c00 = cov2[:, 0, 0] + LOWPASS
    c01 = cov2[:, 0, 1]
    c11 = cov2[:, 1, 1] + LOWPASS
    det = c00 * c11 - c01 * c01
    ok = in_front & (det > 0)
    det_s = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c11 / det_s, -c01 / det_s, c00 / det_s], dim=-1)
    with torch.no_grad():
        mid = 0.5 * (c00 + c11)
        lam = mid + torch.sqrt(torch.clamp_min(mid * mid - det, 0.1))
        radii = torch.ceil(3.0 * torch.sqrt(lam.clamp_min(0)))
        u, v = means2d[:, 0], means2d[:, 1]
        on_screen = (u + radii > 0) & (u - radii < width) & (v + radii > 0) & (v - radii < height)
        keep = ok & on_screen & torch.isfinite(radii) & (radii > 0)
        radii = torch.where(keep, radii, torch.zeros_like(radii)).to(torch.int64)
    cam_pos = camera.c2w[:3, 3].to(means.dtype)
    dirs = means - cam_pos
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    colors = eval_sh_colors(sh, dirs)
    return Projected(
        means2d=means2d,
        conics=conics,
        depths=z,
        radii=radii,
        colors=colors,
        opacities=torch.sigmoid(opacity_logits),
        cov2d=torch.stack([c00, c01, c11], dim=-1),
    )


def project_map(gmap: GaussianMap, camera: Camera, *, near: float = 0.01) -> Projected:
    """:func:`project_gaussians` on the fields of ``gmap``."""
    g = gmap
    return project_gaussians(
        g.means, g.log_scales, g.quats, g.opacity_logits, g.sh, camera, near=near
    )
