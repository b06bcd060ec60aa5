"""The anchor's proxy ψ timed beside the Fisher in ``agilegs bench render --device cuda``.

On the row's map and image: a directional proxy ψ as the anchor builds it with its default
settings (``AnchorConfig``: its sample of Gaussians, its deep opacity maps' occluders, cells
and slices, the proxy's image width; every parameter slot of the map's fields with its
direction factor; the rates and weights drawn, seeded, since only the shapes set the cost),
and a capture pool around the map:

- ``anchor_pool``: ψ at every pool pose without gradient (the starts' scoring; on CUDA one
  launch of the Triton kernels, :mod:`agilegs.service.nbv.kernels.gpu_proxy`);
- ``anchor_grad``: ψ and its twist gradient at ``STARTS`` poses, as one step of the ascent
  takes it (autograd through ``poses @ se3_exp(xi)`` at xi = 0);
- ``anchor_pool_torch``, ``anchor_grad_torch``: the same through the pure-torch reference
  (``AGILEGS_KERNELS=torch``'s path);

with ``anchor_agree`` the larger of the two largest differences (ψ at the pool, the twist
gradients), relative to the reference's largest entry, and ``anchor_path`` the path that
served (``triton`` on CUDA, ``numba`` on the CPU, ``torch``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

STARTS = 4
"""Poses of the gradient's timing (the anchor's three starts and the warm start)."""


def anchor_functions(gm: Any, cam: Any, *, samples: int | None = None, pool: int = 100
                     ) -> tuple[dict[str, Callable[[], Any]], dict[str, Any]]:
    """The timed kinds above, and a function computing the agreement and the path
    (``details["agree"]()`` -> (agree, path)). ``samples``: the proxy's sample (default:
    the anchor's); ``pool``: the pool's poses."""
    import torch

    from agilegs.config.selection import FIELD_NAMES, AnchorConfig
    from agilegs.service.nbv import GaussianMap, init_information, se3_exp
    from agilegs.service.nbv.anchor.assembly import proxy_intrinsics
    from agilegs.service.nbv.anchor.fitting import slot_kinds
    from agilegs.service.nbv.anchor.proxy import ProxyPsi
    from agilegs.service.nbv.anchor.visibility import OpacityMaps
    from agilegs.service.nbv.candidates import capture_pool, scene_center_radius
    from agilegs.service.nbv.kernels import backend
    from agilegs.service.nbv.kernels.gpu_proxy import gpu_proxy_applies

    cfg = AnchorConfig()
    dev, dt = gm.means.device, gm.means.dtype
    gen = torch.Generator().manual_seed(0)
    intr = proxy_intrinsics(cam.intrinsics, cfg)
    centre, r98 = scene_center_radius(gm.means)
    grid = OpacityMaps.build(gm, intr, centre, r98, cells=cfg.transmittance_cells,
                             bins=cfg.transmittance_bins, max_occluders=cfg.occluders,
                             generator=gen)
    one = GaussianMap(**{k: v[:1] for k, v in gm.tensors().items()})
    kinds = slot_kinds(init_information(one, 1e-6), FIELD_NAMES).to(dev)
    n = gm.num_gaussians
    draw = torch.Generator(device=dev).manual_seed(0)
    rate = torch.rand(n, kinds.numel(), generator=draw, dtype=dt, device=dev)
    c = torch.rand(n, generator=draw, dtype=dt, device=dev) + 0.1
    radius = 2.6 * r98  # the pool's
    proxy = ProxyPsi.build(gm, c, intr, num_samples=cfg.num_gaussians if samples is None
                           else samples, near=cfg.near_fraction * radius,
                           edge=cfg.edge_softness * intr.width, generator=gen, grid=grid,
                           rate=rate, slot_kinds=kinds)
    poses = capture_pool(centre.cpu(), radius, pool, seed=0).to(dev, dt)
    starts = poses[:STARTS]

    def values() -> Any:
        with torch.no_grad():
            return proxy(poses)

    def gradient() -> Any:
        xi = torch.zeros(starts.shape[0], 6, dtype=dt, device=dev, requires_grad=True)
        val = proxy(starts @ se3_exp(xi))
        (g,) = torch.autograd.grad(val.sum(), xi)
        return g

    def on_torch(fn: Callable[[], Any]) -> Callable[[], Any]:
        def run() -> Any:
            try:
                backend.set_default_backend("torch")
                return fn()
            finally:
                backend.set_default_backend(None)
        return run

    def agree() -> tuple[float, str]:
        pairs = ((values(), on_torch(values)()), (gradient(), on_torch(gradient)()))
        err = max(float((a.double() - b.double()).abs().max()
                        / b.double().abs().max().clamp_min(1e-30)) for a, b in pairs)
        path = ("triton" if gpu_proxy_applies(None, poses, proxy.means)
                else "numba" if proxy.uses_kernel(poses) else "torch")
        return err, path

    fns = {"anchor_pool": values, "anchor_grad": gradient,
           "anchor_pool_torch": on_torch(values), "anchor_grad_torch": on_torch(gradient)}
    return fns, {"agree": agree, "samples": int(proxy.means.shape[0]),
                 "slots": int(kinds.numel()), "pool": pool}
