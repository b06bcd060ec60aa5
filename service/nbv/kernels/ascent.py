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


@_jit
def _skew_into(a0: float, a1: float, a2: float, k: np.ndarray) -> None:
    """The cross-product matrix of (a0, a1, a2) into ``k`` [3, 3]."""
    k[0, 0], k[0, 1], k[0, 2] = 0.0, -a2, a1
    k[1, 0], k[1, 1], k[1, 2] = a2, 0.0, -a0
    k[2, 0], k[2, 1], k[2, 2] = -a1, a0, 0.0


@_jit
def _unit_jvp(x: np.ndarray, dx: np.ndarray, floor: float, out: np.ndarray,
              dout: np.ndarray) -> float:
    """``x / max(|x|, floor)`` of a 3-vector ``x`` [3] into ``out`` [3] and its tangents
    ``dx`` [6, 3] into ``dout`` [6, 3] (the clamp passing its gradient where ``|x|`` >=
    ``floor``, the norm's gradient 0 at 0, as torch's); returns ``|x|``."""
    n = _norm3(x[0], x[1], x[2])
    nc = n if n > floor else floor
    passes = n >= floor
    for i in range(3):
        out[i] = x[i] / nc
    for j in range(6):
        dn = 0.0
        if n > 0.0:
            dn = (x[0] * dx[j, 0] + x[1] * dx[j, 1] + x[2] * dx[j, 2]) / n
        dnc = dn if passes else 0.0
        for i in range(3):
            dout[j, i] = dx[j, i] / nc - x[i] * dnc / (nc * nc)
    return n


