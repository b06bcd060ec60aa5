"""Training renders through gsplat on CUDA, and the choice between it and the built-in rasterizer.

gsplat (https://github.com/nerfstudio-project/gsplat, the optional extra ``agilegs[cuda]``) is
the 3DGS ecosystem's CUDA rasterizer. Its ``rasterization`` follows the same model as the
built-in one (:mod:`agilegs.service.nbv.rasterize`): OpenCV pinhole cameras, pixel centres at
``+0.5``, EWA projection with the 0.3 px² low-pass, a near plane at 0.01, SH colour
``0.5 + SH`` clamped at 0, α = min(0.99, o·exp(-σ)) skipped under 1/255, front-to-back
compositing stopped at a transmittance of 1e-4. The two differ in how far a Gaussian's
footprint reaches before the 1/255 test (the reference 3DGS rule, 3σ of the major axis, binned
in 8-pixel tiles, against gsplat's opacity-aware per-axis extent binned in 16-pixel tiles), so
they agree to within edge pixels of opaque Gaussians: the GPU tests state the tolerance.

The built-in rasterizer stays the reference and serves everything else: the CPU, float64
maps, renders differentiable in the camera pose, and the Fisher information.

``MapperConfig.rasterizer`` chooses: ``"builtin"``; ``"gsplat"`` (an error where it cannot
run, naming why); ``"auto"`` (gsplat where the map is a float32 map on CUDA and gsplat loads,
the built-in rasterizer elsewhere).
"""

from __future__ import annotations

import logging
from functools import lru_cache
from typing import Any

import torch
from torch import Tensor

from agilegs.service.nbv import Camera, GaussianMap, RenderResult

log = logging.getLogger(__name__)

__all__ = ["RASTERIZERS", "gsplat_rasterization", "gsplat_status", "render_gsplat",
           "resolve_rasterizer"]

RASTERIZERS: tuple[str, ...] = ("auto", "builtin", "gsplat")
GSPLAT_TILE = 16
GSPLAT_NEAR = 0.01


@lru_cache(maxsize=1)
def _gsplat_or_reason() -> tuple[Any, str | None]:
    if not torch.cuda.is_available():
        return None, "CUDA is not available"
    try:
        import gsplat
    except ImportError as exc:
        return None, f"gsplat is not installed ({exc}): pip install 'agilegs[cuda]'"
    try:  # the first use builds gsplat's CUDA extension (minutes, once per machine)
        from gsplat.cuda._backend import _C
    except Exception as exc:  # a failed build raises anything from the compiler driver
        return None, f"gsplat's CUDA extension failed to load: {exc}"
    if _C is None:
        return None, "gsplat's CUDA extension is not built (no CUDA toolkit was found)"
    log.info("gsplat %s loaded", getattr(gsplat, "__version__", "?"))
    return gsplat.rasterization, None


def gsplat_status() -> str | None:
    """None when gsplat can render here, else the reason it cannot (one line)."""
    return _gsplat_or_reason()[1]


def gsplat_rasterization() -> Any:
    """gsplat's ``rasterization`` function; :class:`RuntimeError` saying why when unavailable."""
    fn, why = _gsplat_or_reason()
    if fn is None:
        raise RuntimeError(f"gsplat cannot render here: {why}")
    return fn


def resolve_rasterizer(name: str, device: torch.device | str, dtype: torch.dtype) -> str:
    """``"builtin"`` or ``"gsplat"`` for a map on ``device`` of ``dtype``.

    Raises:
        ValueError: ``name`` is not one of :data:`RASTERIZERS`, or it is ``"gsplat"`` and
            gsplat cannot render such a map here (the message says why).
    """
    if name not in RASTERIZERS:
        raise ValueError(f"rasterizer must be one of {', '.join(RASTERIZERS)}, got {name!r}")
    if name == "builtin":
        return "builtin"
    dev = torch.device(device)
    if dev.type != "cuda":
        why: str | None = f"the map is on {dev}; gsplat renders on CUDA only"
    elif dtype != torch.float32:
        why = f"the map is {dtype}; gsplat renders float32 only"
    else:
        why = gsplat_status()
    if why is None:
        return "gsplat"
    if name == "gsplat":
        raise ValueError(f"rasterizer='gsplat': {why}")
    return "builtin"


def render_gsplat(
    gmap: GaussianMap,
    camera: Camera,
    *,
    background: Tensor | None = None,
    sh_degree: int | None = None,
) -> RenderResult:
    """Render ``gmap`` from ``camera`` with gsplat (differentiable in the map, not the pose).

    Args:
        gmap: float32 Gaussians on CUDA (N of them), ``sh`` [N, K, 3]; fields may require grad.
        camera: the view (its pose is not differentiated).
        background: colour [3] composited behind (default black): C + (1 - alpha) · bg.
        sh_degree: SH degree to evaluate (default: the largest ``sh`` holds).

    Returns:
        RenderResult with rgb [H, W, 3], alpha [H, W], depth [H, W] (expected depth, 0 where
        alpha is 0), means2d [1, N, 2] (gsplat's screen-space centres, the tensor its
        compositing reads: ``retain_grad()`` before backward gives the densification
        gradient), radii [N] (the larger axis of gsplat's per-axis extent; 0 where culled),
        depths [N] (camera depth); ``features`` is None.
    """
    rasterization = gsplat_rasterization()
    n, k = gmap.sh.shape[0], gmap.sh.shape[1]
    deg = int(round(k**0.5)) - 1 if sh_degree is None else int(sh_degree)
    if (deg + 1) ** 2 > k:
        raise ValueError(f"sh_degree {deg} needs {(deg + 1) ** 2} SH coefficients, map has {k}")
    dev, dt = gmap.means.device, gmap.means.dtype
    w2c = camera.w2c.detach().to(device=dev, dtype=dt)
    kmat = torch.tensor([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy],
                         [0.0, 0.0, 1.0]], dtype=dt, device=dev)
    colors, alphas, meta = rasterization(
        gmap.means,
        torch.nn.functional.normalize(gmap.quats, dim=-1),
        torch.exp(gmap.log_scales),
        torch.sigmoid(gmap.opacity_logits),
        gmap.sh,
        w2c[None],
        kmat[None],
        camera.width,
        camera.height,
        near_plane=GSPLAT_NEAR,
        sh_degree=deg,
        packed=False,
        tile_size=GSPLAT_TILE,
        render_mode="RGB+ED",
        rasterize_mode="classic",
    )
    rgb = colors[0, ..., :3]
    alpha = alphas[0, ..., 0]
    depth = torch.where(alpha > 0, colors[0, ..., 3], torch.zeros_like(alpha))
    if background is not None:
        bg = torch.as_tensor(background, dtype=dt, device=dev).reshape(3)
        rgb = rgb + (1.0 - alpha)[..., None] * bg
    radii = meta["radii"][0]
    if radii.dim() == 2:  # per-axis extents (gsplat >= 1.5)
        radii = radii.amax(dim=-1)
    means2d = meta["means2d"]
    depths = meta["depths"][0] if meta.get("depths") is not None else torch.zeros(n, device=dev)
    return RenderResult(rgb=rgb, alpha=alpha, depth=depth, features=None,
                        means2d=means2d, radii=radii.to(torch.int64),
                        depths=depths)

