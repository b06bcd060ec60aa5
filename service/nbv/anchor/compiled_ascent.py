"""The anchor's ascent with each start's step in one compiled call
(:func:`agilegs.service.nbv.kernels.ascent_loop.ascent_step`): the gradient, the line search
and the acceptance of :class:`.ascent.Ascent` (the reference) without torch between them,
for a proxy ψ whose kernel serves the poses; between the calls only a cancellation check.

The rules are the reference's; the arithmetic is the kernels' (float64, rounded to float32
where the torch path stores a number), so that the poses and ψ agree with the reference's to
rounding while the ascent stays off the envelope's bounds. At a bound the ascent is not
continuous in the pose (a clamp passes its gradient or not by the last bit of the recomputed
radius, :mod:`.envelope`), and there a start of either path may take another way.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from agilegs.config.selection import AnchorConfig

from ..cancel import checkpoint
from ..kernels import backend
from .envelope import PoolEnvelope
from .line_search import CompiledLineSearch, envelope_vector
from .proxy import ProxyPsi
from .records import AscentTally

__all__ = ["CompiledAscent"]


class CompiledAscent:
    """:class:`.ascent.Ascent` of a proxy ψ from start poses [S, 4, 4] through the compiled
    kernels (the module docstring), with the reference's attributes: building it projects
    the starts into the envelope and evaluates them (torch, as the reference); :meth:`run`
    takes the steps, each start's step one compiled call with a cancellation check before
    it.

    Attributes:
        poses: the current pose of every start [S, 4, 4].
        cur: psi at ``poses`` [S].
        traces: per start, psi at its start and after each accepted step.
        evaluations: the psi evaluations so far.
        tally: the evaluations with and without the gradient, and their seconds (timed
            inside the compiled call).
    """

    def __init__(self, proxy: ProxyPsi, starts: Tensor, *, config: AnchorConfig,
                 envelope: PoolEnvelope | None, radius: float) -> None:
        self.proxy = proxy
        self.config = config
        self.radius = radius
        self.dt = starts.dtype
        self.env = envelope_vector(envelope, self.dt)
        self.tally = AscentTally()
        poses = starts.detach().clone()
        if envelope is not None:
            poses = envelope.project(poses)
        t0 = time.perf_counter()
        with torch.no_grad():
            self.cur = proxy(poses).detach()
        self.tally.value_s += time.perf_counter() - t0
        self.tally.value_evaluations += poses.shape[0]
        self.poses = poses
        self.evaluations = poses.shape[0]
        self.traces = [[float(v)] for v in self.cur]

    @staticmethod
    def serves(psi_fn: Callable[[Tensor], Tensor], poses: Tensor) -> bool:
        """Whether the compiled ascent serves ``psi_fn`` at ``poses``: a proxy whose kernel
        serves them (:meth:`.line_search.CompiledLineSearch.serves`) and a clock for the
        kernels' tally."""
        if not CompiledLineSearch.serves(psi_fn, poses):
            return False
        kernels = backend.kernel_module()
        return kernels is not None and int(kernels.CLOCK) >= 0

    def run(self) -> CompiledAscent:
        """Up to ``config.iterations`` steps of every start; returns the ascent."""
        cfg = self.config
        kin = self.proxy._kernel_inputs()
        n = self.poses.shape[0]
        f64 = torch.float64
        poses = np.ascontiguousarray(self.poses.detach().cpu().to(f64).numpy())
        cur = np.ascontiguousarray(self.cur.detach().cpu().to(f64).numpy())
        eta = np.full(n, float(torch.tensor(cfg.step_size, dtype=self.dt)))
        traces = np.zeros((n, cfg.iterations + 1))
        traces[:, 0] = cur
        ntrace = np.ones(n, dtype=np.int64)
        tally = np.zeros(4)
        prm = np.array([self.radius, cfg.step_size, cfg.min_rel_gain, cfg.iterations,
                        cfg.backtracks], dtype=np.float64)
        active = np.ones(n, dtype=np.uint8)
        fn = backend.kernel_module().ascent_step
        for _ in range(cfg.iterations):
            checkpoint()
            for s in np.flatnonzero(active).tolist():
                checkpoint()
                fn(poses, cur, eta, active, s, self.env, prm, self.dt == torch.float32,
                   kin["intr"], kin["means"], kin["sigma6"], kin["weight"], kin["rate"],
                   kin["kinds"], kin["axes"], kin["mode"], kin["occ"], kin["mass"],
                   kin["vis_prm"], kin["cells"], kin["bins"], traces, ntrace, tally)
        dev = self.poses.device
        self.poses = torch.from_numpy(poses).to(device=dev, dtype=self.dt)
        self.cur = torch.from_numpy(cur).to(device=dev, dtype=self.dt)
        self.traces = [[float(v) for v in traces[s, :int(ntrace[s])]] for s in range(n)]
        self.tally.gradient_evaluations += int(tally[0])
        self.tally.value_evaluations += int(tally[1])
        self.tally.gradient_s += float(tally[2])
        self.tally.value_s += float(tally[3])
        self.evaluations += int(tally[0]) + int(tally[1])
        return self
