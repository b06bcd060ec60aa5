"""The per-Gaussian kernels: the projection (:func:`project`), its vector-Jacobian product
(:func:`project_backward`), every Gaussian's Jacobian (:func:`jacobians`), and the Fisher's
chain to the parameter blocks (:func:`fisher_chain`), all on one analytic per-Gaussian
projection and Jacobian (:func:`_gaussian`)."""

from __future__ import annotations

import math

import numpy as np

from .common import FWD, LOWPASS
from .common import jit as _jit

_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C20, _C21, _C22, _C23, _C24 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                                -1.0925484305920792, 0.5462742152960396)
_C30, _C31, _C32, _C33, _C34, _C35, _C36 = (-0.5900435899266435, 2.890611442640554,
                                            -0.4570457994644658, 0.3731763325901154,
                                            -0.4570457994644658, 1.445305721320277,
                                            -0.5900435899266435)


@_jit
def _sh_basis(x: float, y: float, z: float, nk: int, out: np.ndarray) -> None:
    """Y_k(x, y, z) for k < nk (the reference's order and constants) into out[:nk]."""
    out[0] = _C0
    if nk > 1:
        out[1] = -_C1 * y
        out[2] = _C1 * z
        out[3] = -_C1 * x
    if nk > 4:
        xx, yy, zz = x * x, y * y, z * z
        out[4] = _C20 * x * y
        out[5] = _C21 * y * z
        out[6] = _C22 * (2.0 * zz - xx - yy)
        out[7] = _C23 * x * z
        out[8] = _C24 * (xx - yy)
        if nk > 9:
            out[9] = _C30 * y * (3.0 * xx - yy)
            out[10] = _C31 * x * y * z
            out[11] = _C32 * y * (4.0 * zz - xx - yy)
            out[12] = _C33 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
            out[13] = _C34 * x * (4.0 * zz - xx - yy)
            out[14] = _C35 * z * (xx - yy)
            out[15] = _C36 * x * (xx - 3.0 * yy)


@_jit
def _sh_basis_grad(x: float, y: float, z: float, nk: int, out: np.ndarray) -> None:
    """∂Y_k/∂(x, y, z) for k < nk into out[:nk, 3]."""
    for k in range(nk):
        out[k, 0] = 0.0
        out[k, 1] = 0.0
        out[k, 2] = 0.0
    if nk > 1:
        out[1, 1] = -_C1
        out[2, 2] = _C1
        out[3, 0] = -_C1
    if nk > 4:
        xx, yy, zz = x * x, y * y, z * z
        out[4, 0], out[4, 1] = _C20 * y, _C20 * x
        out[5, 1], out[5, 2] = _C21 * z, _C21 * y
        out[6, 0], out[6, 1], out[6, 2] = -2.0 * _C22 * x, -2.0 * _C22 * y, 4.0 * _C22 * z
        out[7, 0], out[7, 2] = _C23 * z, _C23 * x
        out[8, 0], out[8, 1] = 2.0 * _C24 * x, -2.0 * _C24 * y
        if nk > 9:
            out[9, 0], out[9, 1] = _C30 * 6.0 * x * y, _C30 * (3.0 * xx - 3.0 * yy)
            out[10, 0], out[10, 1], out[10, 2] = _C31 * y * z, _C31 * x * z, _C31 * x * y
            out[11, 0] = _C32 * (-2.0 * x * y)
            out[11, 1] = _C32 * (4.0 * zz - xx - 3.0 * yy)
            out[11, 2] = _C32 * 8.0 * y * z
            out[12, 0] = _C33 * (-6.0 * x * z)
            out[12, 1] = _C33 * (-6.0 * y * z)
            out[12, 2] = _C33 * (6.0 * zz - 3.0 * xx - 3.0 * yy)
            out[13, 0] = _C34 * (4.0 * zz - 3.0 * xx - yy)
            out[13, 1] = _C34 * (-2.0 * x * y)
            out[13, 2] = _C34 * 8.0 * x * z
            out[14, 0], out[14, 1], out[14, 2] = _C35 * 2.0 * x * z, -_C35 * 2.0 * y * z, \
                _C35 * (xx - yy)
            out[15, 0], out[15, 1] = _C36 * (3.0 * xx - 3.0 * yy), _C36 * (-6.0 * x * y)


