"""Real spherical harmonics up to degree 3, with the constants and sign conventions of the
reference 3D Gaussian Splatting implementation (``eval_sh`` in its ``sh_utils``)."""

from __future__ import annotations

import torch
from torch import Tensor

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Basis values Y_k(dir) for k < (degree+1)^2.

    Args:
        degree: SH degree, 0 to 3.
        dirs: unit viewing directions [..., 3].

    Returns:
        basis [..., (degree+1)^2], ordered as the reference implementation's coefficients.
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"degree must be in 0..3, got {degree}")
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [
            C2[0] * xy,
            C2[1] * yz,
            C2[2] * (2.0 * zz - xx - yy),
            C2[3] * xz,
            C2[4] * (xx - yy),
        ]
        if degree >= 3:
            out += [
                C3[0] * y * (3 * xx - yy),
                C3[1] * xy * z,
                C3[2] * y * (4 * zz - xx - yy),
                C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
                C3[4] * x * (4 * zz - xx - yy),
                C3[5] * z * (xx - yy),
                C3[6] * x * (xx - 3 * yy),
            ]
    return torch.stack(out, dim=-1)


def eval_sh_colors(sh: Tensor, dirs: Tensor) -> Tensor:
    """Colour = max(0, 0.5 + sum_k Y_k(dir) sh_k), as the reference rasterizer.

    Args:
        sh: coefficients [N, (d+1)^2, 3].
        dirs: unit directions from the camera centre to each Gaussian [N, 3].

    Returns:
        colours [N, 3], clamped below at 0 (not above).
    """
    k = sh.shape[-2]
    degree = int(round(k**0.5)) - 1
    basis = sh_basis(degree, dirs)  # [N, K]
    rgb = (basis[..., :, None] * sh).sum(dim=-2) + 0.5
    return torch.clamp_min(rgb, 0.0)
