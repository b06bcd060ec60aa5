"""The anchor's rasterization-free ψ (:class:`agilegs.service.nbv.anchor.proxy.ProxyPsi`) and
its gradient in the camera pose, per pose: the deep opacity map of the pose
(:class:`agilegs.service.nbv.anchor.visibility.OpacityMaps`), then every sample's footprint ×
in-frustum × transmittance term, its model's log form, and the weighted sum.

The rules are the pure-torch reference's, step for step (same formulas, same clamps, the
softplus depth with torch's threshold, ``grid_sample``'s trilinear read with border padding
and align_corners, whose coordinates pass gradient only strictly inside the grid). Arithmetic
is float64 whatever the inputs' dtype. The gradient is taken w.r.t. the pose's rotation
(columns: the camera axes in world) and centre, with the deep opacity map held fixed (the
reference deposits it without gradient).

Layouts: ``cams`` [B, 12] (c2w rotation row-major, then the centre); ``intr`` [8] (fx, fy,
cx, cy, width, height, near, edge); ``means`` [S, 3]; ``sigma6`` [S, 6] (xx, yy, zz, 2xy,
2xz, 2yz); ``weight`` [S]; ``rate`` [S, Q] (mode 1: Q = 1); ``kinds`` [Q] (mode 2: the
direction factor of each slot, 0-6); ``axes`` [S, 9] (mode 2: the local axes as the columns of
a row-major 3 × 3); visibility: ``occ`` [M, 3], ``mass`` [M], ``vis_prm`` [5] (centre x, y,
z, half depth, 1 when there is a grid else 0) and the grid's ``cells`` and ``bins``.
Modes: 0 linear (Σ w T), 1 log (Σ w log(1 + r T)), 2 directional (Σ w Σ_q log(1 + r_q f_q T)).

ψ alone (no gradient, no per-sample terms) takes shortcuts that move it by rounding only:
the image bounds' sigmoids of an axis from one exponential, and the directional form's
product over the slots as two interleaved products, its log1p from one logarithm. The
gradient's pass and the per-sample terms (which the directional fit reads) follow the
reference's operations as they are.
"""

from __future__ import annotations

import math

import numpy as np

from .common import inline as _inline
from .common import jit as _jit

_SOFTPLUS_THRESHOLD = 20.0


@_jit
def _sig(x: float) -> float:
    if x > 37.0:  # exp(-x) below half an ulp of 1: the quotient is 1.0 exactly
        return 1.0
    if x >= 0.0:
        return 1.0 / (1.0 + math.exp(-x))
    e = math.exp(x)
    return e / (1.0 + e)


@_jit
def _log1p(x: float) -> float:
    """log(1 + x) from one logarithm, within a few ulps of ``math.log1p``: the rounding of
    u = 1 + x corrected by x / (u - 1) (exact where u is 1)."""
    u = 1.0 + x
    if u == 1.0:
        return x
    return math.log(u) * (x / (u - 1.0))


@_jit
def _sig_pair(a: float, b: float, c: float) -> float:
    """sigmoid(a) * sigmoid(b) where a + b = L and ``c`` = exp(-L) (the two bounds of an
    image axis), from one exponential: with e = exp(-a), e / ((1 + e)(e + c)); the two
    sigmoids apart where e would leave the range of the formula."""
    if a > 600.0 or a < -600.0:
        return _sig(a) * _sig(b)
    e = math.exp(-a)
    return e / ((1.0 + e) * (e + c))