@_jit
def _conic_diff(ok: bool, idet: float, c00: float, c01: float, c11: float,
                d00: float, d01: float, d11: float) -> tuple[float, float, float]:
    """Derivative of the conic (c11, -c01, c00) / det along a change (d00, d01, d11) of the
    2D covariance (``idet`` = 1 / det; det replaced by 1 where the Gaussian is culled, as the
    projection does)."""
    if not ok:
        return d11, -d01, d00
    dd = (c11 * d00 + c00 * d11 - 2.0 * c01 * d01) * idet
    return (d11 - c11 * dd) * idet, -(d01 - c01 * dd) * idet, (d00 - c00 * dd) * idet


JAC_MEANS = 1
JAC_SCALES = 2
JAC_QUATS = 4
JAC_ALL = 7


@_jit
def _jac_means(i: int, sh: np.ndarray, cam: np.ndarray, fwd: np.ndarray, jac: np.ndarray,
               dbasis: np.ndarray, xz: float, yz: float, izs: float, in_front: bool,
               cl_x: float, cl_y: float, ok: bool, idet: float, c00: float, c01: float,
               c11: float, r00: float, r01: float, r02: float, r10: float, r11: float,
               r12: float, r20: float, r21: float, r22: float, a0: float, a1: float, a2: float,
               b0: float, b1: float, b2: float, e0: float, e1: float, e2: float, nrm: float,
               inr: float) -> None:
    """The Jacobian's mean columns of Gaussian i (:func:`_gaussian`'s names): through p, the
    2D mean and the EWA Jacobian; the depth; the viewing direction."""
    w0, w1, w2, w3, w4, w5, w6, w7, w8 = (cam[0], cam[1], cam[2], cam[3], cam[4], cam[5],
                                          cam[6], cam[7], cam[8])
    fx, fy = cam[15], cam[16]
    lxlo, lxhi, lylo, lyhi = cam[22], cam[23], cam[24], cam[25]
    j00 = fx * izs
    j11 = fy * izs
    nk = sh.shape[1]
    # U_a = Σ T_aᵀ (Σ the 3D covariance): dc_ab = dT_a·U_b + dT_b·U_a
    u00 = r00 * a0 + r01 * a1 + r02 * a2
    u01 = r10 * a0 + r11 * a1 + r12 * a2
    u02 = r20 * a0 + r21 * a1 + r22 * a2
    u10 = r00 * b0 + r01 * b1 + r02 * b2
    u11 = r10 * b0 + r11 * b1 + r12 * b2
    u12 = r20 * b0 + r21 * b1 + r22 * b2
    inx = lxlo <= xz <= lxhi
    iny = lylo <= yz <= lyhi
    _sh_basis_grad(e0, e1, e2, nk, dbasis)
    g00 = g01 = g02 = g10 = g11 = g12 = g20 = g21 = g22 = 0.0
    for k in range(nk):
        s_r, s_g, s_b = float(sh[i, k, 0]), float(sh[i, k, 1]), float(sh[i, k, 2])
        g00 += s_r * dbasis[k, 0]
        g01 += s_r * dbasis[k, 1]
        g02 += s_r * dbasis[k, 2]
        g10 += s_g * dbasis[k, 0]
        g11 += s_g * dbasis[k, 1]
        g12 += s_g * dbasis[k, 2]
        g20 += s_b * dbasis[k, 0]
        g21 += s_b * dbasis[k, 1]
        g22 += s_b * dbasis[k, 2]
    # ∂dir/∂m = (I - dir dirᵀ) / |d| (I / 1e-12 below the norm's clamp)
    big = 1.0 if nrm > 1e-12 else 0.0
    gd0 = (g00 * e0 + g01 * e1 + g02 * e2) * big
    gd1 = (g10 * e0 + g11 * e1 + g12 * e2) * big
    gd2 = (g20 * e0 + g21 * e1 + g22 * e2) * big
    mr = fwd[14] * inr
    mg = fwd[15] * inr
    mb = fwd[16] * inr
    for j in range(3):
        dpx = cam[j]
        dpy = cam[3 + j]
        dpz = cam[6 + j]
        dzs = dpz if in_front else 0.0
        dxz = (dpx - xz * dzs) * izs
        dyz = (dpy - yz * dzs) * izs
        jac[0, j] = fx * dxz
        jac[1, j] = fy * dyz
        dclx = dxz if inx else 0.0
        dcly = dyz if iny else 0.0
        # d(fx/z) and d(-fx X / z) with X the clamped x/z
        dj00 = -j00 * dzs * izs
        dj11 = -j11 * dzs * izs
        dj02 = -fx * (dclx - cl_x * dzs * izs) * izs
        dj12 = -fy * (dcly - cl_y * dzs * izs) * izs
        dt00, dt01, dt02 = dj00 * w0 + dj02 * w6, dj00 * w1 + dj02 * w7, \
            dj00 * w2 + dj02 * w8
        dt10, dt11, dt12 = dj11 * w3 + dj12 * w6, dj11 * w4 + dj12 * w7, \
            dj11 * w5 + dj12 * w8
        dc00 = 2.0 * (dt00 * u00 + dt01 * u01 + dt02 * u02)
        dc01 = (dt00 * u10 + dt01 * u11 + dt02 * u12) + (dt10 * u00 + dt11 * u01
                                                         + dt12 * u02)
        dc11 = 2.0 * (dt10 * u10 + dt11 * u11 + dt12 * u12)
        da, db, dc = _conic_diff(ok, idet, c00, c01, c11, dc00, dc01, dc11)
        jac[2, j] = da
        jac[3, j] = db
        jac[4, j] = dc
        ej = e0 if j == 0 else (e1 if j == 1 else e2)
        gj0 = g00 if j == 0 else (g01 if j == 1 else g02)
        gj1 = g10 if j == 0 else (g11 if j == 1 else g12)
        gj2 = g20 if j == 0 else (g21 if j == 1 else g22)
        jac[6, j] = mr * (gj0 - ej * gd0)
        jac[7, j] = mg * (gj1 - ej * gd1)
        jac[8, j] = mb * (gj2 - ej * gd2)
        jac[9, j] = dpz


