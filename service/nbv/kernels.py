"""Compiled CPU kernels (numba) of the projection, the tile compositing and the one-pass Fisher.

numpy arrays in, numpy arrays out; no torch here (:mod:`agilegs.service.nbv.backend` wraps
these in autograd functions and picks them or the pure-torch reference). Every kernel follows
the pure-torch rules of :mod:`agilegs.service.nbv.projection`, :mod:`agilegs.service.nbv.rasterize`
and :mod:`agilegs.service.nbv.information` exactly:

- projection (:func:`project`): EWA with the 0.3 low-pass, the 1.3× field-of-view clamp of
  the Jacobian, culling (depth ≤ near, det ≤ 0, off screen), radius ceil(3 sqrt(λ_max)),
  colour max(0, 0.5 + Σ_k Y_k sh_k), opacity sigmoid(logit). Per-Gaussian arithmetic is float64;
  the outputs take the input dtype.
- binning (:func:`bin_count`, :func:`visible_order`, :func:`bin_fill`): the visible
  Gaussians sorted front to back (stable), each listed in every tile of the clamped tile
  range its square [u - r, u + r] overlaps that also meets the bounding box of its
  α ≥ 1/255 ellipse (pixels outside that box cannot pass the 1/255 test, so leaving those
  tiles out changes nothing). A list entry is a record of its Gaussian's screen attributes
  and its box within the tile; entries refer to the depth-sorted visible ("compact")
  Gaussians.
- compositing (:func:`composite_forward`, :func:`composite_backward`, :func:`fisher_tiles`):
  per tile, per pixel front to back: σ = ½(a dx² + c dy²) + b dx dy and α = o·exp(-σ) in the
  input dtype (the torch path's per-pair arithmetic, so the same pairs pass), σ < 0 and
  α < 1/255 skipped, α clamped at 0.99, the transmittance T (float64) stops before the
  Gaussian that would take it below 1e-4. The forward can record each tile's composited
  pairs; the backward walks them back to front, recovering T_i = T_{i+1} / (1 - α_i) and the
  colour behind.
- the Fisher's chain (:func:`fisher_chain`) and the projection's vector-Jacobian product
  (:func:`project_backward`) share one analytic per-Gaussian Jacobian (:func:`_gaussian`) of
  the screen attributes (mean2d, conic, opacity, colour) and depth w.r.t. the Gaussian's own
  parameters.

Memory access: the binning writes every tile's list as a run of records (the Gaussian's
screen attributes, depth and colours), so that the walks read memory in order; the backward
walks write one row per list entry, and :func:`reduce_entries` sums each Gaussian's rows.

Threads: the kernels are serial and release the GIL; a kernel with ``part, nchunks``
arguments does part ``part`` of ``nchunks`` (tile t in part t mod nchunks; Gaussians in
contiguous ranges), and the parts write disjoint memory, so the caller runs them on as many
Python threads (:mod:`agilegs.service.nbv.backend`). No numba threading layer is involved
(none to configure, nothing that breaks across a fork).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = [
    "CAM",
    "MOMENTS",
    "PHI_INDEX",
    "REC",
    "bin_count",
    "bin_fill",
    "composite_backward",
    "composite_forward",
    "fisher_chain",
    "fisher_tiles",
    "jacobians",
    "project",
    "project_backward",
    "reduce_entries",
    "visible_order",
]

T_MIN = 1e-4
LOWPASS = 0.3
ALPHA_MIN_F64 = 1.0 / 255.0
CAM = 26
"""The camera vector: w2c rotation (9, row-major), translation (3), camera centre (3), fx, fy,
cx, cy, width, height, near, and the limits of x/z and y/z in the EWA Jacobian (1.3 times
the half field of view: x_lo, x_hi, y_lo, y_hi)."""

FWD = 17
"""Per-Gaussian forward values of :func:`_gaussian`: u, v, conic a, b, c, opacity, colour (3),
depth, cov2d (3), radius, colour masks (3)."""

_jit = njit(cache=True, nogil=True, error_model="numpy")
"""Every kernel: compiled on first use for the argument types, cached on disk, the GIL
released, and no Python-style division checks."""

_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C20, _C21, _C22, _C23, _C24 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                                -1.0925484305920792, 0.5462742152960396)
_C30, _C31, _C32, _C33, _C34, _C35, _C36 = (-0.5900435899266435, 2.890611442640554,
                                            -0.4570457994644658, 0.3731763325901154,
                                            -0.4570457994644658, 1.445305721320277,
                                            -0.5900435899266435)


# ----------------------------------------------------------------------------- per Gaussian
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
        # through p: mean2d and the EWA Jacobian; the depth; the viewing direction.
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
    if blocks & JAC_SCALES:
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
    if blocks & JAC_QUATS:
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
def project(means: np.ndarray, log_scales: np.ndarray, quats: np.ndarray, logits: np.ndarray,
            sh: np.ndarray, cam: np.ndarray, part: int, nchunks: int, means2d: np.ndarray,
            conics: np.ndarray, depths: np.ndarray, radii: np.ndarray, colors: np.ndarray,
            opacities: np.ndarray, cov2d: np.ndarray) -> None:
    """Project every Gaussian (see :func:`_gaussian`) into the output arrays ([N, 2], [N, 3],
    [N], [N] int64, [N, 3], [N], [N, 3])."""
    n = means.shape[0]
    nk = sh.shape[1]
    fwd = np.empty(FWD)
    jac = np.zeros((10, 11))
    basis = np.empty(max(nk, 1))
    dbasis = np.empty((max(nk, 1), 3))
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
    fwd = np.empty(FWD)
    jac = np.zeros((10, 11))
    basis = np.empty(max(nk, 1))
    dbasis = np.empty((max(nk, 1), 3))
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
    fwd = np.empty(FWD)
    dbasis = np.empty((max(nk, 1), 3))
    lo = part * n // nchunks
    hi = (part + 1) * n // nchunks
    for i in range(lo, hi):
        _gaussian(i, means, log_scales, quats, logits, sh, cam, JAC_ALL, fwd, jac_out[i],
                  basis_out[i], dbasis)
        for ch in range(3):
            mask_out[i, ch] = fwd[14 + ch]


# ----------------------------------------------------------------------------- binning
REC = 8
"""Leading columns of a list entry's record: mean x, mean y, conic a, b, c, opacity, depth,
and σ_cut (slightly above ln(o·255): where σ exceeds it, α < 1/255 without evaluating the
exponential); the colour (or feature) channels follow."""


@_jit
def _radix_argsort(bits: np.ndarray, nbytes: int) -> np.ndarray:
    """Stable argsort of unsigned keys of ``nbytes`` bytes [n] (least-significant-digit radix
    sort, 8 bits a pass, passes whose digit is constant skipped)."""
    n = bits.shape[0]
    idx = np.arange(n)
    tmp = np.empty(n, np.int64)
    count = np.empty(257, np.int64)
    for byte in range(nbytes):
        shift = np.uint64(8 * byte)
        count[:] = 0
        for i in range(n):
            count[((bits[i] >> shift) & np.uint64(255)) + np.uint64(1)] += 1
        if n and count[((bits[0] >> shift) & np.uint64(255)) + np.uint64(1)] == n:
            continue
        for d in range(256):
            count[d + 1] += count[d]
        for i in range(n):
            j = idx[i]
            d = (bits[j] >> shift) & np.uint64(255)
            tmp[count[d]] = j
            count[d] += 1
        idx, tmp = tmp, idx
    return idx


@_jit
def bin_count(means2d: np.ndarray, conics: np.ndarray, opacities: np.ndarray,
              depths: np.ndarray, colors: np.ndarray, radii: np.ndarray, radii_f: np.ndarray,
              cov2d: np.ndarray, width: int, height: int, tile: int, tile_f: float,
              own: np.ndarray, counts: np.ndarray, areas: np.ndarray) -> int:
    """First binning pass, in the input order: every visible Gaussian's pixel box, its list
    entries, its record; returns the number of visible Gaussians.

    ``radii_f`` and ``tile_f`` are the radii [N] and the tile size in the means' dtype, so that
    the binned tile range floor((u ± r) / tile) is computed in that dtype, as the torch
    binning does. The box is that of the α ≥ 1/255 ellipse (half-widths sqrt(k Σ_aa),
    k = 2 ln(255 o)), widened by a hair, within the binned tiles.

    Writes own [N, REC + C + 5]: the record, then the box (x0, x1, y0, y1 inclusive; empty:
    x0 > x1) and the number of tiles it meets (exact in the record's dtype; one row per
    Gaussian keeps :func:`bin_fill`'s reads to one place each); adds to counts [n_tiles + 1]
    and areas [n_tiles + 1] (zero-initialised; entry t + 1 for tile t: its entries, their
    box areas).
    """
    n = radii.shape[0]
    tiles_x = (width + tile - 1) // tile
    tiles_y = (height + tile - 1) // tile
    nc = colors.shape[1]
    nb = REC + nc
    nvis = 0
    for g in range(n):
        if radii[g] <= 0:
            own[g, nb + 4] = 0
            continue
        nvis += 1
        mx = means2d[g, 0]
        my = means2d[g, 1]
        rf = radii_f[g]
        tx0 = min(max(math.floor((mx - rf) / tile_f), 0), tiles_x - 1)
        tx1 = min(max(math.floor((mx + rf) / tile_f), 0), tiles_x - 1)
        ty0 = min(max(math.floor((my - rf) / tile_f), 0), tiles_y - 1)
        ty1 = min(max(math.floor((my + rf) / tile_f), 0), tiles_y - 1)
        kk = 2.0 * math.log(max(float(opacities[g]) / ALPHA_MIN_F64, 1.0))
        hx = math.sqrt(kk * max(float(cov2d[g, 0]), 0.0)) * (1.0 + 1e-5) + 1e-2
        hy = math.sqrt(kk * max(float(cov2d[g, 2]), 0.0)) * (1.0 + 1e-5) + 1e-2
        x0 = max(tx0 * tile, math.ceil(float(mx) - hx - 0.5))
        x1 = min(min((tx1 + 1) * tile, width) - 1, math.floor(float(mx) + hx - 0.5))
        y0 = max(ty0 * tile, math.ceil(float(my) - hy - 0.5))
        y1 = min(min((ty1 + 1) * tile, height) - 1, math.floor(float(my) + hy - 0.5))
        if x0 > x1 or y0 > y1:
            x0, x1, y0, y1 = 1, 0, 1, 0
        own[g, nb] = x0
        own[g, nb + 1] = x1
        own[g, nb + 2] = y0
        own[g, nb + 3] = y1
        cnt = 0
        for ty in range(y0 // tile, y1 // tile + 1):
            for tx in range(x0 // tile, x1 // tile + 1):
                t = ty * tiles_x + tx
                counts[t + 1] += 1
                areas[t + 1] += ((min(x1, tx * tile + tile - 1) - max(x0, tx * tile) + 1)
                                 * (min(y1, ty * tile + tile - 1) - max(y0, ty * tile) + 1))
                cnt += 1
        own[g, nb + 4] = cnt
        own[g, 0] = mx
        own[g, 1] = my
        own[g, 2] = conics[g, 0]
        own[g, 3] = conics[g, 1]
        own[g, 4] = conics[g, 2]
        own[g, 5] = opacities[g]
        own[g, 6] = depths[g]
        own[g, 7] = 0.5 * kk * (1.0 + 1e-6) + 1e-6
        for ch in range(nc):
            own[g, REC + ch] = colors[g, ch]
    return nvis


@_jit
def visible_order(radii: np.ndarray, depth_bits: np.ndarray, depth_bytes: int, nvis: int,
                  order: np.ndarray) -> None:
    """order [nvis] = the visible Gaussians (radius > 0) front to back, ties by index.

    ``depth_bits`` [N] (uint64) holds the bit patterns of the depths (``depth_bytes`` bytes
    wide): the visible Gaussians lie beyond the near plane, and the bit patterns of positive
    floats order as their values, so a stable radix sort of them is the stable depth order.
    """
    vis = np.empty(nvis, np.int64)
    keys = np.empty(nvis, np.uint64)
    j = 0
    for i in range(radii.shape[0]):
        if radii[i] > 0:
            vis[j] = i
            keys[j] = depth_bits[i]
            j += 1
    idx = _radix_argsort(keys, depth_bytes)
    for v in range(nvis):
        order[v] = vis[idx[v]]


@_jit
def bin_fill(order: np.ndarray, own: np.ndarray, offsets: np.ndarray, width: int, tile: int,
             sorted_own: np.ndarray, rec: np.ndarray, rbox: np.ndarray, rg: np.ndarray,
             ent_off: np.ndarray, ent: np.ndarray) -> None:
    """Second binning pass, front to back: every tile's list as a run of records.

    Args:
        order [V], own: from :func:`visible_order` and :func:`bin_count`.
        sorted_own [V, own's width]: scratch (own gathered in depth order first: a copy loop
            whose reads overlap, where the fill's own control flow would wait on each).
        offsets [n_tiles + 1]: start of each tile's list (the cumulative counts).

    Writes rec [M, REC + C] (each entry's record: the walks read them in order), rbox
    [M, 4] (its box within the tile), rg [M] (its compact Gaussian, index into ``order``),
    ent_off [V + 1] and ent [M] (each compact Gaussian's entries, CSR).
    """
    tiles_x = (width + tile - 1) // tile
    n_tiles = offsets.shape[0] - 1
    width_rec = rec.shape[1]
    nv = order.shape[0]
    for v in range(nv):
        g = order[v]
        for c in range(own.shape[1]):
            sorted_own[v, c] = own[g, c]
    pos = offsets[:n_tiles].copy()
    ent_off[0] = 0
    q = 0
    for v in range(nv):
        row = sorted_own[v]
        bx0, bx1 = int(row[width_rec]), int(row[width_rec + 1])
        by0, by1 = int(row[width_rec + 2]), int(row[width_rec + 3])
        if row[width_rec + 4] > 0:
            for ty in range(by0 // tile, by1 // tile + 1):
                for tx in range(bx0 // tile, bx1 // tile + 1):
                    t = ty * tiles_x + tx
                    e = pos[t]
                    pos[t] += 1
                    ent[q] = e
                    q += 1
                    rg[e] = v
                    for c in range(width_rec):
                        rec[e, c] = row[c]
                    rbox[e, 0] = max(bx0, tx * tile)
                    rbox[e, 1] = min(bx1, tx * tile + tile - 1)
                    rbox[e, 2] = max(by0, ty * tile)
                    rbox[e, 3] = min(by1, ty * tile + tile - 1)
        ent_off[v + 1] = q


@_jit
def reduce_entries(visit: np.ndarray, target: np.ndarray, ent_off: np.ndarray,
                   ent: np.ndarray, per_entry: np.ndarray, part: int, nchunks: int,
                   out: np.ndarray) -> None:
    """out[target[v]] = the sum of compact Gaussian v's entries' rows of per_entry [M, K]
    (float64 sums), for v = visit[j] with j in this part's range; rows not targeted are left
    as they are."""
    nv = visit.shape[0]
    kk = per_entry.shape[1]
    acc = np.empty(kk)
    lo = part * nv // nchunks
    hi = (part + 1) * nv // nchunks
    for j in range(lo, hi):
        v = visit[j]
        for q in range(kk):
            acc[q] = 0.0
        for jj in range(ent_off[v], ent_off[v + 1]):
            e = ent[jj]
            for q in range(kk):
                acc[q] += per_entry[e, q]
        g = target[v]
        for q in range(kk):
            out[g, q] = acc[q]


# ----------------------------------------------------------------------------- compositing
@_jit
def _pixel_tables(tile: int) -> tuple[np.ndarray, np.ndarray]:
    """Column and row of every tile pixel index p = row * tile + col (tables, not divisions by
    a runtime tile size, in the walks' inner loops)."""
    col_of = np.empty(tile * tile, np.int64)
    row_of = np.empty(tile * tile, np.int64)
    for p in range(tile * tile):
        col_of[p] = p % tile
        row_of[p] = p // tile
    return col_of, row_of


@_jit
def _live_rect(x0: int, y0: int, x1: int, y1: int, tile: int, last: np.ndarray,
               k: int) -> tuple[int, int, int, int]:
    """The bounding box of the tile's pixels that still composite at list position k
    (k < last[p]); empty (x0 > x1) if none."""
    lx0, lx1, ly0, ly1 = x1, x0 - 1, y1, y0 - 1
    for py in range(y0, y1):
        for px in range(x0, x1):
            if k < last[(py - y0) * tile + (px - x0)]:
                lx0 = min(lx0, px)
                lx1 = max(lx1, px)
                ly0 = min(ly0, py)
                ly1 = max(ly1, py)
    return lx0, lx1, ly0, ly1


@_jit
def _walk_forward(start: int, length: int, rec: np.ndarray, rbox: np.ndarray, xs: np.ndarray,
                  ys: np.ndarray, x0: int, y0: int, x1: int, y1: int, tile: int, half: float,
                  amin: float, amax: float, tr: np.ndarray, last: np.ndarray, acc: np.ndarray,
                  dacc: np.ndarray, with_color: bool, record: bool, pk: np.ndarray,
                  pp: np.ndarray, pa: np.ndarray, base: int) -> int:
    """One tile front to back: the transmittance tr (from 1), the stop positions last (from
    ``length``) and, ``with_color``, Σ w c and Σ w z, for the pixels of the tile. Only the
    box of the pixels still compositing is visited.

    ``record``: every composited pair, in order, to pk (list position), pp (tile pixel) and
    pa (α before the clamp) from index ``base``. Returns the number of composited pairs.
    """
    nc = rec.shape[1] - REC
    inside = (x1 - x0) * (y1 - y0)
    ndone = 0
    seen = 0
    npairs = 0
    lx0, lx1, ly0, ly1 = x0, x1 - 1, y0, y1 - 1
    for k in range(length):
        if ndone != seen:
            if ndone == inside:
                break
            seen = ndone
            lx0, lx1, ly0, ly1 = _live_rect(x0, y0, x1, y1, tile, last, k)
        e = start + k
        bx0 = max(rbox[e, 0], lx0)
        bx1 = min(rbox[e, 1], lx1)
        by0 = max(rbox[e, 2], ly0)
        by1 = min(rbox[e, 3], ly1)
        if bx0 > bx1 or by0 > by1:
            continue
        mx = rec[e, 0]
        my = rec[e, 1]
        a = rec[e, 2]
        b = rec[e, 3]
        c = rec[e, 4]
        o = rec[e, 5]
        cut = rec[e, 7]
        for py in range(by0, by1 + 1):
            dy = ys[py] - my
            row = (py - y0) * tile - x0
            for px in range(bx0, bx1 + 1):
                p = row + px
                if last[p] <= k:
                    continue
                dx = xs[px] - mx
                sigma = half * (a * dx * dx + c * dy * dy) + b * dx * dy
                if sigma < 0 or sigma > cut:
                    continue
                raw = o * np.exp(-sigma)
                if raw < amin:
                    continue
                al = float(min(raw, amax))
                tp = tr[p]
                tn = tp * (1.0 - al)
                if tn < T_MIN:  # this Gaussian is not composited, nor any behind it
                    last[p] = k
                    ndone += 1
                    continue
                tr[p] = tn
                if with_color:
                    w = tp * al
                    for ch in range(nc):
                        acc[p, ch] += w * rec[e, REC + ch]
                    dacc[p] += w * rec[e, 6]
                if record:
                    pk[base + npairs] = k
                    pp[base + npairs] = p
                    pa[base + npairs] = raw
                npairs += 1
    return npairs


@_jit
def composite_forward(offsets: np.ndarray, rec: np.ndarray, rbox: np.ndarray, xs: np.ndarray,
                      ys: np.ndarray, width: int, height: int, tile: int, half: float,
                      amin: float, amax: float, part: int, nchunks: int, slots: np.ndarray,
                      record: bool,
                      pk: np.ndarray, pp: np.ndarray, pa: np.ndarray, npairs: np.ndarray,
                      out_col: np.ndarray, out_tf: np.ndarray, out_dacc: np.ndarray) -> None:
    """Front-to-back compositing of every tile (the records of :func:`bin_fill`).

    Args:
        xs [W], ys [H]: pixel centres (index + 0.5) in the records' dtype.
        half, amin, amax: 0.5, 1/255 and 0.99 in that dtype.
        slots, record, pk, pp, pa: with ``record``, tile t's composited pairs go to
            [slots[t], slots[t] + npairs[t]) of pk, pp, pa (see :func:`_walk_forward`), for
            :func:`composite_backward`.

    Writes per pixel (flat y * W + x): Σ w c [HW, C] (no background), T_final (float64)
    [HW], Σ w z [HW]; and npairs [n_tiles].
    """
    tiles_x = (width + tile - 1) // tile
    n_tiles = offsets.shape[0] - 1
    nc = rec.shape[1] - REC
    npix = tile * tile
    tr = np.empty(npix)
    last = np.empty(npix, np.int64)
    acc = np.empty((npix, nc))
    dacc = np.empty(npix)
    for t in range(part, n_tiles, nchunks):
        x0 = (t % tiles_x) * tile
        y0 = (t // tiles_x) * tile
        x1 = min(x0 + tile, width)
        y1 = min(y0 + tile, height)
        start = offsets[t]
        length = offsets[t + 1] - start
        for p in range(npix):
            tr[p] = 1.0
            last[p] = length
            dacc[p] = 0.0
            for ch in range(nc):
                acc[p, ch] = 0.0
        npairs[t] = _walk_forward(start, length, rec, rbox, xs, ys, x0, y0, x1, y1, tile,
                                  half, amin, amax, tr, last, acc, dacc, True, record, pk,
                                  pp, pa, slots[t])
        for py in range(y0, y1):
            for px in range(x0, x1):
                p = (py - y0) * tile + (px - x0)
                pix = py * width + px
                for ch in range(nc):
                    out_col[pix, ch] = acc[p, ch]
                out_tf[pix] = tr[p]
                out_dacc[pix] = dacc[p]


@_jit
def composite_backward(offsets: np.ndarray, rec: np.ndarray, rbox: np.ndarray, xs: np.ndarray,
                       ys: np.ndarray, width: int, height: int, tile: int, half: float,
                       amin: float, amax: float, part: int, nchunks: int, slots: np.ndarray,
                       pk: np.ndarray, pp: np.ndarray, pa: np.ndarray, npairs: np.ndarray,
                       t_final: np.ndarray, bg: np.ndarray, g_col: np.ndarray,
                       g_alpha: np.ndarray, g_depth: np.ndarray, grads: np.ndarray) -> None:
    """Backward of :func:`composite_forward` (run with ``record``) for output gradients g_col
    [HW, C] (the colour with the background composited behind), g_alpha [HW] (alpha =
    1 - T_final) and g_depth [HW] (Σ w z): each tile's composited pairs back to front.

    Writes grads [M, 7 + C] (zero-initialised): per list entry the gradients of its
    Gaussian's (mean x, mean y, conic a, b, c, opacity, depth, colour...) from the tile's
    pixels (:func:`reduce_entries` sums them per Gaussian).
    """
    tiles_x = (width + tile - 1) // tile
    n_tiles = offsets.shape[0] - 1
    nc = rec.shape[1] - REC
    npix = tile * tile
    tr = np.empty(npix)
    behind = np.empty(npix)
    tail = np.empty(npix)
    pg = np.empty((npix, nc))
    pgd = np.empty(npix)
    gcl = np.empty(nc)
    col_of, row_of = _pixel_tables(tile)
    for t in range(part, n_tiles, nchunks):
        x0 = (t % tiles_x) * tile
        y0 = (t // tiles_x) * tile
        x1 = min(x0 + tile, width)
        y1 = min(y0 + tile, height)
        start = offsets[t]
        for py in range(y0, y1):
            for px in range(x0, x1):
                p = (py - y0) * tile + (px - x0)
                pix = py * width + px
                tr[p] = t_final[pix]
                behind[p] = 0.0
                s = -float(g_alpha[pix])
                for ch in range(nc):
                    gch = float(g_col[pix, ch])
                    pg[p, ch] = gch
                    s += float(bg[ch]) * gch
                pgd[p] = g_depth[pix]
                tail[p] = t_final[pix] * s
        j = slots[t] + npairs[t] - 1
        first = slots[t]
        while j >= first:
            k = pk[j]
            e = start + k
            mx = rec[e, 0]
            my = rec[e, 1]
            af, bf, cf = float(rec[e, 2]), float(rec[e, 3]), float(rec[e, 4])
            zg = float(rec[e, 6])
            gm0 = gm1 = ga = gb = gc = go = gz = 0.0
            for ch in range(nc):
                gcl[ch] = 0.0
            while j >= first and pk[j] == k:
                p = pp[j]
                raw = pa[j]
                j -= 1
                dxf = float(xs[x0 + col_of[p]] - mx)
                dyf = float(ys[y0 + row_of[p]] - my)
                al = float(min(raw, amax))
                inv = 1.0 / (1.0 - al)
                tp = tr[p] * inv
                tr[p] = tp
                w = tp * al
                gd = pgd[p]
                uu = gd * zg
                for ch in range(nc):
                    gch = pg[p, ch]
                    uu += float(rec[e, REC + ch]) * gch
                    gcl[ch] += w * gch
                gz += w * gd
                gal = tp * uu - (behind[p] + tail[p]) * inv
                behind[p] += w * uu
                # α clamped at 0.99 passes no derivative to the Gaussian's attributes
                gp = gal * al if raw <= amax else 0.0
                gm0 += gp * (af * dxf + bf * dyf)
                gm1 += gp * (bf * dxf + cf * dyf)
                ga -= 0.5 * gp * dxf * dxf
                gb -= gp * dxf * dyf
                gc -= 0.5 * gp * dyf * dyf
                go += gp
            grads[e, 0] = gm0
            grads[e, 1] = gm1
            grads[e, 2] = ga
            grads[e, 3] = gb
            grads[e, 4] = gc
            grads[e, 5] = go / max(float(rec[e, 5]), 1e-30)
            grads[e, 6] = gz
            for ch in range(nc):
                grads[e, 7 + ch] = gcl[ch]


MOMENTS = 34
"""Per-Gaussian Fisher moments: Σ f4·dx^a dy^b for the 15 monomials of degree ≤ 4 (by degree,
then by the power of dy; these hold every entry of Φ = Σ f4 φφᵀ), the 18 entries of
C2 = Σ f2 ⊗ φ (channel-major), and Σ w²."""


@_jit
def fisher_tiles(offsets: np.ndarray, rec: np.ndarray, rbox: np.ndarray, xs: np.ndarray,
                 ys: np.ndarray, width: int, height: int, tile: int, half: float, amin: float,
                 amax: float, part: int, nchunks: int, slots: np.ndarray, bg: np.ndarray,
                 pixels: bool,
                 moments: np.ndarray) -> None:
    """The Fisher's moments (:data:`MOMENTS`) per list entry over its composited pairs: per
    tile a front-to-back walk (the transmittance stop, the composited pairs), then those
    pairs back to front.

    Per pair, with ∂C_c/∂α = T c_c - (S_c + T_final bg_c) / (1 - α) (S_c the colour composited
    behind), φ = (1, dx, dy, dx², dx dy, dy²) and w = T α:
    ``pixels`` False (every channel a residual): f4 = Σ_c (∂C_c/∂α)² α̃², f2_c = ∂C_c/∂α w α̃
    with α̃ = α where α was not clamped at 0.99, else 0; ``pixels`` True (the channel sum one
    residual): f4 = (Σ_c ∂C_c/∂α)² α_raw², f2_c = (Σ_c ∂C_c/∂α) w α_raw. Writes into
    moments [M, MOMENTS] (zero-initialised; :func:`reduce_entries` sums them per Gaussian).
    The records carry 3 colour channels; bg [3].
    """
    tiles_x = (width + tile - 1) // tile
    n_tiles = offsets.shape[0] - 1
    npix = tile * tile
    bg0, bg1, bg2 = float(bg[0]), float(bg[1]), float(bg[2])
    most = 0
    for t in range(n_tiles):
        most = max(most, slots[t + 1] - slots[t])
    tr = np.empty(npix)
    tf = np.empty(npix)
    last = np.zeros(npix, np.int64)
    s0 = np.empty(npix)
    s1 = np.empty(npix)
    s2 = np.empty(npix)
    pk = np.empty(most, np.int32)
    pp = np.empty(most, np.int32)
    pa = np.empty(most, rec.dtype)
    col_of, row_of = _pixel_tables(tile)
    dummy = np.empty((1, 1))
    dummy1 = np.empty(1)
    for t in range(part, n_tiles, nchunks):
        x0 = (t % tiles_x) * tile
        y0 = (t // tiles_x) * tile
        x1 = min(x0 + tile, width)
        y1 = min(y0 + tile, height)
        start = offsets[t]
        length = offsets[t + 1] - start
        for p in range(npix):
            tr[p] = 1.0
            last[p] = length
        n = _walk_forward(start, length, rec, rbox, xs, ys, x0, y0, x1, y1, tile, half,
                          amin, amax, tr, last, dummy, dummy1, False, True, pk, pp, pa, 0)
        for p in range(npix):
            tf[p] = tr[p]
            s0[p] = 0.0
            s1[p] = 0.0
            s2[p] = 0.0
        # back to front over the composited pairs: the moments
        j = n - 1
        while j >= 0:
            k = pk[j]
            e = start + k
            mx = rec[e, 0]
            my = rec[e, 1]
            c0, c1, c2 = float(rec[e, REC]), float(rec[e, REC + 1]), float(rec[e, REC + 2])
            m0 = m1 = m2 = m3 = m4 = m5 = m6 = m7 = m8 = m9 = m10 = m11 = m12 = m13 = \
                m14 = 0.0
            r0 = r1 = r2 = r3 = r4 = r5 = 0.0
            g0 = g1 = g2 = g3 = g4 = g5 = 0.0
            h0 = h1 = h2 = h3 = h4 = h5 = 0.0
            ww = 0.0
            while j >= 0 and pk[j] == k:
                p = pp[j]
                raw = pa[j]
                j -= 1
                x = float(xs[x0 + col_of[p]] - mx)
                y = float(ys[y0 + row_of[p]] - my)
                al = float(min(raw, amax))
                inv = 1.0 / (1.0 - al)
                tp = tr[p] * inv
                tr[p] = tp
                w = tp * al
                tfp = tf[p]
                d0 = tp * c0 - (s0[p] + tfp * bg0) * inv
                d1 = tp * c1 - (s1[p] + tfp * bg1) * inv
                d2 = tp * c2 - (s2[p] + tfp * bg2) * inv
                s0[p] += w * c0
                s1[p] += w * c1
                s2[p] += w * c2
                if pixels:
                    aq = float(raw)
                    dsum = d0 + d1 + d2
                    f4 = dsum * dsum * aq * aq
                    f20 = dsum * w * aq
                    f21 = f20
                    f22 = f20
                else:
                    aq = al if raw <= amax else 0.0
                    f4 = (d0 * d0 + d1 * d1 + d2 * d2) * aq * aq
                    wa = w * aq
                    f20 = d0 * wa
                    f21 = d1 * wa
                    f22 = d2 * wa
                xx = x * x
                xy = x * y
                yy = y * y
                fx = f4 * x
                fy = f4 * y
                fxx = f4 * xx
                fxy = f4 * xy
                fyy = f4 * yy
                m0 += f4
                m1 += fx
                m2 += fy
                m3 += fxx
                m4 += fxy
                m5 += fyy
                m6 += fxx * x
                m7 += fxx * y
                m8 += fxy * y
                m9 += fyy * y
                m10 += fxx * xx
                m11 += fxx * xy
                m12 += fxx * yy
                m13 += fxy * yy
                m14 += fyy * yy
                r0 += f20
                r1 += f20 * x
                r2 += f20 * y
                r3 += f20 * xx
                r4 += f20 * xy
                r5 += f20 * yy
                g0 += f21
                g1 += f21 * x
                g2 += f21 * y
                g3 += f21 * xx
                g4 += f21 * xy
                g5 += f21 * yy
                h0 += f22
                h1 += f22 * x
                h2 += f22 * y
                h3 += f22 * xx
                h4 += f22 * xy
                h5 += f22 * yy
                ww += w * w
            out = moments[e]
            out[0] = m0
            out[1] = m1
            out[2] = m2
            out[3] = m3
            out[4] = m4
            out[5] = m5
            out[6] = m6
            out[7] = m7
            out[8] = m8
            out[9] = m9
            out[10] = m10
            out[11] = m11
            out[12] = m12
            out[13] = m13
            out[14] = m14
            out[15] = r0
            out[16] = r1
            out[17] = r2
            out[18] = r3
            out[19] = r4
            out[20] = r5
            out[21] = g0
            out[22] = g1
            out[23] = g2
            out[24] = g3
            out[25] = g4
            out[26] = g5
            out[27] = h0
            out[28] = h1
            out[29] = h2
            out[30] = h3
            out[31] = h4
            out[32] = h5
            out[33] = ww


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
    fwd = np.empty(FWD)
    jac = np.zeros((10, 11))
    basis = np.empty(max(nk, 1))
    dbasis = np.empty((max(nk, 1), 3))
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
