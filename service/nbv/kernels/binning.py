"""Binning the visible Gaussians to tiles, front to back, as records (:func:`bin_count`,
:func:`visible_order`, :func:`bin_fill`), and the per-Gaussian sums of what the walks wrote
per list entry (:func:`reduce_entries`)."""

from __future__ import annotations

import math

import numpy as np

from .common import ALPHA_MIN_F64, REC
from .common import jit as _jit


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
def reduce_entries(target: np.ndarray, ent_off: np.ndarray, ent: np.ndarray,
                   per_entry: np.ndarray, part: int, nchunks: int, out: np.ndarray) -> None:
    """out[target[v]] = the sum of compact Gaussian v's entries' rows of per_entry [M, K]
    (float64 sums), for the compact Gaussians of this part; rows not targeted are left as
    they are."""
    nv = ent_off.shape[0] - 1
    kk = per_entry.shape[1]
    acc = np.empty(kk)
    lo = part * nv // nchunks
    hi = (part + 1) * nv // nchunks
    for v in range(lo, hi):
        for q in range(kk):
            acc[q] = 0.0
        for jj in range(ent_off[v], ent_off[v + 1]):
            e = ent[jj]
            for q in range(kk):
                acc[q] += per_entry[e, q]
        g = target[v]
        for q in range(kk):
            out[g, q] = acc[q]