@_jit
def _deposit(cam: np.ndarray, intr: np.ndarray, occ: np.ndarray, mass: np.ndarray,
             vis_prm: np.ndarray, g: int, nb: int, grid: np.ndarray, tmp: np.ndarray,
             cum: np.ndarray) -> float:
    """The pose's deep opacity map: cumulated optical depth [nb + 1, g, g] into ``cum``;
    returns z0, the depth of the first slice's near end."""
    fx, fy, cx, cy, wd, ht = intr[0], intr[1], intr[2], intr[3], intr[4], intr[5]
    r00, r01, r02 = cam[0], cam[1], cam[2]
    r10, r11, r12 = cam[3], cam[4], cam[5]
    r20, r21, r22 = cam[6], cam[7], cam[8]
    t0, t1, t2 = cam[9], cam[10], cam[11]
    half = vis_prm[3]
    zc = (vis_prm[0] - t0) * r02 + (vis_prm[1] - t1) * r12 + (vis_prm[2] - t2) * r22
    z0 = zc - half
    dz = 2.0 * half / nb
    ex_t = r00 * t0 + r10 * t1 + r20 * t2
    ey_t = r01 * t0 + r11 * t1 + r21 * t2
    ez_t = r02 * t0 + r12 * t1 + r22 * t2
    cell_px = (wd / g) * (ht / g)
    grid[:] = 0.0
    filled = np.zeros(nb, dtype=np.bool_)  # the slices that hold a deposit
    for j in range(occ.shape[0]):
        px, py, pz = occ[j, 0], occ[j, 1], occ[j, 2]
        ox = (r00 * px + r10 * py + r20 * pz) - ex_t
        oy = (r01 * px + r11 * py + r21 * pz) - ey_t
        oz = (r02 * px + r12 * py + r22 * pz) - ez_t
        if not oz > 1e-6:
            continue
        cu = math.floor((fx * ox / oz + cx) / wd * g)
        cv = math.floor((fy * oy / oz + cy) / ht * g)
        if cu < 0 or cu >= g or cv < 0 or cv >= g:
            continue
        slab = math.floor((oz - z0) / dz)
        slab = min(max(slab, 0.0), nb - 1.0)
        grid[int(slab), int(cv), int(cu)] += mass[j] / (oz * oz) / cell_px
        filled[int(slab)] = True
    # the [1, 2, 1] / 4 blur along the rows, then along the columns (zero outside; an empty
    # slice stays zero)
    for k in range(nb):
        if not filled[k]:
            continue
        for i in range(g):
            for c in range(g):
                s = 0.5 * grid[k, i, c]
                if i > 0:
                    s += 0.25 * grid[k, i - 1, c]
                if i < g - 1:
                    s += 0.25 * grid[k, i + 1, c]
                tmp[k, i, c] = s
        for i in range(g):
            for c in range(g):
                s = 0.5 * tmp[k, i, c]
                if c > 0:
                    s += 0.25 * tmp[k, i, c - 1]
                if c < g - 1:
                    s += 0.25 * tmp[k, i, c + 1]
                grid[k, i, c] = s
    for i in range(g):
        for c in range(g):
            cum[0, i, c] = 0.0
    for k in range(nb):
        if filled[k]:
            for i in range(g):
                for c in range(g):
                    cum[k + 1, i, c] = cum[k, i, c] + grid[k, i, c]
        else:
            cum[k + 1, :, :] = cum[k, :, :]
    return z0


@_jit
def _axis(ix: float, size: int) -> tuple[int, int, float, float]:
    """The border-padded, align_corners linear read of an axis at coordinate ``ix``
    (already within [0, size - 1]): the two indices, the far one's weight, and whether the
    coordinate passes gradient (strictly inside)."""
    i0 = int(math.floor(ix))
    if i0 > size - 1:
        i0 = size - 1
    if i0 < 0:
        i0 = 0
    f = ix - i0
    i1 = i0 + 1
    if i1 > size - 1:
        i1 = size - 1  # weight f is 0 there
    inside = 1.0 if (ix > 0.0 and ix < size - 1.0) else 0.0
    return i0, i1, f, inside


@_inline
def _softplus_depth(z: float, near: float, beta: float) -> tuple[float, float]:
    """The depth softplus-smoothed above the near plane (torch's threshold) and its
    derivative in ``z``."""
    arg = beta * (z - near)
    if arg > _SOFTPLUS_THRESHOLD:
        return near + (z - near), 1.0
    return near + math.log1p(math.exp(arg)) / beta, _sig(arg)


@_inline
def _sigma_times(sigma6: np.ndarray, s: int, e0: float, e1: float, e2: float
                 ) -> tuple[float, float, float]:
    """Σ e for sample ``s``'s covariance (packed as ``sigma6``) and a vector e (3)."""
    sxx, syy, szz = sigma6[s, 0], sigma6[s, 1], sigma6[s, 2]
    sxy, sxz, syz = 0.5 * sigma6[s, 3], 0.5 * sigma6[s, 4], 0.5 * sigma6[s, 5]
    return (sxx * e0 + sxy * e1 + sxz * e2, sxy * e0 + syy * e1 + syz * e2,
            sxz * e0 + syz * e1 + szz * e2)