@_jit
def _jac_scales(jac: np.ndarray, ok: bool, idet: float, c00: float, c01: float, c11: float,
                q_0: float, q_1: float, q_2: float, v00: float, v01: float, v02: float,
                v10: float, v11: float, v12: float) -> None:
    """The Jacobian's log-scale columns (:func:`_gaussian`'s names)."""
    # dΣ = 2 s_k² r_k r_kᵀ
    for k in range(3):
        qk = q_0 if k == 0 else (q_1 if k == 1 else q_2)
        va = v00 if k == 0 else (v01 if k == 1 else v02)
        vb = v10 if k == 0 else (v11 if k == 1 else v12)
        da, db, dc = _conic_diff(ok, idet, c00, c01, c11, 2.0 * qk * va * va,
                                 2.0 * qk * va * vb, 2.0 * qk * vb * vb)
        jac[2, 3 + k] = da
        jac[3, 3 + k] = db
        jac[4, 3 + k] = dc


@_jit
def _jac_quats(jac: np.ndarray, ok: bool, idet: float, c00: float, c01: float, c11: float,
               qw: float, qx: float, qy: float, qz: float, iqn: float, t00: float, t01: float,
               t02: float, t10: float, t11: float, t12: float, a0: float, a1: float, a2: float,
               b0: float, b1: float, b2: float) -> None:
    """The Jacobian's quaternion columns (:func:`_gaussian`'s names)."""
    # R(q / |q|); dc_ab = Σ_k s_k² (dV_ak V_bk + V_ak dV_bk), dV = T dR
    for j in range(4):
        # d(q/|q|)/dq_j = (e_j - q̂ q̂_j) / |q|
        qj = qw if j == 0 else (qx if j == 1 else (qy if j == 2 else qz))
        nw = ((1.0 if j == 0 else 0.0) - qw * qj) * iqn
        nx = ((1.0 if j == 1 else 0.0) - qx * qj) * iqn
        ny = ((1.0 if j == 2 else 0.0) - qy * qj) * iqn
        nz = ((1.0 if j == 3 else 0.0) - qz * qj) * iqn
        dr00 = -4.0 * (qy * ny + qz * nz)
        dr01 = 2.0 * (qy * nx + qx * ny - qz * nw - qw * nz)
        dr02 = 2.0 * (qz * nx + qx * nz + qy * nw + qw * ny)
        dr10 = 2.0 * (qy * nx + qx * ny + qz * nw + qw * nz)
        dr11 = -4.0 * (qx * nx + qz * nz)
        dr12 = 2.0 * (qz * ny + qy * nz - qx * nw - qw * nx)
        dr20 = 2.0 * (qz * nx + qx * nz - qy * nw - qw * ny)
        dr21 = 2.0 * (qz * ny + qy * nz + qx * nw + qw * nx)
        dr22 = -4.0 * (qx * nx + qy * ny)
        dv00 = t00 * dr00 + t01 * dr10 + t02 * dr20
        dv01 = t00 * dr01 + t01 * dr11 + t02 * dr21
        dv02 = t00 * dr02 + t01 * dr12 + t02 * dr22
        dv10 = t10 * dr00 + t11 * dr10 + t12 * dr20
        dv11 = t10 * dr01 + t11 * dr11 + t12 * dr21
        dv12 = t10 * dr02 + t11 * dr12 + t12 * dr22
        dc00 = 2.0 * (dv00 * a0 + dv01 * a1 + dv02 * a2)
        dc01 = dv00 * b0 + dv01 * b1 + dv02 * b2 + a0 * dv10 + a1 * dv11 + a2 * dv12
        dc11 = 2.0 * (dv10 * b0 + dv11 * b1 + dv12 * b2)
        da, db, dc = _conic_diff(ok, idet, c00, c01, c11, dc00, dc01, dc11)
        jac[2, 6 + j] = da
        jac[3, 6 + j] = db
        jac[4, 6 + j] = dc


