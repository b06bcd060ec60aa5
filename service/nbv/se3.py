"""SO(3) / SE(3) maths for camera poses, batched over leading dimensions.

Conventions:

* A twist ``xi`` [..., 6] is ``[rho, omega]``: ``rho`` (first three) is the translational
  part, ``omega`` (last three) the rotation vector (axis * angle, radians).
* ``hat(xi)`` is the 4x4 matrix ``[[so3_hat(omega), rho], [0, 0]]`` and
  ``se3_exp(xi) = matrix_exp(hat(xi)) = [[R, V rho], [0, 1]]`` with ``R = so3_exp(omega)``
  and ``V`` the SO(3) left Jacobian ``I + (1 - cos t)/t^2 K + (t - sin t)/t^3 K^2``
  (``K = so3_hat(omega)``, ``t = |omega|``).
* ``so3_log`` returns the principal rotation vector, angle in ``[0, pi]``; ``se3_log`` is the
  exact inverse of ``se3_exp`` on twists whose rotation angle is below pi.

Numerics: every coefficient that is 0/0 at zero angle is computed with a Taylor series below
a small angle and with its closed form above, selected by ``torch.where``. The "double where"
trick feeds a safe angle (1) into the closed form wherever the Taylor branch is taken, so
neither branch produces inf/NaN and gradients at a zero twist are finite and exact.
``so3_log`` handles three regimes: near identity (Taylor in sin^2), generic (atan2), and near
pi, where the axis comes from the symmetric part of ``R`` (the antisymmetric part vanishes).

Everything works in float32 and float64 on any device; no tensor is moved.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "so3_hat",
    "so3_vee",
    "so3_exp",
    "so3_log",
    "hat",
    "vee",
    "se3_exp",
    "se3_log",
    "se3_inverse",
    "rotation_angle",
    "pose_distance",
    "project_to_se3",
]

# Below this squared angle (rad^2) the Taylor branches are used. With terms up to t^8 the
# truncation error at t^2 = 1e-2 is ~1e-18 relative: below float64 resolution.
_TAYLOR_T2 = 1e-2
# so3_log: Taylor in s2 = sin^2(t) below this (series to s2^4, error ~1e-22).
_LOG_SMALL_S2 = 1e-4
# so3_log: use the symmetric-part (near pi) branch when cos(t) is below this (t > ~2.5 rad).
_LOG_NEAR_PI_COS = -0.8


def _check_last(x: Tensor, shape: tuple[int, ...], name: str) -> None:
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if tuple(x.shape[x.ndim - len(shape) :]) != shape or x.ndim < len(shape):
        dims = ", ".join(str(s) for s in shape)
        raise ValueError(f"{name} must have shape [..., {dims}], got {list(x.shape)}")


def _poly(x: Tensor, coeffs: tuple[float, ...]) -> Tensor:
    """``sum_k coeffs[k] * x^k`` by Horner's rule."""
    out = torch.full_like(x, coeffs[-1])
    for c in reversed(coeffs[:-1]):
        out = out * x + c
    return out


# Taylor coefficients in t^2.
_A = (1.0, -1.0 / 6, 1.0 / 120, -1.0 / 5040, 1.0 / 362880)  # sin t / t
_B = (0.5, -1.0 / 24, 1.0 / 720, -1.0 / 40320, 1.0 / 3628800)  # (1 - cos t) / t^2
_C = (1.0 / 6, -1.0 / 120, 1.0 / 5040, -1.0 / 362880, 1.0 / 39916800)  # (t - sin t) / t^3
# (1 - (t/2) cot(t/2)) / t^2: the K^2 coefficient of V^-1
_D = (1.0 / 12, 1.0 / 720, 1.0 / 30240, 1.0 / 1209600, 1.0 / 47900160)
# asin(s) / s in s^2 (t / sin t for t < pi/2)
_ASIN = (1.0, 1.0 / 6, 3.0 / 40, 5.0 / 112, 35.0 / 1152)


