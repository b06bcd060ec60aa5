"""The anchor coverage matrix's per-(candidate, sample) terms
(:func:`agilegs.service.nbv.coverage.coverage_matrix`): the frustum test chi and the
inverse-range term kappa = chi · max(cos, 0) / (dist + eps), with the reference's rules
(camera coordinates ``(x - p) R``, depth clamped at 1e-9 for the projection, the
half-open image bounds, the distance clamped at 1e-12 for the cosine). Float64 arithmetic.

Layouts: ``cams`` [D, 12] (c2w rotation row-major, then the centre); ``intr`` [6] (fx, fy,
cx, cy, width, height); ``samples`` [K, 3].
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