@_jit
def _gaussian(i: int, means: np.ndarray, log_scales: np.ndarray, quats: np.ndarray,
              logits: np.ndarray, sh: np.ndarray, cam: np.ndarray, blocks: int,
              fwd: np.ndarray, jac: np.ndarray, basis: np.ndarray, dbasis: np.ndarray) -> None:
    """Project Gaussian i (float64), and the Jacobian blocks flagged in ``blocks``.

    fwd [FWD]: see :data:`FWD`. jac [10, 11]: rows u, v, conic a, b, c, opacity, colour (3),
    depth; columns mean (3, flag JAC_MEANS), log-scale (3, JAC_SCALES), quaternion (4,
    JAC_QUATS), opacity logit (always). Only the structurally non-zero entries are written:
    the caller zeroes ``jac`` once. basis [K]: the SH basis at the viewing direction (the
    colour's derivative w.r.t. sh[k, c] is basis[k] times the colour mask c).
    """
    w0, w1, w2, w3, w4, w5, w6, w7, w8 = (cam[0], cam[1], cam[2], cam[3], cam[4], cam[5],
                                          cam[6], cam[7], cam[8])
    fx, fy, cx, cy = cam[15], cam[16], cam[17], cam[18]
    width, height, near = cam[19], cam[20], cam[21]
    lxlo, lxhi, lylo, lyhi = cam[22], cam[23], cam[24], cam[25]
    m0, m1, m2 = float(means[i, 0]), float(means[i, 1]), float(means[i, 2])
    px = w0 * m0 + w1 * m1 + w2 * m2 + cam[9]
    py = w3 * m0 + w4 * m1 + w5 * m2 + cam[10]
    pz = w6 * m0 + w7 * m1 + w8 * m2 + cam[11]
    in_front = pz > near
    zs = pz if in_front else 1.0
    izs = 1.0 / zs
    xz = px * izs
    yz = py * izs
    u = fx * xz + cx
    v = fy * yz + cy
    cl_x = min(max(xz, lxlo), lxhi)
    cl_y = min(max(yz, lylo), lyhi)
    # J = [[fx/z, 0, -fx X/z], [0, fy/z, -fy Y/z]] with X, Y the clamped x/z, y/z
    j00 = fx * izs
    j02 = -fx * cl_x * izs
    j11 = fy * izs
    j12 = -fy * cl_y * izs
    # T = J W (2 x 3)
    t00, t01, t02 = j00 * w0 + j02 * w6, j00 * w1 + j02 * w7, j00 * w2 + j02 * w8
    t10, t11, t12 = j11 * w3 + j12 * w6, j11 * w4 + j12 * w7, j11 * w5 + j12 * w8
    # rotation of the normalised quaternion
    q0, q1, q2, q3 = float(quats[i, 0]), float(quats[i, 1]), float(quats[i, 2]), \
        float(quats[i, 3])
    qn = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    iqn = 1.0 / qn
    qw, qx, qy, qz = q0 * iqn, q1 * iqn, q2 * iqn, q3 * iqn
    r00 = 1.0 - 2.0 * (qy * qy + qz * qz)
    r01 = 2.0 * (qx * qy - qw * qz)
    r02 = 2.0 * (qx * qz + qw * qy)
    r10 = 2.0 * (qx * qy + qw * qz)
    r11 = 1.0 - 2.0 * (qx * qx + qz * qz)
    r12 = 2.0 * (qy * qz - qw * qx)
    r20 = 2.0 * (qx * qz - qw * qy)
    r21 = 2.0 * (qy * qz + qw * qx)
    r22 = 1.0 - 2.0 * (qx * qx + qy * qy)
    q_0 = math.exp(2.0 * float(log_scales[i, 0]))
    q_1 = math.exp(2.0 * float(log_scales[i, 1]))
    q_2 = math.exp(2.0 * float(log_scales[i, 2]))
    # V = T R (2 x 3): the image of each principal axis
    v00 = t00 * r00 + t01 * r10 + t02 * r20
    v01 = t00 * r01 + t01 * r11 + t02 * r21
    v02 = t00 * r02 + t01 * r12 + t02 * r22
    v10 = t10 * r00 + t11 * r10 + t12 * r20
    v11 = t10 * r01 + t11 * r11 + t12 * r21
    v12 = t10 * r02 + t11 * r12 + t12 * r22
    a0 = q_0 * v00
    a1 = q_1 * v01
    a2 = q_2 * v02
    b0 = q_0 * v10
    b1 = q_1 * v11
    b2 = q_2 * v12
    c00 = a0 * v00 + a1 * v01 + a2 * v02 + LOWPASS
    c01 = a0 * v10 + a1 * v11 + a2 * v12
    c11 = b0 * v10 + b1 * v11 + b2 * v12 + LOWPASS
    det = c00 * c11 - c01 * c01
    ok = in_front and det > 0.0
    idet = 1.0 / det if ok else 1.0
    mid = 0.5 * (c00 + c11)
    lam = mid + math.sqrt(max(mid * mid - det, 0.1))
    rad = np.ceil(3.0 * math.sqrt(max(lam, 0.0)))
    on_screen = (u + rad > 0.0) and (u - rad < width) and (v + rad > 0.0) and (v - rad < height)
    keep = ok and on_screen and math.isfinite(rad) and rad > 0.0
    # colour from the SH at the viewing direction
    d0, d1, d2 = m0 - cam[12], m1 - cam[13], m2 - cam[14]
    nrm = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    nr = max(nrm, 1e-12)
    inr = 1.0 / nr
    e0, e1, e2 = d0 * inr, d1 * inr, d2 * inr
    nk = sh.shape[1]
    _sh_basis(e0, e1, e2, nk, basis)
    for ch in range(3):
        acc = 0.0
        for k in range(nk):
            acc += basis[k] * float(sh[i, k, ch])
        col = acc + 0.5
        fwd[6 + ch] = max(col, 0.0)
        fwd[14 + ch] = 1.0 if col >= 0.0 else 0.0
    op = 1.0 / (1.0 + math.exp(-float(logits[i])))
    fwd[0] = u
    fwd[1] = v
    fwd[2] = c11 * idet
    fwd[3] = -c01 * idet
    fwd[4] = c00 * idet
    fwd[5] = op
    fwd[9] = pz
    fwd[10] = c00
    fwd[11] = c01
    fwd[12] = c11
    fwd[13] = rad if keep else 0.0
    jac[5, 10] = op * (1.0 - op)
    if blocks & JAC_MEANS:
        _jac_means(i, sh, cam, fwd, jac, dbasis, xz, yz, izs, in_front, cl_x, cl_y, ok, idet,
                   c00, c01, c11, r00, r01, r02, r10, r11, r12, r20, r21, r22, a0, a1, a2, b0,
                   b1, b2, e0, e1, e2, nrm, inr)
    if blocks & JAC_SCALES:
        _jac_scales(jac, ok, idet, c00, c01, c11, q_0, q_1, q_2, v00, v01, v02, v10, v11, v12)
    if blocks & JAC_QUATS:
        _jac_quats(jac, ok, idet, c00, c01, c11, qw, qx, qy, qz, iqn, t00, t01, t02, t10, t11,
                   t12, a0, a1, a2, b0, b1, b2)


