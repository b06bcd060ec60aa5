"""The Triton kernels of :mod:`agilegs.service.nbv.kernels.gpu_proxy` (imported only where
Triton imports): the deep opacity maps of every pose (a deposit, then a blur and a cumulated
sum per pose), and ψ with its pose gradient, one program per (pose, chunk of samples).

Float64 arithmetic throughout (as the CPU kernel ``kernels.proxy.proxy_psi``); the per-sample
body is that kernel's, lane by lane, its branches as selections. The per-sample arrays are
stored a row per component (means [3, S], covariances [6, S], rates [Q, S], local axes
[9, S]; the occluders [3, M]), so that a load of the lanes' samples reads one run of memory."""

# mypy: ignore-errors
# ruff: noqa: N803, N806

import triton
import triton.language as tl

F64 = tl.float64


@triton.jit
def _sig(x):
    """The logistic function, stable on either side."""
    e = tl.exp(-tl.abs(x))
    return tl.where(x >= 0, 1.0 / (1.0 + e), e / (1.0 + e))


@triton.jit
def _log1p(x):
    """log(1 + x), within a few ulps: the rounding of u = 1 + x corrected by x / (u - 1)
    (exact where u is 1)."""
    u = 1.0 + x
    one = u == 1.0
    return tl.where(one, x, tl.log(u) * (x / tl.where(one, 1.0, u - 1.0)))


@triton.jit
def _cam(cam_ptr, b):
    """Pose b's camera axes in world (the columns of its rotation) and its centre."""
    c = cam_ptr + b * 12
    return (tl.load(c), tl.load(c + 3), tl.load(c + 6), tl.load(c + 1), tl.load(c + 4),
            tl.load(c + 7), tl.load(c + 2), tl.load(c + 5), tl.load(c + 8), tl.load(c + 9),
            tl.load(c + 10), tl.load(c + 11))


@triton.jit
def _z0(prm_ptr, ez0, ez1, ez2, t0, t1, t2, BINS):
    """The depth of the first slice's near end and the slices' depth."""
    half = tl.load(prm_ptr + 11)
    zc = ((tl.load(prm_ptr + 8) - t0) * ez0 + (tl.load(prm_ptr + 9) - t1) * ez1
          + (tl.load(prm_ptr + 10) - t2) * ez2)
    return zc - half, 2.0 * half / BINS


@triton.jit
def deposit_kernel(cam_ptr, prm_ptr, occ_ptr, mass_ptr, grid_ptr, M, CELLS, BINS,
                   BLOCK: tl.constexpr):
    """Program (b, k): the occluders k·BLOCK.. (``occ`` [3, M]) of pose b added into its slices
    ``grid`` [B, BINS, CELLS, CELLS] (the mass over depth² and a cell's pixels, in the cell
    and slice of the occluder's centre)."""
    b = tl.program_id(0)
    j = tl.program_id(1) * BLOCK + tl.arange(0, BLOCK)
    ok = j < M
    ex0, ex1, ex2, ey0, ey1, ey2, ez0, ez1, ez2, t0, t1, t2 = _cam(cam_ptr, b)
    fx = tl.load(prm_ptr)
    fy = tl.load(prm_ptr + 1)
    cx = tl.load(prm_ptr + 2)
    cy = tl.load(prm_ptr + 3)
    wd = tl.load(prm_ptr + 4)
    ht = tl.load(prm_ptr + 5)
    z0, dz = _z0(prm_ptr, ez0, ez1, ez2, t0, t1, t2, BINS)
    g = CELLS * 1.0
    px = tl.load(occ_ptr + j, mask=ok, other=0.0)
    py = tl.load(occ_ptr + M + j, mask=ok, other=0.0)
    pz = tl.load(occ_ptr + 2 * M + j, mask=ok, other=0.0)
    ox = (ex0 * px + ex1 * py + ex2 * pz) - (ex0 * t0 + ex1 * t1 + ex2 * t2)
    oy = (ey0 * px + ey1 * py + ey2 * pz) - (ey0 * t0 + ey1 * t1 + ey2 * t2)
    oz = (ez0 * px + ez1 * py + ez2 * pz) - (ez0 * t0 + ez1 * t1 + ez2 * t2)
    ozs = tl.maximum(oz, 1e-6)
    cu = tl.floor((fx * ox / ozs + cx) / wd * g)
    cv = tl.floor((fy * oy / ozs + cy) / ht * g)
    slab = tl.minimum(tl.maximum(tl.floor((oz - z0) / dz), 0.0), BINS - 1.0)
    ok = ok & (oz > 1e-6) & (cu >= 0) & (cu < g) & (cv >= 0) & (cv < g)
    iu = tl.minimum(tl.maximum(cu, 0.0), g - 1.0).to(tl.int64)
    iv = tl.minimum(tl.maximum(cv, 0.0), g - 1.0).to(tl.int64)
    val = tl.load(mass_ptr + j, mask=ok, other=0.0) / (ozs * ozs) / ((wd / g) * (ht / g))
    idx = ((b * BINS + slab.to(tl.int64)) * CELLS + iv) * CELLS + iu
    tl.atomic_add(grid_ptr + idx, val, mask=ok, sem="relaxed")


