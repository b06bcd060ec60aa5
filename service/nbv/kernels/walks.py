"""The tile walks: compositing front to back (:func:`composite_forward`), its backward over
the recorded pairs (:func:`composite_backward`), and the Fisher's per-entry moments
(:func:`fisher_tiles`)."""

from __future__ import annotations

import numpy as np

from .common import REC, T_MIN
from .common import inline as _inline
from .common import jit as _jit


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


@_inline
def _tile(t: int, offsets: np.ndarray, tiles_x: int, tile: int, width: int,
          height: int) -> tuple[int, int, int, int, int, int]:
    """Tile t's pixel box [x0, x1) × [y0, y1) (clipped to the image) and its list entries
    [start, start + length) in the records."""
    x0 = (t % tiles_x) * tile
    y0 = (t // tiles_x) * tile
    start = offsets[t]
    return x0, y0, min(x0 + tile, width), min(y0 + tile, height), start, offsets[t + 1] - start


@_inline
def _unwind(tr: np.ndarray, p: int, raw: float, amax: float) -> tuple[float, float, float,
                                                                        float]:
    """One composited pair taken back off tile pixel p, back to front: tr[p] holds the
    transmittance behind the pair and becomes the one in front of it, T. Returns the pair's α
    (clamped at ``amax``), 1 / (1 - α), T and its weight w = T α."""
    al = float(min(raw, amax))
    inv = 1.0 / (1.0 - al)
    tp = tr[p] * inv
    tr[p] = tp
    return al, inv, tp, tp * al


@_inline
def _offset(xs: np.ndarray, ys: np.ndarray, x0: int, y0: int, col_of: np.ndarray,
            row_of: np.ndarray, p: int, mx: float, my: float) -> tuple[float, float]:
    """Tile pixel p's centre less the Gaussian's projected mean (mx, my): (dx, dy)."""
    return float(xs[x0 + col_of[p]] - mx), float(ys[y0 + row_of[p]] - my)


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
        x0, y0, x1, y1, start, length = _tile(t, offsets, tiles_x, tile, width, height)
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
        x0, y0, x1, y1, start, _ = _tile(t, offsets, tiles_x, tile, width, height)
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
                dxf, dyf = _offset(xs, ys, x0, y0, col_of, row_of, p, mx, my)
                al, inv, tp, w = _unwind(tr, p, raw, amax)
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
        x0, y0, x1, y1, start, length = _tile(t, offsets, tiles_x, tile, width, height)
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
            # the 34 sums in scalars, written out: loops over a small array, or a helper per
            # colour row, measured 41-43 against 35 ms at 100k Gaussians, 256²
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
                x, y = _offset(xs, ys, x0, y0, col_of, row_of, p, mx, my)
                al, inv, tp, w = _unwind(tr, p, raw, amax)
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
