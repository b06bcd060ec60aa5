"""What the kernels share: the decorator, the rules' constants and the layouts of the arrays
they exchange.

numba compiles a kernel with the values of these constants frozen in, and its on-disk cache
checks only the file a kernel is defined in: after changing a value here, delete the cached
compilations (``__pycache__/*.nbi``, ``*.nbc`` beside the kernels, or ``NUMBA_CACHE_DIR``).
"""

from __future__ import annotations

from numba import njit

jit = njit(cache=True, nogil=True, error_model="numpy")
"""Every kernel: compiled on first use for the argument types, cached on disk, the GIL
released, and no Python-style division checks."""

inline = njit(cache=True, nogil=True, error_model="numpy", inline="always")
"""A kernel's small helper (a step the kernels share): as :data:`jit`, and inlined into each
kernel that calls it, so that it costs no call in an inner loop."""

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

REC = 8
"""Leading columns of a list entry's record: mean x, mean y, conic a, b, c, opacity, depth,
and σ_cut (slightly above ln(o·255): where σ exceeds it, α < 1/255 without evaluating the
exponential); the colour (or feature) channels follow."""

MOMENTS = 34
"""Per-Gaussian Fisher moments: Σ f4·dx^a dy^b for the 15 monomials of degree ≤ 4 (by degree,
then by the power of dy; these hold every entry of Φ = Σ f4 φφᵀ), the 18 entries of
C2 = Σ f2 ⊗ φ (channel-major), and Σ w²."""