@triton.jit
def _rows(sl, i, c, ok, CELLS):
    """Slice ``sl``'s [1, 2, 1] / 4 blur along the rows at cell (i, c), zero outside."""
    s = 0.5 * tl.load(sl + i * CELLS + c, mask=ok, other=0.0)
    s += 0.25 * tl.load(sl + (i - 1) * CELLS + c, mask=ok & (i > 0), other=0.0)
    s += 0.25 * tl.load(sl + (i + 1) * CELLS + c, mask=ok & (i < CELLS - 1), other=0.0)
    return s


@triton.jit
def cumulate_kernel(grid_ptr, cum_ptr, CELLS, BINS, LANES: tl.constexpr):
    """Program b: pose b's slices blurred by [1, 2, 1] / 4 along the rows, then the columns,
    and summed front to back into ``cum`` [B, BINS + 1, CELLS, CELLS] (a zero slice first)."""
    b = tl.program_id(0)
    lane = tl.arange(0, LANES)
    n = CELLS * CELLS
    ok = lane < n
    i = lane // CELLS
    c = lane % CELLS
    acc = tl.zeros((LANES,), F64)
    out = cum_ptr + b.to(tl.int64) * (BINS + 1) * n
    tl.store(out + lane, acc, mask=ok)
    for k in range(BINS):
        sl = grid_ptr + (b.to(tl.int64) * BINS + k) * n
        s = 0.5 * _rows(sl, i, c, ok, CELLS)
        s += 0.25 * _rows(sl, i, c - 1, ok & (c > 0), CELLS)
        s += 0.25 * _rows(sl, i, c + 1, ok & (c < CELLS - 1), CELLS)
        acc += s
        tl.store(out + (k + 1) * n + lane, acc, mask=ok)


@triton.jit
def _axis(ix, size):
    """The border-padded, align_corners linear read of an axis at ``ix`` (within
    [0, size - 1]): the two indices, the far one's weight, and 1 where the coordinate passes
    gradient (strictly inside)."""
    i0 = tl.minimum(tl.maximum(tl.floor(ix), 0.0), size - 1.0)
    f = ix - i0
    i1 = tl.minimum(i0 + 1.0, size - 1.0)
    inside = tl.where((ix > 0.0) & (ix < size - 1.0), 1.0, 0.0)
    return i0.to(tl.int64), i1.to(tl.int64), f, inside


@triton.jit
def _transmittance(cum, iu, iv, idp, CELLS, BINS, ok):
    """exp(-τ) at grid coordinates (iu, iv, idp) of the pose's cumulated map ``cum``
    (clamped into it), and dτ / d(iu, iv, idp), zero where a coordinate is clamped."""
    g = CELLS * 1.0
    u0, u1, fu, in_u = _axis(tl.minimum(tl.maximum(iu, 0.0), g - 1.0), g)
    v0, v1, fv, in_v = _axis(tl.minimum(tl.maximum(iv, 0.0), g - 1.0), g)
    d0, d1, fd, in_d = _axis(tl.minimum(tl.maximum(idp, 0.0), BINS * 1.0), BINS + 1.0)
    r00 = (d0 * CELLS + v0) * CELLS
    r01 = (d0 * CELLS + v1) * CELLS
    r10 = (d1 * CELLS + v0) * CELLS
    r11 = (d1 * CELLS + v1) * CELLS
    c000 = tl.load(cum + r00 + u0, mask=ok, other=0.0)
    c001 = tl.load(cum + r00 + u1, mask=ok, other=0.0)
    c010 = tl.load(cum + r01 + u0, mask=ok, other=0.0)
    c011 = tl.load(cum + r01 + u1, mask=ok, other=0.0)
    c100 = tl.load(cum + r10 + u0, mask=ok, other=0.0)
    c101 = tl.load(cum + r10 + u1, mask=ok, other=0.0)
    c110 = tl.load(cum + r11 + u0, mask=ok, other=0.0)
    c111 = tl.load(cum + r11 + u1, mask=ok, other=0.0)
    e00 = c000 + fu * (c001 - c000)
    e01 = c010 + fu * (c011 - c010)
    e10 = c100 + fu * (c101 - c100)
    e11 = c110 + fu * (c111 - c110)
    e0 = e00 + fv * (e01 - e00)
    e1 = e10 + fv * (e11 - e10)
    vis = tl.exp(-(e0 + fd * (e1 - e0)))
    dtu = ((1 - fd) * ((1 - fv) * (c001 - c000) + fv * (c011 - c010))
           + fd * ((1 - fv) * (c101 - c100) + fv * (c111 - c110)))
    dtv = (1 - fd) * (e01 - e00) + fd * (e11 - e10)
    return vis, dtu * in_u, dtv * in_v, (e1 - e0) * in_d


