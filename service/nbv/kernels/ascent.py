"""The trial poses of the anchor's line search
(:func:`agilegs.service.nbv.anchor.ascent.ascend`), compiled: the twist step, the retraction
``T exp(xi^)`` and the projection into the pool envelope
(:meth:`agilegs.service.nbv.anchor.envelope.PoolEnvelope.project`), as the camera row the
proxy's kernel (:func:`agilegs.service.nbv.kernels.proxy.proxy_psi`) takes; the driver
(:class:`agilegs.service.nbv.anchor.line_search.CompiledLineSearch`) calls the two in turn.
No kernel here calls one of another file: numba's on-disk cache of a kernel checks only the
file it is defined in.

The rules are the torch path's, step for step (:func:`~agilegs.service.nbv.se3.se3_exp` with
its Taylor branch below t² = 1e-2, the envelope's clamps and fallbacks, Rodrigues' turn back
towards the aim). Arithmetic is float64; with ``single`` the values the torch path holds in
float32 (the step length's factor, the twist, the trial pose) are rounded to float32 where it
stores them.

Layouts: ``pose`` [4, 4] (c2w); ``gstep`` [6] the metric step direction (the twist gradient
with its translation scaled by r², :func:`~agilegs.service.nbv.anchor.ascent._metric_step`)
and ``gnorm`` its length in the metric; ``env`` [15] (centre, up, aim, r_min, r_max,
elev_min, elev_max, max_off_aim, 1 when there is an envelope else 0).
"""

from __future__ import annotations

import math

import numpy as np

from .common import jit as _jit

_TAYLOR_T2 = 1e-2
_A = (1.0, -1.0 / 6, 1.0 / 120, -1.0 / 5040, 1.0 / 362880)
_B = (0.5, -1.0 / 24, 1.0 / 720, -1.0 / 40320, 1.0 / 3628800)
_C = (1.0 / 6, -1.0 / 120, 1.0 / 5040, -1.0 / 362880, 1.0 / 39916800)


@_jit
def _r32(x: float, single: bool) -> float:
    """``x`` rounded to float32 when ``single``."""
    if single:
        return float(np.float32(x))
    return x


@_jit
def _poly5(x: float, c0: float, c1: float, c2: float, c3: float, c4: float) -> float:
    return (((c4 * x + c3) * x + c2) * x + c1) * x + c0


@_jit
def se3_exp_into(xi: np.ndarray, out: np.ndarray) -> None:
    """``se3_exp`` of one twist [6] (rho, omega) into ``out`` [4, 4]."""
    w0, w1, w2 = xi[3], xi[4], xi[5]
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    if t2 < _TAYLOR_T2:
        a = _poly5(t2, _A[0], _A[1], _A[2], _A[3], _A[4])
        b = _poly5(t2, _B[0], _B[1], _B[2], _B[3], _B[4])
        c = _poly5(t2, _C[0], _C[1], _C[2], _C[3], _C[4])
    else:
        t = math.sqrt(t2)
        sin_t = math.sin(t)
        half = 0.5 * t
        sinc_half = math.sin(half) / half
        a = sin_t / t
        b = 0.5 * sinc_half * sinc_half
        c = (t - sin_t) / (t2 * t)
    k = np.zeros((3, 3))
    k[0, 1], k[0, 2] = -w2, w1
    k[1, 0], k[1, 2] = w2, -w0
    k[2, 0], k[2, 1] = -w1, w0
    kk = _square(k)
    for i in range(3):
        ti = 0.0
        for j in range(3):
            e = 1.0 if i == j else 0.0
            out[i, j] = e + a * k[i, j] + b * kk[i, j]
            ti += (e + b * k[i, j] + c * kk[i, j]) * xi[j]
        out[i, 3] = ti
        out[3, i] = 0.0
    out[3, 3] = 1.0


@_jit
def _square(k: np.ndarray) -> np.ndarray:
    """``k @ k`` of a 3 x 3 matrix."""
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            out[i, j] = k[i, 0] * k[0, j] + k[i, 1] * k[1, j] + k[i, 2] * k[2, j]
    return out


@_jit
def _norm3(x0: float, x1: float, x2: float) -> float:
    return math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)


