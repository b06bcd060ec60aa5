"""The line searches of the anchor's ascent (:func:`agilegs.service.nbv.anchor.ascent.ascend`)
through the compiled kernel :func:`agilegs.service.nbv.kernels.ascent.line_search`: per start,
the number of the trial the reference's backtracking would accept, and the trials it
evaluated."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from agilegs.config.selection import AnchorConfig

from ..cancel import checkpoint
from ..kernels import backend
from .envelope import PoolEnvelope
from .proxy import ProxyPsi

__all__ = ["CompiledLineSearch"]


class CompiledLineSearch:
    """The line searches of :func:`ascend` through the compiled kernel, one start at a time
    (:func:`agilegs.service.nbv.kernels.ascent.line_search`)."""

    def __init__(self, proxy: ProxyPsi, config: AnchorConfig, envelope: PoolEnvelope | None,
                 radius: float, dt: torch.dtype) -> None:
        self.proxy = proxy
        self.config = config
        self.radius = radius
        self.dt = dt
        self.single = dt == torch.float32

        def r(x: float) -> float:  # a bound the torch path applies in the poses' dtype
            return float(torch.tensor(x, dtype=dt)) if self.single else x

        if envelope is None:
            self.env = np.zeros(15)
        else:
            vec = torch.cat([envelope.centre.to(dt), envelope.up.to(dt), envelope.aim.to(dt)])
            self.env = np.concatenate([
                vec.detach().cpu().to(torch.float64).numpy(),
                [r(envelope.r_min), r(envelope.r_max), r(envelope.elev_min),
                 r(envelope.elev_max), r(envelope.max_off_aim), 1.0]])
        self.fn = backend.kernel_module().line_search

    @staticmethod
    def serves(psi_fn: Callable[[Tensor], Tensor], poses: Tensor) -> bool:
        """Whether ``psi_fn`` is a proxy whose kernel serves ``poses`` (float32 or float64
        on the CPU)."""
        return (isinstance(psi_fn, ProxyPsi) and poses.dtype in (torch.float32, torch.float64)
                and poses.device.type == "cpu" and psi_fn.uses_kernel(poses))

    def search(self, ids: Tensor, grad: Tensor, poses: Tensor, cur: Tensor, eta: Tensor
               ) -> tuple[list[int], list[int]]:
        """The line search of each start ``ids`` [K] along its twist gradient ``grad``
        [K, 6] from ``poses[ids]`` with psi ``cur[ids]`` and step length ``eta[ids]``:
        the number of the accepted trial (1 for the first; 0 when none was) and the trials
        evaluated, per start."""
        cfg = self.config
        gnorm = grad.norm(dim=1)
        step_ok = (torch.isfinite(gnorm) & (gnorm > 0)).tolist()
        # the metric step's direction and length (:func:`_metric_step` with eta = 1)
        g = grad.clone()
        g[:, :3] = g[:, :3] * self.radius**2
        norm = torch.sqrt((g[:, :3] ** 2).sum(1) / self.radius**2 + (g[:, 3:] ** 2).sum(1))
        g64 = g.detach().cpu().to(torch.float64).numpy()
        n64 = norm.detach().cpu().to(torch.float64).tolist()
        p64 = poses.detach().cpu().to(torch.float64).numpy()
        kin = self.proxy._kernel_inputs()
        out = np.empty((4, 4))
        found: list[int] = []
        counts: list[int] = []
        for k, s in enumerate(ids.tolist()):
            checkpoint()
            if not step_ok[k]:
                found.append(0)
                counts.append(0)
                continue
            prm = np.array([float(cur[s]), float(eta[s]), 4 * cfg.step_size, cfg.min_rel_gain,
                            float(cfg.backtracks)])
            status, _, _, n = self.fn(
                np.ascontiguousarray(p64[s]), np.ascontiguousarray(g64[k]), n64[k], prm,
                self.env, self.single, kin["intr"], kin["means"], kin["sigma6"],
                kin["weight"], kin["rate"], kin["kinds"], kin["axes"], kin["mode"],
                kin["occ"], kin["mass"], kin["vis_prm"], kin["cells"], kin["bins"], out)
            found.append(int(n) if status else 0)
            counts.append(int(n))
        return found, counts