@triton.jit
def _pick(k, f1, f2, f3, f4, f5, f6):
    """The direction factor of kind ``k`` (0: 1)."""
    return tl.where(k == 1, f1, tl.where(k == 2, f2, tl.where(k == 3, f3, tl.where(
        k == 4, f4, tl.where(k == 5, f5, tl.where(k == 6, f6, 1.0))))))


@triton.jit
def _local(axes_ptr, s, S, ok, j, d0, d1, d2):
    """Sample s's local axis j (a column of its row-major 3 × 3, the nine entries as rows of
    ``axes`` [9, S]) and its cosine with d."""
    a0 = tl.load(axes_ptr + j * S + s, mask=ok, other=0.0)
    a1 = tl.load(axes_ptr + (3 + j) * S + s, mask=ok, other=0.0)
    a2 = tl.load(axes_ptr + (6 + j) * S + s, mask=ok, other=0.0)
    return a0, a1, a2, d0 * a0 + d1 * a1 + d2 * a2


@triton.jit
def _footprint_grad(g_foot, foot, a, bb, cc, pa, pb, pc, qxz, qyz, qzz, tx, ty, iz2, izs,
                    ff, fg, gg):
    """The footprint's gradient carried to the smoothed depth, tx, ty and the six quadratic
    forms (xx, xy, yy, xz, yz, zz) (``kernels.proxy._footprint_grad``)."""
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


