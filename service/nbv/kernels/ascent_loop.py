"""The anchor's ascent compiled: a start's step (its gradient, line search and acceptance)
in one call (:class:`agilegs.service.nbv.anchor.compiled_ascent.CompiledAscent`), with the
rules of :class:`agilegs.service.nbv.anchor.ascent.Ascent`.

Per start and step: the camera row of the projected pose and its derivatives in the twist
(:func:`.ascent.projected_tangents`), ψ's gradient there from the proxy's kernel
(:func:`.proxy.proxy_psi`), chained into the twist gradient; the metric step; the trials of
the backtracking line search (:func:`.ascent.trial_pose`, then ψ), the first trial whose ψ
is finite and not below the current one accepted (its step grown 1.5×, at most 4 step
sizes); a start stops without an accepted trial, after a gain of at most ``min_rel_gain``
times its ψ, with a vanishing or non-finite gradient, or after ``iterations`` steps. With
``single`` the numbers the torch path holds in float32 (ψ, the gradient, the step lengths,
the poses) are rounded to float32 where it stores them.

Unlike the kernels of the other files, these are compiled in each process and not cached on
disk: they call kernels of other files (numba's cache of a kernel checks only the file it
is defined in, so a cached caller would keep a changed callee's old code).

Layouts: ``poses`` [S, 4, 4]; ``env`` [15] (:mod:`.ascent`); ``prm`` [5]: the radius of the
twist metric, the step size, ``min_rel_gain``, ``iterations`` (unused here), ``backtracks``;
``traces`` [S, iterations + 1] (ψ at the start and after each accepted step, ``ntrace`` [S]
of them); ``tally`` [4]: the gradient evaluations, the value evaluations and their seconds
(added to).
"""

from __future__ import annotations

import ctypes
import math
import time
from typing import Any

import numpy as np
from numba import njit

from .ascent import _r32, projected_tangents, trial_pose
from .proxy import proxy_psi

_jit = njit(cache=False, nogil=True, error_model="numpy")

_clock_gettime: Any
try:
    _clock_gettime = ctypes.CDLL(None).clock_gettime
    _clock_gettime.argtypes = [ctypes.c_int, ctypes.c_void_p]
    _clock_gettime.restype = ctypes.c_int
    CLOCK = int(time.CLOCK_MONOTONIC)
except (AttributeError, OSError):  # no C library clock: the ascent is not compiled
    _clock_gettime = None
    CLOCK = -1


@_jit
def _now(ts: np.ndarray) -> float:
    """The monotonic clock in seconds (``ts`` [2] int64 scratch)."""
    _clock_gettime(CLOCK, ts.ctypes.data)
    return ts[0] + 1e-9 * ts[1]


@_jit
def ascent_step(poses: np.ndarray, cur: np.ndarray, eta: np.ndarray, active: np.ndarray,
                s: int, env: np.ndarray, prm: np.ndarray, single: bool, intr: np.ndarray,
                means: np.ndarray, sigma6: np.ndarray, weight: np.ndarray, rate: np.ndarray,
                kinds: np.ndarray, axes: np.ndarray, mode: int, occ: np.ndarray,
                mass: np.ndarray, vis_prm: np.ndarray, cells: int, bins: int,
                traces: np.ndarray, ntrace: np.ndarray, tally: np.ndarray) -> None:
    """One step of start ``s`` when it is ``active`` [S] (uint8): its gradient, its line
    search and the acceptance, updating ``poses``, ``cur`` [S], ``eta`` [S] (its step
    length), ``active`` and its trace; the proxy's arrays as :func:`.proxy.proxy_psi` takes
    them."""
    if active[s] == 0:
        return
    radius, step_size, min_rel_gain, backtracks = prm[0], prm[1], prm[2], int(prm[4])
    cams = np.empty((1, 12))
    dcams = np.empty((6, 12))
    psi = np.zeros(1)
    dpsi = np.zeros((1, 12))
    terms, acc = np.zeros((1, 1)), np.zeros((1, 7))
    grad = np.empty(6)
    gstep = np.empty(6)
    ts = np.zeros(2, dtype=np.int64)
    r2 = radius * radius
    pose = poses[s]
    now = cur[s]
    t0 = _now(ts)
    projected_tangents(pose, env, cams, dcams)
    proxy_psi(cams, intr, means, sigma6, weight, rate, kinds, axes, mode, occ, mass, vis_prm,
              cells, bins, True, False, 0, 1, psi, dpsi, terms, False, acc)
    tally[0] += 1.0
    gsq = 0.0
    for j in range(6):
        g = 0.0
        for m in range(12):
            g += dpsi[0, m] * dcams[j, m]
        grad[j] = _r32(g, single)
        gsq += grad[j] * grad[j]
    t1 = _now(ts)
    tally[2] += t1 - t0
    gnorm = math.sqrt(gsq)
    if not (math.isfinite(gnorm) and gnorm > 0.0):
        active[s] = 0
        return
    for j in range(6):  # the Riemannian gradient: the inverse metric applied
        gstep[j] = _r32(grad[j] * r2, single) if j < 3 else grad[j]
    mnorm = _r32(math.sqrt(
        _r32((gstep[0] * gstep[0] + gstep[1] * gstep[1] + gstep[2] * gstep[2]) / r2, single)
        + (gstep[3] * gstep[3] + gstep[4] * gstep[4] + gstep[5] * gstep[5])), single)
    loc = eta[s]
    accepted = False
    for _n in range(backtracks + 1):
        trial_pose(pose, gstep, mnorm, loc, env, single, cams)
        proxy_psi(cams, intr, means, sigma6, weight, rate, kinds, axes, mode, occ, mass,
                  vis_prm, cells, bins, False, False, 0, 1, psi, dpsi, terms, False, acc)
        tally[1] += 1.0
        val = _r32(psi[0], single)
        if math.isfinite(val) and val >= now:
            for i in range(3):
                for j in range(3):
                    pose[i, j] = cams[0, 3 * i + j]
                pose[i, 3] = cams[0, 9 + i]
            gain = _r32(val - now, single)
            cur[s] = val
            traces[s, ntrace[s]] = val
            ntrace[s] += 1
            grown = loc * 1.5
            eta[s] = _r32(grown if grown < 4.0 * step_size else 4.0 * step_size, single)
            accepted = True
            if gain <= min_rel_gain * abs(now):
                active[s] = 0
            break
        loc = _r32(loc * 0.5, single)
    tally[3] += _now(ts) - t1
    if not accepted:
        active[s] = 0