def _safe_angle(t2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(small, t2_safe, t_safe)``: the Taylor mask and the angle fed to closed forms.

    Where ``small`` (``t2 < _TAYLOR_T2``) the closed forms see the harmless angle 1, so they
    give no inf/NaN values and, through ``torch.where``, no NaN gradients ("double where").
    """
    small = t2 < _TAYLOR_T2
    t2_safe = torch.where(small, torch.ones_like(t2), t2)
    return small, t2_safe, torch.sqrt(t2_safe)


def _coefficients(t2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``A = sin t/t``, ``B = (1-cos t)/t^2``, ``C = (t-sin t)/t^3`` from ``t2 = t^2``."""
    small, t2_safe, t = _safe_angle(t2)
    sin_t = torch.sin(t)
    half = 0.5 * t
    sinc_half = torch.sin(half) / half
    a_big = sin_t / t
    b_big = 0.5 * sinc_half * sinc_half  # 2 sin^2(t/2) / t^2: no cancellation
    c_big = (t - sin_t) / (t2_safe * t)  # cancellation error ~eps/t^2, weighted by t^2 in V
    a = torch.where(small, _poly(t2, _A), a_big)
    b = torch.where(small, _poly(t2, _B), b_big)
    c = torch.where(small, _poly(t2, _C), c_big)
    return a, b, c


def _d_coefficient(t2: Tensor) -> Tensor:
    """``D = (1 - (t/2) cot(t/2)) / t^2`` (the K^2 term of V^-1), finite for t in [0, pi]."""
    small, t2_safe, t = _safe_angle(t2)
    half = 0.5 * t
    d_big = (1.0 - half * torch.cos(half) / torch.sin(half)) / t2_safe
    return torch.where(small, _poly(t2, _D), d_big)


# --------------------------------------------------------------------------------- SO(3)
def so3_hat(omega: Tensor) -> Tensor:
    """Skew-symmetric matrix [..., 3, 3] of ``omega`` [..., 3] (``hat(w) v = w x v``)."""
    _check_last(omega, (3,), "omega")
    x, y, z = omega.unbind(-1)
    o = torch.zeros_like(x)
    rows = [
        torch.stack([o, -z, y], dim=-1),
        torch.stack([z, o, -x], dim=-1),
        torch.stack([-y, x, o], dim=-1),
    ]
    return torch.stack(rows, dim=-2)


def so3_vee(m: Tensor) -> Tensor:
    """Inverse of ``so3_hat``: ``[m21, m02, m10]`` [..., 3] (antisymmetric part, halved)."""
    _check_last(m, (3, 3), "m")
    return 0.5 * torch.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]],
        dim=-1,
    )


def so3_exp(omega: Tensor) -> Tensor:
    """Rotation matrices [..., 3, 3] from rotation vectors ``omega`` [..., 3] (Rodrigues)."""
    _check_last(omega, (3,), "omega")
    k = so3_hat(omega)
    t2 = (omega * omega).sum(-1)
    a, b, _ = _coefficients(t2)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device)
    kk = k @ k
    return eye + a[..., None, None] * k + b[..., None, None] * kk


