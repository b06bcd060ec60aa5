"""The line searches of the anchor's ascent (:func:`agilegs.service.nbv.anchor.ascent.ascend`)
through compiled kernels: per start, the number of the trial the reference's backtracking would
accept, and the trials it evaluated; each trial's pose by
:func:`agilegs.service.nbv.kernels.ascent.trial_pose`, its ψ by the proxy's kernel."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from agilegs.config.selection import AnchorConfig

from ..cancel import checkpoint
from ..kernels import backend
from .envelope import PoolEnvelope
from .proxy import ProxyPsi

__all__ = ["CompiledLineSearch", "envelope_vector"]


def envelope_vector(envelope: PoolEnvelope | None, dt: torch.dtype) -> np.ndarray:
    """The envelope as the kernels' vector [15] (:mod:`agilegs.service.nbv.kernels.ascent`),
    its bounds as the torch path holds them in ``dt``; zeros without an envelope."""
    if envelope is None:
        return np.zeros(15)

    def r(x: float) -> float:  # a bound the torch path applies in the poses' dtype
        return float(torch.tensor(x, dtype=dt)) if dt == torch.float32 else x

    vec = torch.cat([envelope.centre.to(dt), envelope.up.to(dt), envelope.aim.to(dt)])
    return np.concatenate([
        vec.detach().cpu().to(torch.float64).numpy(),
        [r(envelope.r_min), r(envelope.r_max), r(envelope.elev_min), r(envelope.elev_max),
         r(envelope.max_off_aim), 1.0]])


class CompiledLineSearch:
    """The line searches of :func:`~agilegs.service.nbv.anchor.ascent.ascend` through the
    compiled kernels, one start at a time: the trials' poses
    (:func:`agilegs.service.nbv.kernels.ascent.trial_pose`) and their ψ
    (:func:`agilegs.service.nbv.kernels.proxy.proxy_psi`), in turn; the numbers the torch
    path holds in float32 (the trial pose, ψ, the step length) rounded as it does."""

    def __init__(self, proxy: ProxyPsi, config: AnchorConfig, envelope: PoolEnvelope | None,
                 radius: float, dt: torch.dtype) -> None:
        self.proxy = proxy
        self.config = config
        self.radius = radius
        self.dt = dt
        self.single = dt == torch.float32
        self.env = envelope_vector(envelope, dt)
        self.kernels = backend.kernel_module()

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
        trial_pose, psi_fn = self.kernels.trial_pose, self.kernels.proxy_psi
        cams = np.empty((1, 12))
        psi = np.zeros(1)
        dpsi, terms, acc = np.zeros((1, 12)), np.zeros((1, 1)), np.zeros((1, 7))
        args = (kin["intr"], kin["means"], kin["sigma6"], kin["weight"], kin["rate"],
                kin["kinds"], kin["axes"], kin["mode"], kin["occ"], kin["mass"],
                kin["vis_prm"], kin["cells"], kin["bins"], False, False, 0, 1, psi, dpsi,
                terms, False, acc)
        found: list[int] = []
        counts: list[int] = []
        for k, s in enumerate(ids.tolist()):
            checkpoint()
            found.append(0)
            counts.append(0)
            if not step_ok[k]:
                continue
            pose, step, now = np.ascontiguousarray(p64[s]), float(eta[s]), float(cur[s])
            for n in range(cfg.backtracks + 1):
                trial_pose(pose, g64[k], n64[k], step, self.env, self.single, cams)
                psi_fn(cams, *args)
                val = float(np.float32(psi[0])) if self.single else float(psi[0])
                counts[-1] = n + 1
                if math.isfinite(val) and val >= now:
                    found[-1] = n + 1
                    break
                step = self.round(step * 0.5)
        return found, counts

    def round(self, x: float) -> float:
        """``x`` as the torch path holds it (float32 or float64)."""
        return float(np.float32(x)) if self.single else x