@_jit
def envelope_project_into(c2w: np.ndarray, env: np.ndarray, out: np.ndarray) -> None:
    """One pose [4, 4] moved into the envelope ``env`` [15]
    (:meth:`~agilegs.service.nbv.anchor.envelope.PoolEnvelope.project`) into ``out``
    [4, 4]; a copy without an envelope."""
    out[:, :] = c2w
    if env[14] < 0.5:
        return
    c0, c1, c2 = env[0], env[1], env[2]
    u0, u1, u2 = env[3], env[4], env[5]
    a0, a1, a2 = env[6], env[7], env[8]
    r_min, r_max, elev_min, elev_max, max_off = env[9], env[10], env[11], env[12], env[13]
    rel0, rel1, rel2 = c2w[0, 3] - c0, c2w[1, 3] - c1, c2w[2, 3] - c2
    r = _norm3(rel0, rel1, rel2)
    r = r if r > 1e-9 else 1e-9
    ru = rel0 * u0 + rel1 * u1 + rel2 * u2
    h0, h1, h2 = rel0 - ru * u0, rel1 - ru * u1, rel2 - ru * u2
    hn = _norm3(h0, h1, h2)
    if hn > 1e-9:
        hc = hn if hn > 1e-12 else 1e-12
        d0, d1, d2 = h0 / hc, h1 / hc, h2 / hc
    else:  # looking straight down or up: up x the camera's x axis
        x0, x1, x2 = c2w[0, 0], c2w[1, 0], c2w[2, 0]
        d0, d1, d2 = u1 * x2 - u2 * x1, u2 * x0 - u0 * x2, u0 * x1 - u1 * x0
    dn = _norm3(d0, d1, d2)
    dn = dn if dn > 1e-12 else 1e-12
    d0, d1, d2 = d0 / dn, d1 / dn, d2 / dn
    s = min(max(ru / r, -1.0), 1.0)
    elev_c = min(max(math.asin(s), elev_min), elev_max)
    r_c = min(max(r, r_min), r_max)
    ce, se = math.cos(elev_c), math.sin(elev_c)
    p0 = c0 + r_c * (ce * d0 + se * u0)
    p1 = c1 + r_c * (ce * d1 + se * u1)
    p2 = c2 + r_c * (ce * d2 + se * u2)
    # turned back towards the aim by the angle beyond the pool's largest off-aim angle
    f0, f1, f2 = c2w[0, 2], c2w[1, 2], c2w[2, 2]
    t0, t1, t2 = a0 - p0, a1 - p1, a2 - p2
    tn = _norm3(t0, t1, t2)
    tn = tn if tn > 1e-12 else 1e-12
    t0, t1, t2 = t0 / tn, t1 / tn, t2 / tn
    cosang = min(max(f0 * t0 + f1 * t1 + f2 * t2, -1.0), 1.0)
    excess = math.acos(cosang) - max_off
    excess = excess if excess > 0.0 else 0.0
    x0, x1, x2 = f1 * t2 - f2 * t1, f2 * t0 - f0 * t2, f0 * t1 - f1 * t0
    an = _norm3(x0, x1, x2)
    angle = excess if (excess > 0.0 and an > 1e-9) else 0.0
    if an > 1e-9:
        ac = an if an > 1e-12 else 1e-12
        x0, x1, x2 = x0 / ac, x1 / ac, x2 / ac
    else:
        x0 = x1 = x2 = 0.0
    k = np.zeros((3, 3))
    k[0, 1], k[0, 2] = -x2, x1
    k[1, 0], k[1, 2] = x2, -x0
    k[2, 0], k[2, 1] = -x1, x0
    kk = _square(k)
    sa, ca = math.sin(angle), 1.0 - math.cos(angle)
    fix = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            fix[i, j] = (1.0 if i == j else 0.0) + sa * k[i, j] + ca * kk[i, j]
    for i in range(3):
        for j in range(3):
            out[i, j] = fix[i, 0] * c2w[0, j] + fix[i, 1] * c2w[1, j] + fix[i, 2] * c2w[2, j]
    out[0, 3], out[1, 3], out[2, 3] = p0, p1, p2


@_jit
def trial_pose(pose: np.ndarray, gstep: np.ndarray, gnorm: float, eta: float,
               env: np.ndarray, single: bool, cams: np.ndarray) -> None:
    """The trial pose of a step of length ``eta`` from ``pose`` [4, 4] along ``gstep`` [6]
    (metric length ``gnorm``): ``project(pose exp(xi^))``, xi = gstep * eta / gnorm, as the
    proxy kernel's camera row into ``cams`` [1, 12] (rotation row-major, then the centre)."""
    xi = np.empty(6)
    step = np.empty((4, 4))
    moved = np.empty((4, 4))
    trial = np.empty((4, 4))
    scale = _r32(eta / (gnorm if gnorm > 1e-30 else 1e-30), single)
    for j in range(6):
        xi[j] = _r32(gstep[j] * scale, single)
    se3_exp_into(xi, step)
    for i in range(4):
        for j in range(4):
            moved[i, j] = (pose[i, 0] * step[0, j] + pose[i, 1] * step[1, j]
                           + pose[i, 2] * step[2, j] + pose[i, 3] * step[3, j])
    envelope_project_into(moved, env, trial)
    for i in range(3):
        for j in range(3):
            cams[0, 3 * i + j] = _r32(trial[i, j], single)
        cams[0, 9 + i] = _r32(trial[i, 3], single)