@_inline
def _dot(a0: float, a1: float, a2: float, b0: float, b1: float, b2: float) -> float:
    return a0 * b0 + a1 * b1 + a2 * b2


@_inline
def _footprint(qxx: float, qxy: float, qxz: float, qyy: float, qyz: float, qzz: float,
               tx: float, ty: float, iz2: float, ff: float, fg: float, gg: float
               ) -> tuple[float, float, float, float, float, float, float, float]:
    """The projected covariance's quadratic forms (pa, pb, pc), its low-passed entries (a,
    bb, cc), their determinant and the footprint sqrt(det) (clamped at 1e-12), from the
    camera axes' forms q.. and the sample's image-plane coordinates (tx, ty)."""
    pa = qxx - 2 * tx * qxz + tx * tx * qzz
    pb = qxy - tx * qyz - ty * qxz + tx * ty * qzz
    pc = qyy - 2 * ty * qyz + ty * ty * qzz
    a = ff * iz2 * pa + 0.3
    bb = fg * iz2 * pb
    cc = gg * iz2 * pc + 0.3
    det = a * cc - bb * bb
    return pa, pb, pc, a, bb, cc, det, math.sqrt(det if det > 1e-12 else 1e-12)


@_inline
def _footprint_grad(g_foot: float, foot: float, a: float, bb: float, cc: float, pa: float,
                    pb: float, pc: float, qxz: float, qyz: float, qzz: float, tx: float,
                    ty: float, iz2: float, izs: float, ff: float, fg: float, gg: float
                    ) -> tuple[float, float, float, float, float, float, float, float, float]:
    """The footprint's gradient ``g_foot`` carried to the smoothed depth (its part through
    the 1 / z² scale), tx, ty and the six quadratic forms (xx, xy, yy, xz, yz, zz)."""
    ga = g_foot * cc / (2.0 * foot)
    gc = g_foot * a / (2.0 * foot)
    gb = -g_foot * bb / foot
    izs3 = -2.0 * iz2 * izs
    g_zs = (ga * ff * pa + gb * fg * pb + gc * gg * pc) * izs3
    g_tx = ga * ff * iz2 * (-2 * qxz + 2 * tx * qzz) + gb * fg * iz2 * (-qyz + ty * qzz)
    g_ty = gb * fg * iz2 * (-qxz + tx * qzz) + gc * gg * iz2 * (-2 * qyz + 2 * ty * qzz)
    g_qxx = ga * ff * iz2
    g_qxy = gb * fg * iz2
    g_qyy = gc * gg * iz2
    g_qxz = ga * ff * iz2 * (-2 * tx) - gb * fg * iz2 * ty
    g_qyz = -gb * fg * iz2 * tx + gc * gg * iz2 * (-2 * ty)
    g_qzz = ga * ff * iz2 * tx * tx + gb * fg * iz2 * tx * ty + gc * gg * iz2 * ty * ty
    return g_zs, g_tx, g_ty, g_qxx, g_qxy, g_qyy, g_qxz, g_qyz, g_qzz


@_inline
def _in_frustum(z: float, u: float, v: float, near: float, wd: float, ht: float, edge: float,
                pairs: bool, c_wd: float, c_ht: float
                ) -> tuple[float, float, float, float, float, float]:
    """The smooth in-frustum test at depth ``z`` and pixel (u, v), and its five sigmoids
    (near, left, right, top, bottom); with ``pairs`` (ψ alone) each pair of opposite bounds
    from one exponential (``c_wd``, ``c_ht``: exp(-width / edge), exp(-height / edge)) and
    the four bounds' sigmoids left 0."""
    s0 = _sig((z - near) / (0.25 * near))
    if pairs:
        return (s0 * _sig_pair(u / edge, (wd - u) / edge, c_wd)
                * _sig_pair(v / edge, (ht - v) / edge, c_ht)), s0, 0.0, 0.0, 0.0, 0.0
    s1 = _sig(u / edge)
    s2 = _sig((wd - u) / edge)
    s3 = _sig(v / edge)
    s4 = _sig((ht - v) / edge)
    return s0 * s1 * s2 * s3 * s4, s0, s1, s2, s3, s4


