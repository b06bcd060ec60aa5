"""FisherRF (Jiang, Lei and Daniilidis, ECCV 2024) as its public code computes it.

Point by point, following JiangWenPL/FisherRF:

- The acquisition score is a trace, acq(v) = Σ_q H_v,q / (H_train,q + λ), argmax over the
  candidates (``active/H_reg.py``, ``HRegSelector.select_single_view``: ``I_train =
  reciprocal(H_train + reg_lambda)``, ``acq = sum(cur_H * I_train)``).
- λ = 1e-6 (``active_train.py``, ``--reg_lambda``), :class:`FisherRFConfig.reg_lambda`.
- The parameter blocks are xyz, f_dc, f_rest, scaling and opacity: rotation is left out
  (``active_train.py``, ``--filter_out_grad rotation``; ``HRegSelector.__init__``).
- H_train is rebuilt at every selection from all training views on the current map
  (``HRegSelector.nbvs``: a loop over ``scene.getTrainCameras()``); here the acquired poses.
- A view's H comes from one backward pass of the render with an all-ones output gradient
  (``nbvs``: ``pred_img.backward(gradient=torch.ones_like(pred_img))`` through
  ``modified_render``) in which the forked rasterizer squares each pixel's contribution
  before accumulating it (``diff/cuda_rasterizer/backward.cu``, the fused ``renderCUDA``
  backward with ``acc_func = atomicAddSquare``). Read from that kernel:

  * one residual per pixel: the output gradient is 1 on every channel, so the per-pixel
    gradient is that of the channel sum Σ_c C_pc (``dL_dalpha`` sums the channels before
    anything is squared);
  * it is taken all the way to the renderer's inputs inside the pixel loop (3D means, SH
    coefficients, the activated scales s = exp(log s), the rotation, the activated opacity
    σ) and squared there;
  * α's derivatives use o·G whether or not α was clamped at 0.99 (``dL_dG = con_o.w *
    dL_dalpha``; the reference rasterizer does the same);
  * torch's autograd then chains the squared sums from the activated to the stored
    parameters linearly, as any gradient: H_logscale = H_s · s and H_logit = H_σ · σ(1 - σ).

``fisherrf_hessian`` evaluates exactly that with the one-pass moment machinery of
:mod:`agilegs.service.nbv.information` (channel-summed residuals; the compiled kernels where
they apply, :mod:`agilegs.service.nbv.kernels.backend`); ``fisherrf_hessian_bruteforce`` is the slow
reference (one autograd backward per pixel). The rotation block is not offered:
its kernel gradient is taken w.r.t. the unnormalised quaternion, which our projection (it
normalises) does not expose; FisherRF leaves it out by default anyway.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch
from torch import Tensor

from agilegs.config.selection import FISHERRF_FIELDS

from ..camera import Camera
from ..cancel import checkpoint
from ..gaussians import GaussianMap
from ..information import (
    _check_fields,
    jacobian_sandwich,
    projection_jacobians,
    screen_second_moments,
)
from ..kernels.backend import Backend, resolve
from ..kernels.ops import kernel_fisher
from ..rasterize import render
from .base import MethodResult, SelectionContext, register, timed
from .common import argmax_first

__all__ = ["FisherRFMethod", "fisherrf_hessian", "fisherrf_hessian_bruteforce"]


def fisherrf_hessian(
    gmap: GaussianMap,
    camera: Camera,
    *,
    background: Tensor | None = None,
    fields: Iterable[str] | None = None,
    tile_size: int = 8,
    near: float = 0.01,
    max_elements: int = 1 << 22,
    backend: Backend | None = None,
) -> dict[str, Tensor]:
    """FisherRF's diagonal Hessian of one view, per stored parameter block.

    H_θ = Σ_p (∂(Σ_c C_pc)/∂a(θ))² · a'(θ) with a the activation the renderer applies
    (identity for means and SH, exp for the log-scales, sigmoid for the opacity logits).

    Args:
        gmap: the map (N Gaussians).
        camera: the view.
        background: the render's background colour [3] (None: black).
        fields: blocks to return (default: means, log_scales, opacity_logits, sh).
        backend: "auto", "numba" or "torch" (:mod:`agilegs.service.nbv.kernels.backend`).

    Returns:
        {field: H, the field's shape}.
    """
    want = _check_fields(fields, FISHERRF_FIELDS)
    g = gmap.detach()
    if resolve(backend, [*g.tensors().values(), camera.c2w]):
        # the kernels give Jᵀ M J in the stored parameters; FisherRF chains linearly
        hk = kernel_fisher(g, camera, want, background=background, tile_size=tile_size,
                           near=near, residuals="pixels")
        if "opacity_logits" in hk:  # J = σ' on the opacity: Jᵀ M J = M_oo σ'², FisherRF M_oo σ'
            sig = torch.sigmoid(g.opacity_logits)
            sp = sig * (1.0 - sig)
            hk["opacity_logits"] = torch.where(
                sp > 0, hk["opacity_logits"] / sp.clamp_min(1e-38), torch.zeros_like(sp))
        if "log_scales" in hk:
            hk["log_scales"] = hk["log_scales"] / torch.exp(g.log_scales).clamp_min(1e-30)
        return hk
    with torch.no_grad():
        m = screen_second_moments(g, camera, background=background, tile_size=tile_size,
                                  near=near, max_elements=max_elements, residuals="pixels",
                                  backend=backend)
    jac_fields = tuple(f for f in want if f != "opacity_logits")
    jac = (projection_jacobians(g, camera, jac_fields, near=near, backend="torch")
           if jac_fields else {})
    out: dict[str, Tensor] = {}
    with torch.no_grad():
        for f in want:
            shape = getattr(g, f).shape
            if f == "opacity_logits":
                # the opacity reaches the image through σ only: ∂s/∂σ is the unit vector
                sig = torch.sigmoid(g.opacity_logits)
                out[f] = m[:, 5, 5] * sig * (1.0 - sig)
                continue
            h = jacobian_sandwich(jac[f], m)  # in the stored parameters
            if f == "log_scales":  # J_logs = s J_s: H_s · s = (J_logsᵀ M J_logs) / s
                h = h / torch.exp(g.log_scales).clamp_min(1e-30)
            out[f] = h.reshape(shape)
    return out


def fisherrf_hessian_bruteforce(
    gmap: GaussianMap,
    camera: Camera,
    *,
    background: Tensor | None = None,
    tile_size: int = 8,
) -> dict[str, Tensor]:
    """Reference: one autograd backward of Σ_c C_pc per pixel w.r.t. the activated
    parameters, squared and summed, then chained linearly to the stored ones (slow).

    α's 0.99 clamp passes no derivative here (the render's autograd): compare with
    :func:`fisherrf_hessian` on maps whose opacities stay below 0.99.
    """
    g = gmap.detach()
    act = {
        "means": g.means.clone().requires_grad_(True),
        "scales": torch.exp(g.log_scales).requires_grad_(True),
        "opacity": torch.sigmoid(g.opacity_logits).requires_grad_(True),
        "sh": g.sh.clone().requires_grad_(True),
    }
    rebuilt = GaussianMap(
        means=act["means"],
        log_scales=torch.log(act["scales"]),
        quats=g.quats,
        opacity_logits=torch.logit(act["opacity"]),
        sh=act["sh"],
    )
    rgb = render(rebuilt, camera, background=background, tile_size=tile_size,
                 backward="autograd").rgb
    per_pixel = rgb.sum(-1).reshape(-1)
    acc = {k: torch.zeros_like(v) for k, v in act.items()}
    names = list(act)
    for i in range(per_pixel.numel()):
        if i % 256 == 0:
            checkpoint()
        if not per_pixel[i].requires_grad:
            continue
        grads = torch.autograd.grad(per_pixel[i], [act[k] for k in names], retain_graph=True,
                                    allow_unused=True)
        for k, gr in zip(names, grads):
            if gr is not None:
                acc[k] += gr * gr
    s = act["scales"].detach()
    sig = act["opacity"].detach()
    return {
        "means": acc["means"],
        "log_scales": acc["scales"] * s,
        "opacity_logits": acc["opacity"] * sig * (1.0 - sig),
        "sh": acc["sh"],
    }


class FisherRFMethod:
    name = "fisherrf"
    uses_information = False  # it rebuilds its own H_train from the acquired views

    def __call__(self, ctx: SelectionContext) -> MethodResult:
        cfg = ctx.config.fisherrf
        fields = tuple(cfg.fields)
        g = ctx.gmap.detach()
        lat: dict[str, float] = {}
        acquired = ctx.acquired if ctx.acquired is not None else torch.zeros(0, 4, 4)
        with timed(lat, "information"):
            h_train = {f: torch.zeros_like(getattr(g, f)) for f in fields}
            for pose in acquired.detach().to(g.dtype):
                checkpoint()
                hv = fisherrf_hessian(g, Camera(c2w=pose, intrinsics=ctx.intrinsics),
                                      background=ctx.background, fields=fields)
                for f in fields:
                    h_train[f] += hv[f]
            inv = {f: (h_train[f] + cfg.reg_lambda).reciprocal() for f in fields}
        with timed(lat, "scoring"):
            acq = torch.empty(len(ctx.eligible), dtype=torch.float64)
            for i, pose in enumerate(ctx.eligible_poses):
                checkpoint()
                hv = fisherrf_hessian(g, Camera(c2w=pose, intrinsics=ctx.intrinsics),
                                      background=ctx.background, fields=fields)
                acq[i] = sum(float((hv[f] * inv[f]).sum(dtype=torch.float64)) for f in fields)
        scores = {v: float(a) for v, a in zip(ctx.eligible, acq)}
        return MethodResult(index=ctx.eligible[argmax_first(acq)], scores=scores,
                            latency_ms=lat, details={"training_views": int(acquired.shape[0])})


register(FisherRFMethod())
