"""The exact psi: the trace surrogate of the exact Fisher of a render at T, and its pose gradient.

psi(T) = trace_surrogate(fisher_diag(gmap, camera(T)), h_acc), rendered at reduced resolution
(``AnchorConfig.resolution``, default 64 pixels wide) on the background Hhat was computed
with. A value is one Fisher pass: the compiled kernels where they serve
(:mod:`agilegs.service.nbv.kernels.backend`), else the pure-torch path.

The gradient w.r.t. a right-perturbation twist at 0 (``c2w = P(T exp(xi))``, P the envelope's
projection), one of:

- ``"autograd"``: torch autograd through the torch renderer and Fisher, which differentiate in
  the pose (the reference);
- ``"central"``: central differences over the six twist coordinates, 12 values;
- ``"forward"``: forward differences, 6 values and the value at T (which the ascent knows).

The difference steps are ``h * radius`` on the translation coordinates and ``h`` on the
rotation ones (the ascent's metric: a radian counts as one radius), ``h`` ``eps ** (1/3)``
(central) or ``eps ** (1/2)`` (forward) of the map's dtype, floored at :data:`MIN_STEP`: the
rasterizer's hard cut-offs (alpha < 1/255, the transmittance's stop) make psi piecewise smooth,
and a step far below a pixel's width measures their jumps rather than the slope.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from agilegs.config.selection import AnchorConfig

from ..camera import Camera, Intrinsics
from ..cancel import checkpoint
from ..gaussians import GaussianMap
from ..information import fisher_diag, trace_surrogate
from ..kernels.backend import Backend, resolve
from ..kernels.gpu import gpu_moments_apply
from ..se3 import se3_exp
from .envelope import PoolEnvelope

__all__ = ["GRADIENTS", "MIN_STEP", "ExactPsi", "exact_psi_fn"]

Gradient = Literal["autograd", "central", "forward"]
GRADIENTS: tuple[str, ...] = ("autograd", "central", "forward")
MIN_STEP = 1e-3
"""The smallest difference step (radians, or pool radii on the translation coordinates)."""


class ExactPsi:
    """psi(T) of poses [B, 4, 4] -> [B] (see the module docstring), differentiable in the poses
    when they require grad (then through the torch path).

    Args:
        gmap, h_acc, intrinsics, fields: the map, Hhat, the candidates' intrinsics and the
            blocks entering psi.
        config: the anchor settings (``resolution``).
        background: the background colour [3] of the renders (None: black).
        backend: the Fisher's backend (None: the default, ``AGILEGS_KERNELS``).
        gradient: how :meth:`twist_gradient` differentiates (one of :data:`GRADIENTS`).
        step: the difference step ``h`` (None: from the dtype, :meth:`step`).
    """

    def __init__(self, gmap: GaussianMap, h_acc: dict[str, Tensor], intrinsics: Intrinsics,
                 config: AnchorConfig, fields: tuple[str, ...], *,
                 background: Tensor | None = None, backend: Backend | None = None,
                 gradient: Gradient = "forward", step: float | None = None) -> None:
        if gradient not in GRADIENTS:
            raise ValueError(f"gradient must be one of {GRADIENTS}, got {gradient!r}")
        if step is not None and not step > 0:
            raise ValueError(f"step must be > 0, got {step!r}")
        width = config.resolution or 64
        height = max(1, round(width * intrinsics.height / intrinsics.width))
        self.gmap = gmap
        self.small = intrinsics.scaled(width, height)
        self.h_sel = {k: h_acc[k] for k in fields}
        self.fields = fields
        self.background = background
        self.backend = backend
        self.gradient = gradient
        self.fixed_step = step

    def __call__(self, c2w: Tensor) -> Tensor:
        out = []
        for pose in c2w:
            checkpoint()
            cam = Camera(c2w=pose, intrinsics=self.small)
            fd = fisher_diag(self.gmap, cam, fields=self.fields, background=self.background,
                             backend=self.backend)
            out.append(torch.as_tensor(trace_surrogate(fd, self.h_sel)))
        return torch.stack(out)

    def compiled(self, poses: Tensor) -> bool:
        """Whether a value at ``poses`` [B, 4, 4] (no grad) runs on compiled kernels: the
        CPU's, or on CUDA the Triton moments (:mod:`~agilegs.service.nbv.kernels.gpu`)."""
        return (resolve(self.backend, [*self.gmap.tensors().values(), poses])
                or gpu_moments_apply(self.backend, poses))

    def differences(self, poses: Tensor) -> bool:
        """Whether :meth:`twist_gradient` differentiates by differences of values here: a
        difference ``gradient`` whose values run on the compiled kernels."""
        return self.gradient != "autograd" and self.compiled(poses)

    def step(self, dtype: torch.dtype) -> float:
        """The difference step ``h`` for poses of ``dtype`` (see the module docstring)."""
        if self.fixed_step is not None:
            return self.fixed_step
        eps = torch.finfo(dtype).eps
        h = eps ** (1 / 3) if self.gradient == "central" else eps ** 0.5
        return max(h, MIN_STEP)

    def twist_gradient(self, poses: Tensor, *, envelope: PoolEnvelope | None, radius: float,
                       center: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """psi [B] at ``poses`` [B, 4, 4] (projected into ``envelope``) and its gradient
        [B, 6] w.r.t. the twist (v, w) of ``P(T exp(xi))`` at 0, by differences of values
        (``self.gradient`` "central" or "forward"; the "autograd" gradient is
        :func:`~.ascent.ascend`'s own); ``center`` [B], psi at the poses when known (forward
        differences use it)."""
        dt = poses.dtype
        if self.gradient == "autograd":
            raise ValueError("twist_gradient takes differences; 'autograd' is the ascent's own "
                             "gradient (anchor.ascent.ascend)")
        h = self.step(dt)
        scale = torch.tensor([radius] * 3 + [1.0] * 3, dtype=dt, device=poses.device) * h
        with torch.no_grad():
            if center is None:
                placed = envelope.project(poses) if envelope is not None else poses
                center = self(placed)
            grads = []
            for pose in poses:
                xi = torch.diag(scale)  # [6, 6]: one twist coordinate each
                signs = [xi, -xi] if self.gradient == "central" else [xi]
                moved = pose @ se3_exp(torch.cat(signs))
                if envelope is not None:
                    moved = envelope.project(moved)
                vals = self(moved)
                if self.gradient == "central":
                    grads.append((vals[:6] - vals[6:]) / (2 * scale))
                else:
                    grads.append(vals)
            g = torch.stack(grads)
            if self.gradient == "forward":
                g = (g - center.detach().to(dt).unsqueeze(1)) / scale
        return center.detach(), g


def exact_psi_fn(gmap: GaussianMap, h_acc: dict[str, Tensor], intrinsics: Intrinsics,
                 config: AnchorConfig, fields: tuple[str, ...], *,
                 background: Tensor | None = None, backend: Backend | None = None,
                 gradient: Gradient = "forward", step: float | None = None) -> ExactPsi:
    """The exact psi of ``gmap`` against ``h_acc`` (:class:`ExactPsi`, same arguments)."""
    return ExactPsi(gmap, h_acc, intrinsics, config, fields, background=background,
                    backend=backend, gradient=gradient, step=step)