@_inline
def _transmittance(cum: np.ndarray, iu: float, iv: float, idp: float, g: int, nb: int,
                   want_grad: bool) -> tuple[float, float, float, float]:
    """exp(-τ), τ the deep opacity map ``cum`` [nb + 1, g, g] read trilinearly at grid
    coordinates (iu, iv, idp) (clamped into the grid); with ``want_grad`` dτ / d(iu, iv,
    idp), zero where a coordinate is clamped (else zeros)."""
    iu_c = min(max(iu, 0.0), g - 1.0)
    iv_c = min(max(iv, 0.0), g - 1.0)
    id_c = min(max(idp, 0.0), float(nb))
    u0, u1, fu, in_u = _axis(iu_c, g)
    v0, v1, fv, in_v = _axis(iv_c, g)
    d0, d1, fd, in_d = _axis(id_c, nb + 1)
    c000 = cum[d0, v0, u0]
    c001 = cum[d0, v0, u1]
    c010 = cum[d0, v1, u0]
    c011 = cum[d0, v1, u1]
    c100 = cum[d1, v0, u0]
    c101 = cum[d1, v0, u1]
    c110 = cum[d1, v1, u0]
    c111 = cum[d1, v1, u1]
    e00 = c000 + fu * (c001 - c000)
    e01 = c010 + fu * (c011 - c010)
    e10 = c100 + fu * (c101 - c100)
    e11 = c110 + fu * (c111 - c110)
    e0 = e00 + fv * (e01 - e00)
    e1 = e10 + fv * (e11 - e10)
    vis = math.exp(-(e0 + fd * (e1 - e0)))
    if not want_grad:
        return vis, 0.0, 0.0, 0.0
    dtu = ((1 - fd) * ((1 - fv) * (c001 - c000) + fv * (c011 - c010))
           + fd * ((1 - fv) * (c101 - c100) + fv * (c111 - c110)))
    dtv = (1 - fd) * (e01 - e00) + fd * (e11 - e10)
    return vis, dtu * in_u, dtv * in_v, (e1 - e0) * in_d


@_inline
def _direction_factors(m0: float, m1: float, m2: float, t0: float, t1: float, t2: float,
                       axes: np.ndarray, s: int
                       ) -> tuple[float, float, float, float, float, float, float, float,
                                  float, float, float]:
    """The unit ray d (3) from the centre t to the sample's mean, the ray's length and that
    length clamped at 1e-12, and the sample's direction factors but the first (which is 1):
    1 - d_k² per world axis (3), 1 - (d · a_j)² per local axis a_j of ``axes`` (3)."""
    v0 = m0 - t0
    v1 = m1 - t1
    v2 = m2 - t2
    length = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    nrm = length if length > 1e-12 else 1e-12
    d0 = v0 / nrm
    d1 = v1 / nrm
    d2 = v2 / nrm
    c0 = d0 * axes[s, 0] + d1 * axes[s, 3] + d2 * axes[s, 6]
    c1 = d0 * axes[s, 1] + d1 * axes[s, 4] + d2 * axes[s, 7]
    c2 = d0 * axes[s, 2] + d1 * axes[s, 5] + d2 * axes[s, 8]
    return (d0, d1, d2, length, nrm, 1.0 - d0 * d0, 1.0 - d1 * d1, 1.0 - d2 * d2,
            1.0 - c0 * c0, 1.0 - c1 * c1, 1.0 - c2 * c2)


@_inline
def _slots_log(term: float, f7: np.ndarray, kinds: np.ndarray, rate: np.ndarray, s: int,
               nq: int) -> float:
    """Σ_q log(1 + term f_q r_q) over sample ``s``'s slots, ψ alone: one log1p of
    Π_q (1 + x_q) - 1, accumulated as p + x + p x (no cancellation for small x) in two
    running products (even and odd slots, half the chain of dependent operations)."""
    acc = 0.0
    acc2 = 0.0
    for q in range(0, nq - 1, 2):
        xq = term * f7[kinds[q]] * rate[s, q]
        xq2 = term * f7[kinds[q + 1]] * rate[s, q + 1]
        acc = acc + xq + acc * xq
        acc2 = acc2 + xq2 + acc2 * xq2
    if nq % 2 == 1:
        xq = term * f7[kinds[nq - 1]] * rate[s, nq - 1]
        acc = acc + xq + acc * xq
    return _log1p(acc + acc2 + acc * acc2)


