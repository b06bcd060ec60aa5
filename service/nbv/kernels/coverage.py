"""The anchor coverage matrix's per-(candidate, sample) terms
(:func:`agilegs.service.nbv.coverage.coverage_matrix`): the frustum test chi and the
inverse-range term kappa = chi · max(cos, 0) / (dist + eps), with the reference's rules
(camera coordinates ``(x - p) R``, depth clamped at 1e-9 for the projection, the
half-open image bounds, the distance clamped at 1e-12 for the cosine). Float64 arithmetic.
:func:`coverage_terms` serves one anchor's samples; :func:`coverage_blocks` every anchor's at
once (:func:`agilegs.service.nbv.coverage.coverage_blocks`), the same numbers.

Layouts: ``cams`` [D, 12] (c2w rotation row-major, then the centre); ``intr`` [6] (fx, fy,
cx, cy, width, height); ``samples`` [K, 3]; ``pts`` [3, K] the same by coordinate; ``seg``
[A + 1] the first sample of each anchor's block (then K).
"""

from __future__ import annotations

import math

import numpy as np

from .common import jit as _jit


@_jit
def coverage_terms(cams: np.ndarray, intr: np.ndarray, samples: np.ndarray, near: float,
                   eps: float, d0: int, d1: int, kappa: np.ndarray, chi: np.ndarray,
                   cover: np.ndarray) -> None:
    """kappa [D, K], chi [D, K] (uint8) and the fraction of samples inside each frustum
    ``cover`` [D], for candidates d0..d1-1."""
    fx, fy, cx, cy, wd, ht = intr[0], intr[1], intr[2], intr[3], intr[4], intr[5]
    nk = samples.shape[0]
    for d in range(d0, d1):
        c = cams[d]
        px, py, pz = c[9], c[10], c[11]
        inside = 0
        for k in range(nk):
            r0 = samples[k, 0] - px
            r1 = samples[k, 1] - py
            r2 = samples[k, 2] - pz
            x = r0 * c[0] + r1 * c[3] + r2 * c[6]
            y = r0 * c[1] + r1 * c[4] + r2 * c[7]
            z = r0 * c[2] + r1 * c[5] + r2 * c[8]
            dist = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
            zs = z if z > 1e-9 else 1e-9
            u = fx * x / zs + cx
            v = fy * y / zs + cy
            ok = z > near and u >= 0.0 and u < wd and v >= 0.0 and v < ht
            if ok:
                cos = z / (dist if dist > 1e-12 else 1e-12)
                cos = cos if cos > 0.0 else 0.0
                kappa[d, k] = cos / (dist + eps)
                chi[d, k] = 1
                inside += 1
            else:
                kappa[d, k] = 0.0
                chi[d, k] = 0
        cover[d] = inside / nk if nk > 0 else math.nan



@_jit
def _block_row(sx: np.ndarray, sy: np.ndarray, sz: np.ndarray, k0: int, k1: int,
               c: np.ndarray, intr: np.ndarray, near: float, eps: float,
               kappa: np.ndarray) -> int:
    """kappa of one candidate ``c`` [12] at samples k0..k1-1 into ``kappa`` [K] (row of
    one candidate), :func:`coverage_terms`'s arithmetic without branches (so that the loop
    runs on vector lanes); returns how many samples are inside the frustum."""
    fx, fy, cx, cy, wd, ht = intr[0], intr[1], intr[2], intr[3], intr[4], intr[5]
    px, py, pz = c[9], c[10], c[11]
    c0, c1, c2, c3, c4, c5, c6, c7, c8 = c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7], c[8]
    inside = 0
    for k in range(k0, k1):
        r0 = sx[k] - px
        r1 = sy[k] - py
        r2 = sz[k] - pz
        x = r0 * c0 + r1 * c3 + r2 * c6
        y = r0 * c1 + r1 * c4 + r2 * c7
        z = r0 * c2 + r1 * c5 + r2 * c8
        dist = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        zs = z if z > 1e-9 else 1e-9
        u = fx * x / zs + cx
        v = fy * y / zs + cy
        ok = (z > near) & (u >= 0.0) & (u < wd) & (v >= 0.0) & (v < ht)
        cos = z / (dist if dist > 1e-12 else 1e-12)
        cos = cos if cos > 0.0 else 0.0
        val = cos / (dist + eps)
        kappa[k] = val if ok else 0.0
        inside += 1 if ok else 0
    return inside


@_jit
def coverage_blocks(cams: np.ndarray, intr: np.ndarray, pts: np.ndarray, seg: np.ndarray,
                    live: np.ndarray, near: float, eps: float, d0: int, d1: int,
                    kappa: np.ndarray, cover: np.ndarray) -> None:
    """kappa [D, K] (float32 or float64: the value rounded once) of every anchor's block of
    samples ``pts`` [3, K] (by coordinate) and the fraction of each block inside each
    frustum ``cover`` [A, D], for candidates d0..d1-1, with :func:`coverage_terms`'s
    arithmetic. A (candidate, anchor) whose ``live`` [A, D] is 0 (a row weight of zero) is
    not computed: its kappa block is 0 and its cover 0 (NaN for an empty block)."""
    na = seg.shape[0] - 1
    sx, sy, sz = pts[0], pts[1], pts[2]
    for d in range(d0, d1):
        row = kappa[d]
        for a in range(na):
            k0, k1 = seg[a], seg[a + 1]
            if live[a, d] == 0:
                row[k0:k1] = 0.0
                cover[a, d] = 0.0 if k1 > k0 else math.nan
                continue
            inside = _block_row(sx, sy, sz, k0, k1, cams[d], intr, near, eps, row)
            cover[a, d] = inside / (k1 - k0) if k1 > k0 else math.nan
