"""The Triton kernel of :mod:`agilegs.service.nbv.kernels.gpu` (imported only where Triton
imports): one program per image tile, one lane per pixel."""

# mypy: ignore-errors
# ruff: noqa: N803

import triton
import triton.language as tl


@triton.jit
def _pair(attr_ptr, box_ptr, v, pxf, pyf, pxi, pyi, amin):
    """Visible Gaussian v at the lanes' pixels: dx, dy (pixel centre less its mean), its
    unclamped α = o·exp(-σ), and whether the pair composites if reached (the pixel in v's box,
    σ >= 0 and α >= amin)."""
    a = attr_ptr + v * 9
    dx = pxf - tl.load(a)
    dy = pyf - tl.load(a + 1)
    sigma = 0.5 * (tl.load(a + 2) * dx * dx + tl.load(a + 4) * dy * dy) \
        + tl.load(a + 3) * dx * dy
    raw = tl.load(a + 5) * tl.exp(-sigma)
    b = box_ptr + v * 4
    inbox = (pxi >= tl.load(b)) & (pxi <= tl.load(b + 1)) & (pyi >= tl.load(b + 2)) \
        & (pyi <= tl.load(b + 3))
    return dx, dy, raw, inbox & (sigma >= 0) & (raw >= amin)


@triton.jit
def _add_phi(o, f, dx, dy, xx, xy, yy):
    """Add Σ f·φ over the lanes to o[0:6], φ = (1, dx, dy, dx², dx dy, dy²)."""
    tl.atomic_add(o, tl.sum(f, axis=0), sem="relaxed")
    tl.atomic_add(o + 1, tl.sum(f * dx, axis=0), sem="relaxed")
    tl.atomic_add(o + 2, tl.sum(f * dy, axis=0), sem="relaxed")
    tl.atomic_add(o + 3, tl.sum(f * xx, axis=0), sem="relaxed")
    tl.atomic_add(o + 4, tl.sum(f * xy, axis=0), sem="relaxed")
    tl.atomic_add(o + 5, tl.sum(f * yy, axis=0), sem="relaxed")