@_inline
def _ray_grad(dd: np.ndarray, gf7: np.ndarray, axes: np.ndarray, s: int, w: float,
              length: float, nrm: float) -> tuple[float, float, float]:
    """The direction factors' gradient ``gf7`` (times the weight ``w``) carried to the unit
    ray ``dd``, then to the ray's end at the sample (minus the centre's gradient)."""
    gd0 = -2.0 * dd[0] * gf7[1] * w
    gd1 = -2.0 * dd[1] * gf7[2] * w
    gd2 = -2.0 * dd[2] * gf7[3] * w
    for j in range(3):
        a0, a1, a2 = axes[s, j], axes[s, 3 + j], axes[s, 6 + j]
        cj = dd[0] * a0 + dd[1] * a1 + dd[2] * a2
        k2 = -2.0 * cj * gf7[4 + j] * w
        gd0 += k2 * a0
        gd1 += k2 * a1
        gd2 += k2 * a2
    if length > 1e-12:
        dot = gd0 * dd[0] + gd1 * dd[1] + gd2 * dd[2]
        return (gd0 - dot * dd[0]) / nrm, (gd1 - dot * dd[1]) / nrm, (gd2 - dot * dd[2]) / nrm
    return gd0 / nrm, gd1 / nrm, gd2 / nrm