def so3_log(r: Tensor) -> Tensor:
    """Principal rotation vectors [..., 3] (angle in [0, pi]) of rotations ``r`` [..., 3, 3].

    At exactly pi both ``+pi a`` and ``-pi a`` are valid; the sign follows the (numerically
    tiny) antisymmetric part, ``+`` when it is zero. The gradient is finite at the identity;
    at exactly pi the logarithm is not differentiable.
    """
    _check_last(r, (3, 3), "R")
    s = so3_vee(r)  # sin(t) * axis
    s2 = (s * s).sum(-1)
    tr = r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]
    c = (0.5 * (tr - 1.0)).clamp(-1.0, 1.0)  # cos t

    near_pi = c < _LOG_NEAR_PI_COS
    small = (~near_pi) & (s2 < _LOG_SMALL_S2)
    generic = ~(near_pi | small)

    # generic: t = atan2(|s|, c), omega = t / |s| * s
    s2_safe = torch.where(generic, s2, torch.ones_like(s2))
    sn = torch.sqrt(s2_safe)
    factor_generic = torch.atan2(sn, c) / sn
    # near identity: t / sin t = asin(|s|)/|s| as a series in |s|^2 (t < pi/2 here)
    factor_small = _poly(torch.where(small, s2, torch.zeros_like(s2)), _ASIN)
    factor = torch.where(small, factor_small, factor_generic)
    omega_regular = factor[..., None] * s

    # near pi: (R + R^T)/2 = c I + (1 - c) a a^T; read a off the largest diagonal entry
    denom = torch.where(near_pi, 1.0 - c, torch.ones_like(c))
    sym = 0.5 * (r + r.transpose(-1, -2))
    eye = torch.eye(3, dtype=r.dtype, device=r.device)
    aat = (sym - c[..., None, None] * eye) / denom[..., None, None]
    diag = torch.diagonal(aat, dim1=-2, dim2=-1)  # [..., 3]
    k = diag.argmax(-1, keepdim=True)  # [..., 1]
    col = torch.gather(aat, -1, k[..., None, :].expand(*aat.shape[:-1], 1)).squeeze(-1)
    akk = torch.gather(diag, -1, k).squeeze(-1)
    akk_safe = torch.where(near_pi & (akk > 0), akk, torch.ones_like(akk))
    axis = col / torch.sqrt(akk_safe)[..., None]  # unit for a rotation; renormalise anyway
    an = torch.linalg.vector_norm(axis, dim=-1)
    an_safe = torch.where(near_pi & (an > 0), an, torch.ones_like(an))
    axis = axis / an_safe[..., None]
    sgn = torch.where((axis * s).sum(-1) < 0, -torch.ones_like(c), torch.ones_like(c))
    axis = axis * sgn[..., None]
    t_pi = torch.atan2((axis * s).sum(-1), c)  # sin t = a . s >= 0 with the sign above
    omega_pi = t_pi[..., None] * axis

    return torch.where(near_pi[..., None], omega_pi, omega_regular)


def rotation_angle(r: Tensor) -> Tensor:
    """Geodesic angle [...] in [0, pi] of rotations ``r`` [..., 3, 3] (atan2 form, stable)."""
    _check_last(r, (3, 3), "R")
    s = so3_vee(r)
    s2 = (s * s).sum(-1)
    pos = s2 > 0
    sn = torch.where(pos, torch.sqrt(torch.where(pos, s2, torch.ones_like(s2))), 0.0 * s2)
    tr = r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]
    return torch.atan2(sn, 0.5 * (tr - 1.0))


# --------------------------------------------------------------------------------- SE(3)
def hat(xi: Tensor) -> Tensor:
    """4x4 twist matrices [..., 4, 4] ``[[so3_hat(omega), rho], [0, 0]]`` of ``xi`` [..., 6]."""
    _check_last(xi, (6,), "xi")
    rho, omega = xi[..., :3], xi[..., 3:]
    top = torch.cat([so3_hat(omega), rho[..., None]], dim=-1)  # [..., 3, 4]
    bottom = torch.zeros_like(top[..., :1, :])
    return torch.cat([top, bottom], dim=-2)


def vee(x: Tensor) -> Tensor:
    """Inverse of ``hat``: twists [..., 6] ``[rho, omega]`` from [..., 4, 4]."""
    _check_last(x, (4, 4), "X")
    return torch.cat([x[..., :3, 3], so3_vee(x[..., :3, :3])], dim=-1)


def _compose(r: Tensor, t: Tensor) -> Tensor:
    top = torch.cat([r, t[..., None]], dim=-1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom = bottom + torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=r.dtype, device=r.device)
    return torch.cat([top, bottom], dim=-2)


def se3_exp(xi: Tensor) -> Tensor:
    """Rigid transforms [..., 4, 4] ``[[R, V rho], [0, 1]]`` from twists ``xi`` [..., 6].

    Equal to ``torch.linalg.matrix_exp(hat(xi))``; finite gradients at ``xi = 0``.
    """
    _check_last(xi, (6,), "xi")
    rho, omega = xi[..., :3], xi[..., 3:]
    k = so3_hat(omega)
    kk = k @ k
    t2 = (omega * omega).sum(-1)
    a, b, c = _coefficients(t2)
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    r = eye + a[..., None, None] * k + b[..., None, None] * kk
    v = eye + b[..., None, None] * k + c[..., None, None] * kk
    t = (v @ rho[..., None]).squeeze(-1)
    return _compose(r, t)