@_jit
def _scratch(nk: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One thread's scratch for :func:`_gaussian`: fwd [FWD], jac [10, 11] (zeroed once: only
    its structurally non-zero entries are written), basis [K], dbasis [K, 3]."""
    k = max(nk, 1)
    return np.empty(FWD), np.zeros((10, 11)), np.empty(k), np.empty((k, 3))


@_jit
def project(means: np.ndarray, log_scales: np.ndarray, quats: np.ndarray, logits: np.ndarray,
            sh: np.ndarray, cam: np.ndarray, part: int, nchunks: int, means2d: np.ndarray,
            conics: np.ndarray, depths: np.ndarray, radii: np.ndarray, colors: np.ndarray,
            opacities: np.ndarray, cov2d: np.ndarray) -> None:
    """Project every Gaussian (see :func:`_gaussian`) into the output arrays ([N, 2], [N, 3],
    [N], [N] int64, [N, 3], [N], [N, 3])."""
    n = means.shape[0]
    nk = sh.shape[1]
    fwd, jac, basis, dbasis = _scratch(nk)
    lo = part * n // nchunks
    hi = (part + 1) * n // nchunks
    for i in range(lo, hi):
        _gaussian(i, means, log_scales, quats, logits, sh, cam, 0, fwd, jac, basis, dbasis)
        means2d[i, 0] = fwd[0]
        means2d[i, 1] = fwd[1]
        conics[i, 0] = fwd[2]
        conics[i, 1] = fwd[3]
        conics[i, 2] = fwd[4]
        opacities[i] = fwd[5]
        colors[i, 0] = fwd[6]
        colors[i, 1] = fwd[7]
        colors[i, 2] = fwd[8]
        depths[i] = fwd[9]
        cov2d[i, 0] = fwd[10]
        cov2d[i, 1] = fwd[11]
        cov2d[i, 2] = fwd[12]
        radii[i] = int(fwd[13])


@_jit
def project_backward(means: np.ndarray, log_scales: np.ndarray, quats: np.ndarray,
                     logits: np.ndarray, sh: np.ndarray, cam: np.ndarray, part: int, nchunks: int,
                     g_screen: np.ndarray, g_means: np.ndarray, g_log_scales: np.ndarray,
                     g_quats: np.ndarray, g_logits: np.ndarray, g_sh: np.ndarray) -> None:
    """Vector-Jacobian product of :func:`project`: g_screen [N, 10] holds the gradients of
    (u, v, conic a, b, c, opacity, colour r, g, b, depth); writes the parameters' gradients
    (every output array zero-initialised by the caller)."""
    n = means.shape[0]
    nk = sh.shape[1]
    fwd, jac, basis, dbasis = _scratch(nk)
    lo = part * n // nchunks
    hi = (part + 1) * n // nchunks
    for i in range(lo, hi):
        nonzero = False
        for r in range(10):
            if g_screen[i, r] != 0.0:
                nonzero = True
        if not nonzero:
            continue
        _gaussian(i, means, log_scales, quats, logits, sh, cam, JAC_ALL, fwd, jac, basis,
                  dbasis)
        for c in range(11):
            acc = 0.0
            for r in range(10):
                acc += jac[r, c] * g_screen[i, r]
            if c < 3:
                g_means[i, c] = acc
            elif c < 6:
                g_log_scales[i, c - 3] = acc
            elif c < 10:
                g_quats[i, c - 6] = acc
            else:
                g_logits[i] = acc
        for ch in range(3):
            gc = g_screen[i, 6 + ch] * fwd[14 + ch]
            for k in range(nk):
                g_sh[i, k, ch] = basis[k] * gc


@_jit
def jacobians(means: np.ndarray, log_scales: np.ndarray, quats: np.ndarray, logits: np.ndarray,
              sh: np.ndarray, cam: np.ndarray, part: int, nchunks: int, jac_out: np.ndarray,
              basis_out: np.ndarray, mask_out: np.ndarray) -> None:
    """Every Gaussian's Jacobian [N, 10, 11] (see :func:`_gaussian`), SH basis [N, K] and
    colour masks [N, 3]."""
    n = means.shape[0]
    nk = sh.shape[1]
    fwd, _, _, dbasis = _scratch(nk)
    lo = part * n // nchunks
    hi = (part + 1) * n // nchunks
    for i in range(lo, hi):
        _gaussian(i, means, log_scales, quats, logits, sh, cam, JAC_ALL, fwd, jac_out[i],
                  basis_out[i], dbasis)
        for ch in range(3):
            mask_out[i, ch] = fwd[14 + ch]


# ----------------------------------------------------------------------------- the chain
PHI_INDEX = np.array([[0, 1, 2, 3, 4, 5],
                      [1, 3, 4, 6, 7, 8],
                      [2, 4, 5, 7, 8, 9],
                      [3, 6, 7, 10, 11, 12],
                      [4, 7, 8, 11, 12, 13],
                      [5, 8, 9, 12, 13, 14]], dtype=np.int64)
"""Φ_ij as an index into the 15 monomial moments: φ_i φ_j = dx^(a_i + a_j) dy^(b_i + b_j)."""


@_jit
def fisher_chain(order: np.ndarray, moments: np.ndarray, means: np.ndarray, log_scales: np.ndarray,
                 quats: np.ndarray, logits: np.ndarray, sh: np.ndarray, cam: np.ndarray,
                 part: int, nchunks: int, pixels: bool, want: np.ndarray, h_means: np.ndarray,
                 h_log_scales: np.ndarray, h_quats: np.ndarray, h_logits: np.ndarray,
                 h_sh: np.ndarray) -> None:
    """diag(Jᵀ M J) per parameter block of the visible Gaussians (``order`` [V]) from their
    moments (rows of moments [N, MOMENTS]; those with Σ w² = 0, the last column, had no
    composited pair and keep 0); ``want`` [5] flags means, log_scales, quats,
    opacity_logits, sh. The outputs are zero-initialised by the caller. The Gaussians are
    taken in index order (their parameters are read in order).

    Per Jacobian column J (rows u, v, conic a, b, c, opacity, colour): with y = Aᵀ J_geo in
    the monomial space (y0 = J_o / o, y1 = a J_u + b J_v, y2 = b J_u + c J_v, y3 = -J_a / 2,
    y4 = -J_b, y5 = -J_c / 2), Jᵀ M J = yᵀ Φ y + 2 Σ_c J_c (C2_c · y) + Σ w² Σ_c J_c²
    (``pixels``: Σ w² (Σ_c J_c)²).
    """
    nk = sh.shape[1]
    visible = np.zeros(means.shape[0], np.bool_)
    for v in range(order.shape[0]):
        visible[order[v]] = True
    idx = np.nonzero(visible)[0]
    n = idx.shape[0]
    blocks = ((JAC_MEANS if want[0] else 0) | (JAC_SCALES if want[1] else 0)
              | (JAC_QUATS if want[2] else 0))
    fwd, jac, basis, dbasis = _scratch(nk)
    phi = np.empty((6, 6))
    y = np.empty(6)
    lo = part * n // nchunks
    hi = (part + 1) * n // nchunks
    for ii in range(lo, hi):
        i = idx[ii]
        mom = moments[i]
        mcc = mom[33]
        if mcc == 0.0:
            continue
        _gaussian(i, means, log_scales, quats, logits, sh, cam, blocks, fwd, jac, basis,
                  dbasis)
        for r in range(6):
            for q in range(6):
                phi[r, q] = mom[PHI_INDEX[r, q]]
        ca, cb, cc = fwd[2], fwd[3], fwd[4]
        op = fwd[5]
        inv_o = 1.0 / max(op, 1e-30)
        if want[0]:
            for col in range(3):
                y[0] = jac[5, col] * inv_o
                y[1] = ca * jac[0, col] + cb * jac[1, col]
                y[2] = cb * jac[0, col] + cc * jac[1, col]
                y[3] = -0.5 * jac[2, col]
                y[4] = -jac[3, col]
                y[5] = -0.5 * jac[4, col]
                acc = 0.0
                for r in range(6):
                    s = 0.0
                    for q in range(6):
                        s += phi[r, q] * y[q]
                    acc += y[r] * s
                csum = 0.0
                csq = 0.0
                for ch in range(3):
                    jc = jac[6 + ch, col]
                    s = 0.0
                    for q in range(6):
                        s += mom[15 + 6 * ch + q] * y[q]
                    acc += 2.0 * jc * s
                    csum += jc
                    csq += jc * jc
                acc += mcc * (csum * csum if pixels else csq)
                h_means[i, col] = acc
        for blk in range(2):
            if not want[1 + blk]:
                continue
            c_lo = 3 if blk == 0 else 6
            c_hi = 6 if blk == 0 else 10
            for col in range(c_lo, c_hi):
                # only the conic rows: y3, y4, y5
                y3 = -0.5 * jac[2, col]
                y4 = -jac[3, col]
                y5 = -0.5 * jac[4, col]
                acc = (y3 * (phi[3, 3] * y3 + 2.0 * (phi[3, 4] * y4 + phi[3, 5] * y5))
                       + y4 * (phi[4, 4] * y4 + 2.0 * phi[4, 5] * y5)
                       + y5 * phi[5, 5] * y5)
                if blk == 0:
                    h_log_scales[i, col - 3] = acc
                else:
                    h_quats[i, col - 6] = acc
        if want[3]:
            y0 = (op * (1.0 - op)) * inv_o
            h_logits[i] = y0 * y0 * phi[0, 0]
        if want[4]:
            for ch in range(3):
                mk = fwd[14 + ch] * mcc
                for k in range(nk):
                    h_sh[i, k, ch] = basis[k] * basis[k] * mk