@_jit
def proxy_psi(cams: np.ndarray, intr: np.ndarray, means: np.ndarray, sigma6: np.ndarray,
              weight: np.ndarray, rate: np.ndarray, kinds: np.ndarray, axes: np.ndarray,
              mode: int, occ: np.ndarray, mass: np.ndarray, vis_prm: np.ndarray, cells: int,
              bins: int, want_grad: bool, per_sample: bool, b0: int, b1: int,
              psi: np.ndarray, grad: np.ndarray, terms_out: np.ndarray,
              accumulate: bool, acc_out: np.ndarray) -> None:
    """ψ of poses b0..b1-1 into ``psi`` [B]; with ``want_grad`` ∂ψ/∂(rotation, centre) into
    ``grad`` [B, 12] (the layout of ``cams``); with ``per_sample`` the unweighted terms
    footprint × inside × visible into ``terms_out`` [B, S] (ψ is then not reduced) and, with
    ``accumulate`` too, every term times each of the sample's seven direction factors (with
    ``axes``) added to ``acc_out`` [S, 7] (one thread: the poses add to the same rows)."""
    fx, fy, cx, cy, wd, ht, near, edge = (intr[0], intr[1], intr[2], intr[3], intr[4],
                                          intr[5], intr[6], intr[7])
    ff, fg, gg = fx * fx, fx * fy, fy * fy
    beta = 20.0 / near
    has_grid = vis_prm[4] > 0.5
    g = cells
    nb = bins
    grid = np.zeros((nb, g, g))
    tmp = np.zeros((nb, g, g))
    cum = np.zeros((nb + 1, g, g))
    dz = 2.0 * vis_prm[3] / nb
    nq = rate.shape[1]
    f7 = np.ones(7)  # the direction factors (the first is 1)
    gf7 = np.empty(7)
    # (the pairs need exp(-width / edge) well inside the range of floats)
    reduce_only = not want_grad and not per_sample and wd / edge < 600.0 and ht / edge < 600.0
    c_wd = math.exp(-wd / edge) if reduce_only else 0.0
    c_ht = math.exp(-ht / edge) if reduce_only else 0.0
    dd = np.empty(3)
    for b in range(b0, b1):
        cam = cams[b]
        z0 = 0.0
        if has_grid:
            z0 = _deposit(cam, intr, occ, mass, vis_prm, g, nb, grid, tmp, cum)
        ex0, ex1, ex2 = cam[0], cam[3], cam[6]
        ey0, ey1, ey2 = cam[1], cam[4], cam[7]
        ez0, ez1, ez2 = cam[2], cam[5], cam[8]
        t0, t1, t2 = cam[9], cam[10], cam[11]
        ex_t = ex0 * t0 + ex1 * t1 + ex2 * t2
        ey_t = ey0 * t0 + ey1 * t1 + ey2 * t2
        ez_t = ez0 * t0 + ez1 * t1 + ez2 * t2
        total = 0.0
        gex0 = gex1 = gex2 = 0.0
        gey0 = gey1 = gey2 = 0.0
        gez0 = gez1 = gez2 = 0.0
        gt0 = gt1 = gt2 = 0.0
        for s in range(means.shape[0]):
            m0, m1, m2 = means[s, 0], means[s, 1], means[s, 2]
            x = (ex0 * m0 + ex1 * m1 + ex2 * m2) - ex_t
            y = (ey0 * m0 + ey1 * m1 + ey2 * m2) - ey_t
            z = (ez0 * m0 + ez1 * m1 + ez2 * m2) - ez_t
            zs, dzs = _softplus_depth(z, near, beta)
            izs = 1.0 / zs
            tx = x / zs
            ty = y / zs
            # footprint: the quadratic forms of the camera axes
            sx0, sx1, sx2 = _sigma_times(sigma6, s, ex0, ex1, ex2)
            sy0, sy1, sy2 = _sigma_times(sigma6, s, ey0, ey1, ey2)
            sz0, sz1, sz2 = _sigma_times(sigma6, s, ez0, ez1, ez2)
            qxz = _dot(ex0, ex1, ex2, sz0, sz1, sz2)
            qyz = _dot(ey0, ey1, ey2, sz0, sz1, sz2)
            qzz = _dot(ez0, ez1, ez2, sz0, sz1, sz2)
            iz2 = 1.0 / (zs * zs)
            pa, pb, pc, a, bb, cc, det, foot = _footprint(
                _dot(ex0, ex1, ex2, sx0, sx1, sx2), _dot(ex0, ex1, ex2, sy0, sy1, sy2), qxz,
                _dot(ey0, ey1, ey2, sy0, sy1, sy2), qyz, qzz, tx, ty, iz2, ff, fg, gg)
            # the smooth in-frustum test
            inside, s0, s1, s2, s3, s4 = _in_frustum(z, fx * x / zs + cx, fy * y / zs + cy,
                                                     near, wd, ht, edge, reduce_only, c_wd,
                                                     c_ht)
            # the transmittance from the deep opacity map
            vis, tu, tv, td = 1.0, 0.0, 0.0, 0.0
            zt = z if z > 1e-6 else 1e-6
            if has_grid:
                vis, tu, tv, td = _transmittance(
                    cum, (fx * x / zt + cx) / wd * g - 0.5, (fy * y / zt + cy) / ht * g - 0.5,
                    (z - z0) / dz - 1.0, g, nb, want_grad)
            term = foot * inside * vis
            if per_sample:
                terms_out[b, s] = term
                if accumulate:
                    _, _, _, _, _, f1, f2, f3, f4, f5, f6 = _direction_factors(
                        m0, m1, m2, t0, t1, t2, axes, s)
                    acc_out[s, 0] += term
                    acc_out[s, 1] += term * f1
                    acc_out[s, 2] += term * f2
                    acc_out[s, 3] += term * f3
                    acc_out[s, 4] += term * f4
                    acc_out[s, 5] += term * f5
                    acc_out[s, 6] += term * f6
                continue
            # the model's log form and its derivative in the term (and direction factors)
            w = weight[s]
            if mode == 0:
                total += w * term
                gterm = w
            elif mode == 1:
                r = rate[s, 0]
                total += w * math.log1p(term * r)
                gterm = w * r / (1.0 + term * r)
            else:
                (dd[0], dd[1], dd[2], length, nrm, f7[1], f7[2], f7[3], f7[4], f7[5],
                 f7[6]) = _direction_factors(m0, m1, m2, t0, t1, t2, axes, s)
                if not want_grad:
                    total += w * _slots_log(term, f7, kinds, rate, s, nq)
                    continue
                # the reference's one chain, with the derivatives in the term and in each
                # direction factor
                for k in range(7):
                    gf7[k] = 0.0
                acc = 0.0
                gterm = 0.0
                for q in range(nq):
                    kq = kinds[q]
                    tf = term * f7[kq]
                    r = rate[s, q]
                    xq = tf * r
                    acc = acc + xq + acc * xq
                    den = 1.0 / (1.0 + xq)
                    gterm += f7[kq] * r * den
                    gf7[kq] += term * r * den
                total += w * math.log1p(acc)
                gterm *= w
                r0, r1, r2 = _ray_grad(dd, gf7, axes, s, w, length, nrm)
                gt0 -= r0
                gt1 -= r1
                gt2 -= r2
            if not want_grad or gterm == 0.0:
                continue
            # term = foot * inside * vis
            g_foot = gterm * inside * vis
            g_in = gterm * foot * vis
            g_vis = gterm * foot * inside
            gx = 0.0
            gy = 0.0
            gz = 0.0
            g_zs = 0.0
            # footprint
            if det > 1e-12:
                fz, g_tx, g_ty, g_qxx, g_qxy, g_qyy, g_qxz, g_qyz, g_qzz = _footprint_grad(
                    g_foot, foot, a, bb, cc, pa, pb, pc, qxz, qyz, qzz, tx, ty, iz2, izs, ff,
                    fg, gg)
                g_zs += fz
                gx += g_tx * izs
                gy += g_ty * izs
                g_zs += -(g_tx * tx + g_ty * ty) * izs
                gex0 += _dot(2 * g_qxx, g_qxy, g_qxz, sx0, sy0, sz0)
                gex1 += _dot(2 * g_qxx, g_qxy, g_qxz, sx1, sy1, sz1)
                gex2 += _dot(2 * g_qxx, g_qxy, g_qxz, sx2, sy2, sz2)
                gey0 += _dot(g_qxy, 2 * g_qyy, g_qyz, sx0, sy0, sz0)
                gey1 += _dot(g_qxy, 2 * g_qyy, g_qyz, sx1, sy1, sz1)
                gey2 += _dot(g_qxy, 2 * g_qyy, g_qyz, sx2, sy2, sz2)
                gez0 += _dot(g_qxz, g_qyz, 2 * g_qzz, sx0, sy0, sz0)
                gez1 += _dot(g_qxz, g_qyz, 2 * g_qzz, sx1, sy1, sz1)
                gez2 += _dot(g_qxz, g_qyz, 2 * g_qzz, sx2, sy2, sz2)
            # in-frustum test
            gi = g_in * inside
            dlu = ((1.0 - s1) - (1.0 - s2)) / edge
            dlv = ((1.0 - s3) - (1.0 - s4)) / edge
            gx += gi * dlu * fx * izs
            gy += gi * dlv * fy * izs
            gz += gi * (1.0 - s0) / (0.25 * near)
            g_zs += gi * (dlu * (-fx * x * iz2) + dlv * (-fy * y * iz2))
            # transmittance
            if has_grid:
                gtau = -g_vis * vis
                gu = gtau * tu * g / wd
                gv = gtau * tv * g / ht
                zt_ok = 1.0 if z >= 1e-6 else 0.0
                izt = 1.0 / zt
                gx += gu * fx * izt
                gy += gv * fy * izt
                gz += (-(gu * fx * x + gv * fy * y) * izt * izt) * zt_ok
                gz += gtau * td / dz
            gz += g_zs * dzs
            # camera coordinates -> the camera axes and the centre
            q0 = m0 - t0
            q1 = m1 - t1
            q2 = m2 - t2
            gex0, gex1, gex2 = gex0 + gx * q0, gex1 + gx * q1, gex2 + gx * q2
            gey0, gey1, gey2 = gey0 + gy * q0, gey1 + gy * q1, gey2 + gy * q2
            gez0, gez1, gez2 = gez0 + gz * q0, gez1 + gz * q1, gez2 + gz * q2
            gt0 -= gx * ex0 + gy * ey0 + gz * ez0
            gt1 -= gx * ex1 + gy * ey1 + gz * ez1
            gt2 -= gx * ex2 + gy * ey2 + gz * ez2
        psi[b] = total
        if want_grad:
            grad[b, 0], grad[b, 3], grad[b, 6] = gex0, gex1, gex2
            grad[b, 1], grad[b, 4], grad[b, 7] = gey0, gey1, gey2
            grad[b, 2], grad[b, 5], grad[b, 8] = gez0, gez1, gez2
            grad[b, 9], grad[b, 10], grad[b, 11] = gt0, gt1, gt2