@triton.jit
def moments_kernel(attr_ptr, box_ptr, ent_ptr, off_ptr, const_ptr, out_ptr,  # type: ignore[no-untyped-def]
                   width, height, tiles_x, TILE: tl.constexpr, BLOCK: tl.constexpr,
                   PIXELS: tl.constexpr):
    """One tile: lanes are its pixels (see :mod:`agilegs.service.nbv.kernels.gpu`); the pair
    terms are those of ``kernels.walks.fisher_tiles`` (f4, f2 per channel, w², and the
    monomials of dx, dy)."""
    t = tl.program_id(0)
    start = tl.load(off_ptr + t)
    length = tl.load(off_ptr + t + 1) - start
    lane = tl.arange(0, BLOCK)
    x0 = (t % tiles_x) * TILE
    y0 = (t // tiles_x) * TILE
    pxi = x0 + lane % TILE
    pyi = y0 + lane // TILE
    valid = (lane < TILE * TILE) & (pxi < width) & (pyi < height)
    ty = attr_ptr.dtype.element_ty
    amin = tl.load(const_ptr).to(ty)
    amax = tl.load(const_ptr + 1).to(ty)
    t_min = tl.load(const_ptr + 2)
    bg0 = tl.load(const_ptr + 3)
    bg1 = tl.load(const_ptr + 4)
    bg2 = tl.load(const_ptr + 5)
    pxf = pxi.to(ty) + 0.5
    pyf = pyi.to(ty) + 0.5
    trans = tl.full((BLOCK,), 1.0, tl.float64)
    last = tl.full((BLOCK,), 0, tl.int64) + length
    live = valid
    # front to back: the transmittance and each pixel's stop
    k = 0
    while (k < length) & (tl.sum(live.to(tl.int32), axis=0) > 0):
        v = tl.load(ent_ptr + start + k)
        dx, dy, raw, ok = _pair(attr_ptr, box_ptr, v, pxf, pyf, pxi, pyi, amin)
        hit = live & ok
        al = tl.minimum(raw, amax).to(tl.float64)
        tn = trans * (1.0 - al)
        stop = hit & (tn < t_min)
        last = tl.where(stop, k, last)
        live = live & (stop == 0)
        trans = tl.where(hit & (stop == 0), tn, trans)
        k += 1
    t_final = trans
    s0 = tl.zeros((BLOCK,), tl.float64)
    s1 = tl.zeros((BLOCK,), tl.float64)
    s2 = tl.zeros((BLOCK,), tl.float64)
    kmax = tl.max(tl.where(valid, last, 0), axis=0)
    # back to front: unwind the transmittance, sum every pair's terms per Gaussian
    for i in range(0, kmax):
        kb = kmax - 1 - i
        v = tl.load(ent_ptr + start + kb)
        dx, dy, raw, ok = _pair(attr_ptr, box_ptr, v, pxf, pyf, pxi, pyi, amin)
        hit = valid & (kb < last) & ok
        if tl.sum(hit.to(tl.int32), axis=0) > 0:
            a = attr_ptr + v * 9
            c0 = tl.load(a + 6)
            c1 = tl.load(a + 7)
            c2 = tl.load(a + 8)
            al64 = tl.minimum(raw, amax).to(tl.float64)
            inv64 = 1.0 / (1.0 - al64)
            tb = tl.where(hit, trans * inv64, trans)
            trans = tb
            w64 = tb * al64
            d0 = (tb * c0 - (s0 + t_final * bg0) * inv64).to(ty)
            d1 = (tb * c1 - (s1 + t_final * bg1) * inv64).to(ty)
            d2 = (tb * c2 - (s2 + t_final * bg2) * inv64).to(ty)
            s0 = tl.where(hit, s0 + w64 * c0, s0)
            s1 = tl.where(hit, s1 + w64 * c1, s1)
            s2 = tl.where(hit, s2 + w64 * c2, s2)
            w = w64.to(ty)
            if PIXELS:
                aq = raw
                dsum = d0 + d1 + d2
                f4 = dsum * dsum * aq * aq
                f20 = dsum * w * aq
                f21 = f20
                f22 = f20
            else:
                aq = tl.where(raw <= amax, al64.to(ty), 0.0)
                f4 = (d0 * d0 + d1 * d1 + d2 * d2) * aq * aq
                wa = w * aq
                f20 = d0 * wa
                f21 = d1 * wa
                f22 = d2 * wa
            f4 = tl.where(hit, f4, 0.0)
            f20 = tl.where(hit, f20, 0.0)
            f21 = tl.where(hit, f21, 0.0)
            f22 = tl.where(hit, f22, 0.0)
            ww = tl.where(hit, w * w, 0.0)
            xx = dx * dx
            xy = dx * dy
            yy = dy * dy
            o = out_ptr + v * 34
            _add_phi(o, f4, dx, dy, xx, xy, yy)  # the monomials of degree <= 2
            fxx = f4 * xx
            fxy = f4 * xy
            fyy = f4 * yy
            tl.atomic_add(o + 6, tl.sum(fxx * dx, axis=0), sem="relaxed")
            tl.atomic_add(o + 7, tl.sum(fxx * dy, axis=0), sem="relaxed")
            tl.atomic_add(o + 8, tl.sum(fxy * dy, axis=0), sem="relaxed")
            tl.atomic_add(o + 9, tl.sum(fyy * dy, axis=0), sem="relaxed")
            tl.atomic_add(o + 10, tl.sum(fxx * xx, axis=0), sem="relaxed")
            tl.atomic_add(o + 11, tl.sum(fxx * xy, axis=0), sem="relaxed")
            tl.atomic_add(o + 12, tl.sum(fxx * yy, axis=0), sem="relaxed")
            tl.atomic_add(o + 13, tl.sum(fxy * yy, axis=0), sem="relaxed")
            tl.atomic_add(o + 14, tl.sum(fyy * yy, axis=0), sem="relaxed")
            _add_phi(o + 15, f20, dx, dy, xx, xy, yy)
            _add_phi(o + 21, f21, dx, dy, xx, xy, yy)
            _add_phi(o + 27, f22, dx, dy, xx, xy, yy)
            tl.atomic_add(o + 33, tl.sum(ww, axis=0), sem="relaxed")