@_jit
def projected_tangents(pose: np.ndarray, env: np.ndarray, cams: np.ndarray,
                       dcams: np.ndarray) -> None:
    """The camera row [1, 12] of ``project(pose exp(xi^))`` at xi = 0 (the pose [4, 4] moved
    into the envelope ``env`` [15], :func:`envelope_project_into`) into ``cams``, and its
    derivatives in the six twist coordinates (rho, omega) into ``dcams`` [6, 12]: forward
    differentiation through the projection's steps, each with the derivative torch's
    autograd takes (a clamp passes it where its argument lies within the bounds, bounds
    included; a ``where`` only through the branch taken)."""
    rot = np.empty((3, 3))
    drot = np.zeros((6, 3, 3))
    dp = np.zeros((6, 3))
    for i in range(3):
        for j in range(3):
            rot[i, j] = pose[i, j]
    for j in range(3):  # d(pose (I + hat(xi)))/d xi: R e_j in the centre, R hat(e_k) turning
        for i in range(3):
            dp[j, i] = pose[i, j]
    k = np.empty((3, 3))
    for a in range(3):
        _skew_into(1.0 if a == 0 else 0.0, 1.0 if a == 1 else 0.0, 1.0 if a == 2 else 0.0, k)
        for i in range(3):
            for j in range(3):
                drot[3 + a, i, j] = rot[i, 0] * k[0, j] + rot[i, 1] * k[1, j] + rot[i, 2] * k[2, j]
    if env[14] < 0.5:
        for i in range(3):
            for j in range(3):
                cams[0, 3 * i + j] = rot[i, j]
                for t in range(6):
                    dcams[t, 3 * i + j] = drot[t, i, j]
            cams[0, 9 + i] = pose[i, 3]
            for t in range(6):
                dcams[t, 9 + i] = dp[t, i]
        return
    up = env[3:6]
    r_min, r_max, elev_min, elev_max, max_off = env[9], env[10], env[11], env[12], env[13]
    rel = np.empty(3)
    for i in range(3):
        rel[i] = pose[i, 3] - env[i]
    r0 = _norm3(rel[0], rel[1], rel[2])
    r = r0 if r0 > 1e-9 else 1e-9
    dr = np.zeros(6)
    dru = np.zeros(6)
    for t in range(6):
        if r0 >= 1e-9 and r0 > 0.0:
            dr[t] = (rel[0] * dp[t, 0] + rel[1] * dp[t, 1] + rel[2] * dp[t, 2]) / r0
        dru[t] = dp[t, 0] * up[0] + dp[t, 1] * up[1] + dp[t, 2] * up[2]
    ru = rel[0] * up[0] + rel[1] * up[1] + rel[2] * up[2]
    h = np.empty(3)
    dh = np.empty((6, 3))
    for i in range(3):
        h[i] = rel[i] - ru * up[i]
        for t in range(6):
            dh[t, i] = dp[t, i] - dru[t] * up[i]
    hd = np.empty(3)
    dhd = np.empty((6, 3))
    if _norm3(h[0], h[1], h[2]) > 1e-9:
        _unit_jvp(h, dh, 1e-12, hd, dhd)
    else:  # looking straight down or up: up x the camera's x axis
        hd[0] = up[1] * rot[2, 0] - up[2] * rot[1, 0]
        hd[1] = up[2] * rot[0, 0] - up[0] * rot[2, 0]
        hd[2] = up[0] * rot[1, 0] - up[1] * rot[0, 0]
        for t in range(6):
            dhd[t, 0] = up[1] * drot[t, 2, 0] - up[2] * drot[t, 1, 0]
            dhd[t, 1] = up[2] * drot[t, 0, 0] - up[0] * drot[t, 2, 0]
            dhd[t, 2] = up[0] * drot[t, 1, 0] - up[1] * drot[t, 0, 0]
    hdir = np.empty(3)
    dhdir = np.empty((6, 3))
    _unit_jvp(hd, dhd, 1e-12, hdir, dhdir)
    s_raw = ru / r
    s = min(max(s_raw, -1.0), 1.0)
    s_in = s_raw >= -1.0 and s_raw <= 1.0
    elev = math.asin(s)
    elev_c = min(max(elev, elev_min), elev_max)
    e_in = elev >= elev_min and elev <= elev_max
    r_c = min(max(r, r_min), r_max)
    r_in = r >= r_min and r <= r_max
    ce, se = math.cos(elev_c), math.sin(elev_c)
    newp = np.empty(3)
    dnewp = np.empty((6, 3))
    for i in range(3):
        newp[i] = env[i] + r_c * (ce * hdir[i] + se * up[i])
    for t in range(6):
        ds = (dru[t] / r - ru * dr[t] / (r * r)) if s_in else 0.0
        de = ds / math.sqrt(1.0 - s * s) if e_in else 0.0
        drc = dr[t] if r_in else 0.0
        for i in range(3):
            dnewp[t, i] = (drc * (ce * hdir[i] + se * up[i])
                           + r_c * (-se * de * hdir[i] + ce * dhdir[t, i] + ce * de * up[i]))
    # turned back towards the aim by the angle beyond the pool's largest off-aim angle
    ta = np.empty(3)
    dta = np.empty((6, 3))
    for i in range(3):
        ta[i] = env[6 + i] - newp[i]
        for t in range(6):
            dta[t, i] = -dnewp[t, i]
    aim = np.empty(3)
    daim = np.empty((6, 3))
    _unit_jvp(ta, dta, 1e-12, aim, daim)
    f0, f1, f2 = rot[0, 2], rot[1, 2], rot[2, 2]
    c_raw = f0 * aim[0] + f1 * aim[1] + f2 * aim[2]
    cosang = min(max(c_raw, -1.0), 1.0)
    c_in = c_raw >= -1.0 and c_raw <= 1.0
    excess_raw = math.acos(cosang) - max_off
    excess = excess_raw if excess_raw > 0.0 else 0.0
    ax = np.empty(3)
    dax = np.empty((6, 3))
    ax[0] = f1 * aim[2] - f2 * aim[1]
    ax[1] = f2 * aim[0] - f0 * aim[2]
    ax[2] = f0 * aim[1] - f1 * aim[0]
    for t in range(6):
        g0, g1, g2 = drot[t, 0, 2], drot[t, 1, 2], drot[t, 2, 2]
        a0, a1, a2 = daim[t, 0], daim[t, 1], daim[t, 2]
        dax[t, 0] = g1 * aim[2] - g2 * aim[1] + f1 * a2 - f2 * a1
        dax[t, 1] = g2 * aim[0] - g0 * aim[2] + f2 * a0 - f0 * a2
        dax[t, 2] = g0 * aim[1] - g1 * aim[0] + f0 * a1 - f1 * a0
    axis = np.zeros(3)
    daxis = np.zeros((6, 3))
    an = _norm3(ax[0], ax[1], ax[2])
    if an > 1e-9:
        _unit_jvp(ax, dax, 1e-12, axis, daxis)
    need = excess > 0.0 and an > 1e-9
    angle = excess if need else 0.0
    sa, ca = math.sin(angle), math.cos(angle)
    _skew_into(axis[0], axis[1], axis[2], k)
    kk = _square(k)
    fix = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            fix[i, j] = (1.0 if i == j else 0.0) + sa * k[i, j] + (1.0 - ca) * kk[i, j]
    dk = np.empty((3, 3))
    dfix = np.empty((3, 3))
    for t in range(6):
        dang = 0.0
        if need and excess_raw >= 0.0 and c_in:
            dc = (drot[t, 0, 2] * aim[0] + drot[t, 1, 2] * aim[1] + drot[t, 2, 2] * aim[2]
                  + f0 * daim[t, 0] + f1 * daim[t, 1] + f2 * daim[t, 2])
            dang = -dc / math.sqrt(1.0 - cosang * cosang)
        _skew_into(daxis[t, 0], daxis[t, 1], daxis[t, 2], dk)
        for i in range(3):
            for j in range(3):
                dkk = 0.0
                for m in range(3):
                    dkk += dk[i, m] * k[m, j] + k[i, m] * dk[m, j]
                dfix[i, j] = (ca * dang * k[i, j] + sa * dk[i, j] + sa * dang * kk[i, j]
                              + (1.0 - ca) * dkk)
        for i in range(3):
            for j in range(3):
                dcams[t, 3 * i + j] = (dfix[i, 0] * rot[0, j] + dfix[i, 1] * rot[1, j]
                                       + dfix[i, 2] * rot[2, j] + fix[i, 0] * drot[t, 0, j]
                                       + fix[i, 1] * drot[t, 1, j] + fix[i, 2] * drot[t, 2, j])
            dcams[t, 9 + i] = dnewp[t, i]
    for i in range(3):
        for j in range(3):
            cams[0, 3 * i + j] = (fix[i, 0] * rot[0, j] + fix[i, 1] * rot[1, j]
                                  + fix[i, 2] * rot[2, j])
        cams[0, 9 + i] = newp[i]