def se3_log(t_mat: Tensor) -> Tensor:
    """Twists [..., 6] ``[rho, omega]`` of rigid transforms [..., 4, 4]; inverse of se3_exp.

    The rotation part is the principal logarithm (angle in [0, pi]); ``rho = V^-1 t`` with
    ``V^-1 = I - K/2 + D K^2``, ``D = (1 - (t/2) cot(t/2)) / t^2`` (finite up to pi).
    """
    _check_last(t_mat, (4, 4), "T")
    omega = so3_log(t_mat[..., :3, :3])
    trans = t_mat[..., :3, 3]
    k = so3_hat(omega)
    t2 = (omega * omega).sum(-1)
    d = _d_coefficient(t2)
    eye = torch.eye(3, dtype=t_mat.dtype, device=t_mat.device)
    v_inv = eye - 0.5 * k + d[..., None, None] * (k @ k)
    rho = (v_inv @ trans[..., None]).squeeze(-1)
    return torch.cat([rho, omega], dim=-1)


def se3_inverse(t_mat: Tensor) -> Tensor:
    """Inverse rigid transforms [..., 4, 4]: ``[[R^T, -R^T t], [0, 1]]`` (differentiable)."""
    _check_last(t_mat, (4, 4), "T")
    rt = t_mat[..., :3, :3].transpose(-1, -2)
    t = -(rt @ t_mat[..., :3, 3:4]).squeeze(-1)
    return _compose(rt, t)


def project_to_se3(t_mat: Tensor) -> Tensor:
    """The nearest rigid transforms [..., 4, 4] to near-rigid ones: each rotation block
    replaced by its nearest rotation in the Frobenius norm (``U V^T`` of its SVD, with the
    sign that makes the determinant +1), the translation kept, the last row ``[0, 0, 0, 1]``.
    Not differentiable through the SVD's degenerate cases; meant for inputs, not iterates."""
    _check_last(t_mat, (4, 4), "T")
    m = t_mat[..., :3, :3]
    u, _, vh = torch.linalg.svd(m.double())
    d = torch.linalg.det(u @ vh)
    u = torch.cat([u[..., :, :2], u[..., :, 2:] * d[..., None, None]], dim=-1)
    return _compose((u @ vh).to(t_mat.dtype), t_mat[..., :3, 3])


def pose_distance(t1: Tensor, t2: Tensor, rot_weight: float = 1.0) -> Tensor:
    """Distance [...] between rigid transforms [..., 4, 4] (broadcast over leading dims).

    ``d = ||p1 - p2||_2 + rot_weight * angle(R1^T R2)``: the Euclidean distance between the
    translations (for camera-to-world poses, the camera centres, in world units) plus
    ``rot_weight`` (world units per radian) times the geodesic rotation angle in [0, pi].
    Both terms are metrics, so ``d`` is a metric on SE(3) for ``rot_weight >= 0``; it is what
    the K-nearest-candidate rule uses. Gradients are finite everywhere (zero where a term
    is exactly zero).
    """
    _check_last(t1, (4, 4), "T1")
    _check_last(t2, (4, 4), "T2")
    if not rot_weight >= 0:
        raise ValueError(f"rot_weight must be >= 0, got {rot_weight!r}")
    dp = t1[..., :3, 3] - t2[..., :3, 3]
    n2 = (dp * dp).sum(-1)
    pos = n2 > 0
    trans = torch.where(pos, torch.sqrt(torch.where(pos, n2, torch.ones_like(n2))), 0.0 * n2)
    rel = t1[..., :3, :3].transpose(-1, -2) @ t2[..., :3, :3]
    return trans + rot_weight * rotation_angle(rel)