@triton.jit
def psi_kernel(cam_ptr, prm_ptr, means_ptr, sig_ptr, w_ptr, rate_ptr, kinds_ptr, axes_ptr,
               cum_ptr, part_ptr, terms_ptr, S, Q, CHUNK, CELLS, BINS,
               MODE: tl.constexpr, HAS_GRID: tl.constexpr, WANT_GRAD: tl.constexpr,
               PER_SAMPLE: tl.constexpr, BLOCK: tl.constexpr):
    """Program (b, p): samples p·CHUNK.. of pose b. ψ's part and its gradient in the pose's
    rotation and centre (the layout of ``cams``) into ``part`` [B, P, 13] (ψ first), or,
    with ``PER_SAMPLE``, the terms footprint × inside × visible into ``terms`` [B, S].
    MODE: 0 linear, 1 log, 2 directional (``kernels.proxy.proxy_psi``)."""
    b = tl.program_id(0)
    p = tl.program_id(1)
    ex0, ex1, ex2, ey0, ey1, ey2, ez0, ez1, ez2, t0, t1, t2 = _cam(cam_ptr, b)
    fx = tl.load(prm_ptr)
    fy = tl.load(prm_ptr + 1)
    cx = tl.load(prm_ptr + 2)
    cy = tl.load(prm_ptr + 3)
    wd = tl.load(prm_ptr + 4)
    ht = tl.load(prm_ptr + 5)
    near = tl.load(prm_ptr + 6)
    edge = tl.load(prm_ptr + 7)
    ff = fx * fx
    fg = fx * fy
    gg = fy * fy
    beta = 20.0 / near
    g = CELLS * 1.0
    z0, dz = _z0(prm_ptr, ez0, ez1, ez2, t0, t1, t2, BINS)
    cum = cum_ptr + b.to(tl.int64) * (BINS + 1) * CELLS * CELLS
    ex_t = ex0 * t0 + ex1 * t1 + ex2 * t2
    ey_t = ey0 * t0 + ey1 * t1 + ey2 * t2
    ez_t = ez0 * t0 + ez1 * t1 + ez2 * t2
    zero = tl.zeros((BLOCK,), F64)
    tot = zero
    gex0 = zero
    gex1 = zero
    gex2 = zero
    gey0 = zero
    gey1 = zero
    gey2 = zero
    gez0 = zero
    gez1 = zero
    gez2 = zero
    gt0 = zero
    gt1 = zero
    gt2 = zero
    for it in range(0, CHUNK, BLOCK):
        s = p * CHUNK + it + tl.arange(0, BLOCK)
        ok = s < S
        m0 = tl.load(means_ptr + s, mask=ok, other=0.0)
        m1 = tl.load(means_ptr + S + s, mask=ok, other=0.0)
        m2 = tl.load(means_ptr + 2 * S + s, mask=ok, other=0.0)
        x = (ex0 * m0 + ex1 * m1 + ex2 * m2) - ex_t
        y = (ey0 * m0 + ey1 * m1 + ey2 * m2) - ey_t
        z = (ez0 * m0 + ez1 * m1 + ez2 * m2) - ez_t
        # the depth softplus-smoothed above the near plane (torch's threshold)
        arg = beta * (z - near)
        lin = arg > 20.0
        zs = tl.where(lin, near + (z - near), near + _log1p(tl.exp(tl.minimum(arg, 20.0))) / beta)
        dzs = tl.where(lin, 1.0, _sig(arg))
        izs = 1.0 / zs
        tx = x / zs
        ty = y / zs
        # the footprint: the quadratic forms of the camera axes
        sxx = tl.load(sig_ptr + s, mask=ok, other=0.0)
        syy = tl.load(sig_ptr + S + s, mask=ok, other=0.0)
        szz = tl.load(sig_ptr + 2 * S + s, mask=ok, other=0.0)
        sxy = 0.5 * tl.load(sig_ptr + 3 * S + s, mask=ok, other=0.0)
        sxz = 0.5 * tl.load(sig_ptr + 4 * S + s, mask=ok, other=0.0)
        syz = 0.5 * tl.load(sig_ptr + 5 * S + s, mask=ok, other=0.0)
        sx0 = sxx * ex0 + sxy * ex1 + sxz * ex2
        sx1 = sxy * ex0 + syy * ex1 + syz * ex2
        sx2 = sxz * ex0 + syz * ex1 + szz * ex2
        sy0 = sxx * ey0 + sxy * ey1 + sxz * ey2
        sy1 = sxy * ey0 + syy * ey1 + syz * ey2
        sy2 = sxz * ey0 + syz * ey1 + szz * ey2
        sz0 = sxx * ez0 + sxy * ez1 + sxz * ez2
        sz1 = sxy * ez0 + syy * ez1 + syz * ez2
        sz2 = sxz * ez0 + syz * ez1 + szz * ez2
        qxx = ex0 * sx0 + ex1 * sx1 + ex2 * sx2
        qxy = ex0 * sy0 + ex1 * sy1 + ex2 * sy2
        qyy = ey0 * sy0 + ey1 * sy1 + ey2 * sy2
        qxz = ex0 * sz0 + ex1 * sz1 + ex2 * sz2
        qyz = ey0 * sz0 + ey1 * sz1 + ey2 * sz2
        qzz = ez0 * sz0 + ez1 * sz1 + ez2 * sz2
        iz2 = 1.0 / (zs * zs)
        pa = qxx - 2 * tx * qxz + tx * tx * qzz
        pb = qxy - tx * qyz - ty * qxz + tx * ty * qzz
        pc = qyy - 2 * ty * qyz + ty * ty * qzz
        a = ff * iz2 * pa + 0.3
        bb = fg * iz2 * pb
        cc = gg * iz2 * pc + 0.3
        det = a * cc - bb * bb
        foot = tl.sqrt(tl.maximum(det, 1e-12))
        # the smooth in-frustum test
        u = fx * x / zs + cx
        v = fy * y / zs + cy
        s0 = _sig((z - near) / (0.25 * near))
        s1 = _sig(u / edge)
        s2 = _sig((wd - u) / edge)
        s3 = _sig(v / edge)
        s4 = _sig((ht - v) / edge)
        inside = s0 * s1 * s2 * s3 * s4
        # the transmittance from the deep opacity map
        zt = tl.maximum(z, 1e-6)
        if HAS_GRID:
            vis, tu, tv, td = _transmittance(
                cum, (fx * x / zt + cx) / wd * g - 0.5, (fy * y / zt + cy) / ht * g - 0.5,
                (z - z0) / dz - 1.0, CELLS, BINS, ok)
        else:
            vis = zero + 1.0
            tu = zero
            tv = zero
            td = zero
        term = foot * inside * vis
        if PER_SAMPLE:
            tl.store(terms_ptr + b.to(tl.int64) * S + s, term, mask=ok)
        else:
            w = tl.load(w_ptr + s, mask=ok, other=0.0)
            if MODE == 0:
                tot += w * term
                gterm = w
            elif MODE == 1:
                r = tl.load(rate_ptr + s, mask=ok, other=0.0)
                tot += w * _log1p(term * r)
                gterm = w * r / (1.0 + term * r)
            else:
                # the direction factors of the unit ray d from the centre to the sample
                v0 = m0 - t0
                v1 = m1 - t1
                v2 = m2 - t2
                length = tl.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
                nrm = tl.maximum(length, 1e-12)
                d0 = v0 / nrm
                d1 = v1 / nrm
                d2 = v2 / nrm
                a00, a01, a02, c0 = _local(axes_ptr, s, S, ok, 0, d0, d1, d2)
                a10, a11, a12, c1 = _local(axes_ptr, s, S, ok, 1, d0, d1, d2)
                a20, a21, a22, c2 = _local(axes_ptr, s, S, ok, 2, d0, d1, d2)
                f1 = 1.0 - d0 * d0
                f2 = 1.0 - d1 * d1
                f3 = 1.0 - d2 * d2
                f4 = 1.0 - c0 * c0
                f5 = 1.0 - c1 * c1
                f6 = 1.0 - c2 * c2
                acc = zero
                gterm = zero
                g1 = zero
                g2 = zero
                g3 = zero
                g4 = zero
                g5 = zero
                g6 = zero
                for q in range(Q):
                    kq = tl.load(kinds_ptr + q)
                    fq = _pick(kq, f1, f2, f3, f4, f5, f6)
                    r = tl.load(rate_ptr + q * S + s, mask=ok, other=0.0)
                    xq = term * fq * r
                    acc = acc + xq + acc * xq
                    if WANT_GRAD:
                        den = 1.0 / (1.0 + xq)
                        gterm += fq * r * den
                        h = term * r * den
                        g1 += tl.where(kq == 1, h, 0.0)
                        g2 += tl.where(kq == 2, h, 0.0)
                        g3 += tl.where(kq == 3, h, 0.0)
                        g4 += tl.where(kq == 4, h, 0.0)
                        g5 += tl.where(kq == 5, h, 0.0)
                        g6 += tl.where(kq == 6, h, 0.0)
                tot += w * _log1p(acc)
                gterm *= w
                if WANT_GRAD:
                    # the factors' gradient carried to the ray, then to the centre
                    gd0 = -2.0 * d0 * g1 * w
                    gd1 = -2.0 * d1 * g2 * w
                    gd2 = -2.0 * d2 * g3 * w
                    k2 = -2.0 * c0 * g4 * w
                    gd0 += k2 * a00
                    gd1 += k2 * a01
                    gd2 += k2 * a02
                    k2 = -2.0 * c1 * g5 * w
                    gd0 += k2 * a10
                    gd1 += k2 * a11
                    gd2 += k2 * a12
                    k2 = -2.0 * c2 * g6 * w
                    gd0 += k2 * a20
                    gd1 += k2 * a21
                    gd2 += k2 * a22
                    dot = tl.where(length > 1e-12, gd0 * d0 + gd1 * d1 + gd2 * d2, 0.0)
                    gt0 -= (gd0 - dot * d0) / nrm
                    gt1 -= (gd1 - dot * d1) / nrm
                    gt2 -= (gd2 - dot * d2) / nrm
            if WANT_GRAD:
                gterm = tl.where(ok, gterm, 0.0)
                g_foot = gterm * inside * vis
                g_in = gterm * foot * vis
                g_vis = gterm * foot * inside
                # the footprint (where its determinant is not clamped)
                fz, g_tx, g_ty, g_qxx, g_qxy, g_qyy, g_qxz, g_qyz, g_qzz = _footprint_grad(
                    g_foot, foot, a, bb, cc, pa, pb, pc, qxz, qyz, qzz, tx, ty, iz2, izs,
                    ff, fg, gg)
                on = (det > 1e-12) & (gterm != 0.0)
                fz = tl.where(on, fz, 0.0)
                g_tx = tl.where(on, g_tx, 0.0)
                g_ty = tl.where(on, g_ty, 0.0)
                g_qxx = tl.where(on, g_qxx, 0.0)
                g_qxy = tl.where(on, g_qxy, 0.0)
                g_qyy = tl.where(on, g_qyy, 0.0)
                g_qxz = tl.where(on, g_qxz, 0.0)
                g_qyz = tl.where(on, g_qyz, 0.0)
                g_qzz = tl.where(on, g_qzz, 0.0)
                g_zs = fz - (g_tx * tx + g_ty * ty) * izs
                gx = g_tx * izs
                gy = g_ty * izs
                gex0 += 2 * g_qxx * sx0 + g_qxy * sy0 + g_qxz * sz0
                gex1 += 2 * g_qxx * sx1 + g_qxy * sy1 + g_qxz * sz1
                gex2 += 2 * g_qxx * sx2 + g_qxy * sy2 + g_qxz * sz2
                gey0 += g_qxy * sx0 + 2 * g_qyy * sy0 + g_qyz * sz0
                gey1 += g_qxy * sx1 + 2 * g_qyy * sy1 + g_qyz * sz1
                gey2 += g_qxy * sx2 + 2 * g_qyy * sy2 + g_qyz * sz2
                gez0 += g_qxz * sx0 + g_qyz * sy0 + 2 * g_qzz * sz0
                gez1 += g_qxz * sx1 + g_qyz * sy1 + 2 * g_qzz * sz1
                gez2 += g_qxz * sx2 + g_qyz * sy2 + 2 * g_qzz * sz2
                # the in-frustum test
                gi = g_in * inside
                dlu = ((1.0 - s1) - (1.0 - s2)) / edge
                dlv = ((1.0 - s3) - (1.0 - s4)) / edge
                gx += gi * dlu * fx * izs
                gy += gi * dlv * fy * izs
                gz = gi * (1.0 - s0) / (0.25 * near)
                g_zs += gi * (dlu * (-fx * x * iz2) + dlv * (-fy * y * iz2))
                # the transmittance
                if HAS_GRID:
                    gtau = -g_vis * vis
                    gu = gtau * tu * g / wd
                    gv = gtau * tv * g / ht
                    izt = 1.0 / zt
                    gx += gu * fx * izt
                    gy += gv * fy * izt
                    gz += tl.where(z >= 1e-6, -(gu * fx * x + gv * fy * y) * izt * izt, 0.0)
                    gz += gtau * td / dz
                gz += g_zs * dzs
                gx = tl.where(gterm != 0.0, gx, 0.0)
                gy = tl.where(gterm != 0.0, gy, 0.0)
                gz = tl.where(gterm != 0.0, gz, 0.0)
                # camera coordinates -> the camera axes and the centre
                q0 = m0 - t0
                q1 = m1 - t1
                q2 = m2 - t2
                gex0 += gx * q0
                gex1 += gx * q1
                gex2 += gx * q2
                gey0 += gy * q0
                gey1 += gy * q1
                gey2 += gy * q2
                gez0 += gz * q0
                gez1 += gz * q1
                gez2 += gz * q2
                gt0 -= gx * ex0 + gy * ey0 + gz * ez0
                gt1 -= gx * ex1 + gy * ey1 + gz * ez1
                gt2 -= gx * ex2 + gy * ey2 + gz * ez2
    if not PER_SAMPLE:
        o = part_ptr + (b.to(tl.int64) * tl.num_programs(1) + p) * 13
        tl.store(o, tl.sum(tot, axis=0))
        if WANT_GRAD:
            tl.store(o + 1, tl.sum(gex0, axis=0))
            tl.store(o + 4, tl.sum(gex1, axis=0))
            tl.store(o + 7, tl.sum(gex2, axis=0))
            tl.store(o + 2, tl.sum(gey0, axis=0))
            tl.store(o + 5, tl.sum(gey1, axis=0))
            tl.store(o + 8, tl.sum(gey2, axis=0))
            tl.store(o + 3, tl.sum(gez0, axis=0))
            tl.store(o + 6, tl.sum(gez1, axis=0))
            tl.store(o + 9, tl.sum(gez2, axis=0))
            tl.store(o + 10, tl.sum(gt0, axis=0))
            tl.store(o + 11, tl.sum(gt1, axis=0))
            tl.store(o + 12, tl.sum(gt2, axis=0))
