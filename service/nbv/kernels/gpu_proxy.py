"""The anchor's proxy ψ (:class:`~agilegs.service.nbv.anchor.proxy.ProxyPsi`) on a GPU: every
pose and every sample in one Triton launch, ψ and its gradient in the poses together.

The CPU kernel (:func:`agilegs.service.nbv.kernels.proxy.proxy_psi`) walks the poses one by
one and their samples in turn; on a GPU the pure-torch reference
(:meth:`~agilegs.service.nbv.anchor.proxy.ProxyPsi.reference`) costs tens of small kernels and
a backward pass per evaluation. Here, for poses [B, 4, 4]:

1. ``deposit_kernel`` (programs: pose × block of occluders): each pose's deep opacity map
   (:class:`~agilegs.service.nbv.anchor.visibility.OpacityMaps`), every occluder's mass added
   into the cell and depth slice of its centre (atomic adds);
2. ``cumulate_kernel`` (a program per pose): each slice blurred by [1, 2, 1]² and the slices
   summed front to back;
3. ``psi_kernel`` (programs: pose × chunk of samples, a lane per sample): each sample's
   footprint × in-frustum × transmittance term, the model's log form (linear, log or
   directional), and with ``want_grad`` the analytic gradient in the pose's rotation and
   centre (the CPU kernel's, lane by lane), summed per program; the programs' parts are then
   added per pose in a fixed order (deterministic ψ; only the deposit's atomic adds are not).

Without deep opacity maps (visibility 1) steps 1 and 2 are skipped. The arithmetic is float64
whatever the poses' dtype (as on the CPU); ψ comes back in the poses' dtype. The torch path
stays the reference: the tests run these kernels through Triton's interpreter on the CPU
(``TRITON_INTERPRET=1``) against it, and compile them for an sm_90 GPU.

:func:`gpu_proxy_applies` says where this path serves: CUDA tensors of float32 or float64,
Triton importable, a backend other than ``"torch"``; ``ProxyPsi`` dispatches to
:func:`proxy_kernel` there. (``proxy`` below is a ``ProxyPsi``: the anchor imports this module,
not this module the anchor.)
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from agilegs.service.settings import kernel_settings

from .backend import default_backend
from .gpu import _interpreting, _load_triton, triton_available

__all__ = ["gpu_proxy_applies", "proxy_kernel", "proxy_launch"]

BLOCK = 128
"""Samples per program step (one lane each)."""
OCC_BLOCK = 256
"""Occluders per program of the deposit."""
PROGRAMS = 264
"""The programs a launch aims at (twice the SMs of an H100/H200): the samples of each pose
are cut into enough chunks for it, at least one block each."""

_MODES = {"linear": 0, "log": 1, "directional": 2}


def gpu_proxy_applies(backend: str | None, c2w: Tensor, means: Tensor) -> bool:
    """Whether :func:`proxy_kernel` serves poses ``c2w`` of a proxy with samples ``means``:
    both on one CUDA device, float32 or float64, Triton importable, the backend not
    ``"torch"`` (the reference; None: the default backend) and ``AGILEGS_GPU_ANCHOR`` not
    false."""
    if c2w.device.type != "cuda" or means.device != c2w.device:
        return False
    b = default_backend() if backend is None else backend
    return (b != "torch" and c2w.dtype in (torch.float32, torch.float64)
            and kernel_settings().gpu_anchor and triton_available())


def _kernels() -> Any:
    if _load_triton() is None:
        raise RuntimeError("triton is unavailable")
    from . import gpu_proxy_kernel  # noqa: PLC0415 (needs triton)

    return gpu_proxy_kernel


def _inputs(proxy: Any, device: torch.device) -> dict[str, Any]:
    """The proxy's samples, model and occluders as the kernels' float64 tensors on
    ``device``, a row per component (built once per proxy and device)."""
    cache: dict[str, dict[str, Any]] = proxy.__dict__.setdefault("_gpu_inputs", {})
    key = str(device)
    if key in cache:
        return cache[key]
    f64 = torch.float64

    def dev(t: Tensor) -> Tensor:
        return t.detach().to(device=device, dtype=f64).contiguous()

    s = proxy.means.shape[0]
    k = proxy.intrinsics
    if proxy.rate is None:
        mode, rate = "linear", torch.zeros(1, s, dtype=f64, device=device)
    elif proxy.rate.ndim == 1:
        mode, rate = "log", dev(proxy.rate.reshape(1, -1))
    else:
        mode, rate = "directional", dev(proxy.rate.T)
    kinds = (proxy.slot_kinds.detach().to(device=device, dtype=torch.int32).contiguous()
             if mode == "directional" and proxy.slot_kinds is not None
             else torch.zeros(1, dtype=torch.int32, device=device))
    axes = (dev(proxy.axes.reshape(-1, 9).T) if mode == "directional"
            and proxy.axes is not None else torch.zeros(9, 1, dtype=f64, device=device))
    grid = proxy.grid
    centre = [0.0, 0.0, 0.0] if grid is None else [float(v) for v in grid.center.detach().cpu()]
    prm = torch.tensor([k.fx, k.fy, k.cx, k.cy, float(k.width), float(k.height),
                        float(proxy.near), float(proxy.edge), *centre,
                        1.0 if grid is None else float(grid.half_depth)], dtype=f64)
    out: dict[str, Any] = dict(
        mode=mode, prm=prm.to(device), means=dev(proxy.means.T), sigma6=dev(proxy.sigma6),
        weight=dev(proxy.weight), rate=rate, kinds=kinds, axes=axes,
        occ=None if grid is None else dev(grid.means.T),
        mass=None if grid is None else dev(grid.mass),
        cells=1 if grid is None else int(grid.cells), bins=1 if grid is None else int(grid.bins),
    )
    cache[key] = out
    return out


def proxy_launch(proxy: Any, c2w: Tensor, *, want_grad: bool = False,
                 per_sample: bool = False) -> tuple[Tensor, Tensor | None]:
    """The kernels at poses [B, 4, 4] (float64 results): ψ [B] (or, ``per_sample``, the
    terms footprint × inside × visible [B, S]) and with ``want_grad`` dψ/d(rotation, centre)
    [B, 12] (rotation row-major, then the centre).

    Compiled for CUDA tensors; tensors elsewhere need Triton's interpreter (slow: for tests),
    which ``TRITON_INTERPRET=1`` in the environment turns on before Triton is first imported.
    """
    dev = c2w.device
    if dev.type != "cuda" and not _interpreting():
        raise ValueError(f"proxy_launch: the poses are on {dev}; the kernel runs on CUDA, or "
                         "anywhere under Triton's interpreter (TRITON_INTERPRET=1)")
    if proxy.grid is None and proxy.occluders is not None:
        raise ValueError("the point z-buffer visibility has no kernel")
    if proxy.rate is not None and proxy.rate.ndim == 2 and proxy.axes is None:
        raise ValueError("the directional form needs the samples' local axes")
    kin = _inputs(proxy, dev)
    kern = _kernels()
    f64 = torch.float64
    b = c2w.shape[0]
    s = int(kin["means"].shape[1])
    pose = c2w.detach().to(f64)
    cams = torch.cat([pose[:, :3, :3].reshape(b, 9), pose[:, :3, 3]], dim=1).contiguous()
    cells, bins = kin["cells"], kin["bins"]
    has_grid = kin["occ"] is not None
    if has_grid and b > 0:
        occ = kin["occ"]
        m = int(occ.shape[1])
        grid = torch.zeros(b, bins, cells, cells, dtype=f64, device=dev)
        if m > 0:
            kern.deposit_kernel[(b, _cdiv(m, OCC_BLOCK))](
                cams, kin["prm"], occ, kin["mass"], grid, m, cells, bins, BLOCK=OCC_BLOCK)
        cum = torch.empty(b, bins + 1, cells, cells, dtype=f64, device=dev)
        lanes = 1 << max(0, (cells * cells - 1).bit_length())
        kern.cumulate_kernel[(b,)](grid, cum, cells, bins, LANES=lanes)
    else:
        cum = torch.zeros(1, dtype=f64, device=dev)
    blocks = max(1, _cdiv(s, BLOCK))
    parts = max(1, min(blocks, PROGRAMS // max(b, 1)))
    chunk = _cdiv(blocks, parts) * BLOCK
    parts = max(1, _cdiv(s, chunk))
    part = torch.zeros(b, parts, 13, dtype=f64, device=dev)
    terms = torch.zeros(b, s, dtype=f64, device=dev) if per_sample else part
    if b > 0 and s > 0:
        kern.psi_kernel[(b, parts)](
            cams, kin["prm"], kin["means"], kin["sigma6"], kin["weight"], kin["rate"],
            kin["kinds"], kin["axes"], cum, part, terms, s, int(kin["rate"].shape[0]), chunk,
            cells, bins, MODE=_MODES[kin["mode"]], HAS_GRID=has_grid,
            WANT_GRAD=bool(want_grad and not per_sample), PER_SAMPLE=per_sample, BLOCK=BLOCK)
    if per_sample:
        return terms, None
    total = part.sum(1)  # [B, 13], the parts in a fixed order
    return total[:, 0], (total[:, 1:] if want_grad else None)


def _cdiv(a: int, b: int) -> int:
    return -(-a // b)


def _factor_sums(terms: Tensor, points: Tensor, centres: Tensor, axes: Tensor) -> Tensor:
    """The terms [B, S] times each direction factor of the samples ``points`` [S, 3] seen
    from ``centres`` [B, 3] (``anchor.proxy.direction_factors``: 1, 1 - d_k² per world axis,
    1 - (d · a_j)² per local axis of ``axes`` [S, 3, 3]), summed over the poses -> [S, 7]."""
    d = points.unsqueeze(0) - centres.unsqueeze(1)
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    c = torch.einsum("bsk,skj->bsj", d, axes)
    f = torch.cat([torch.ones_like(d[..., :1]), 1.0 - d * d, 1.0 - c * c], dim=-1)
    return (terms.unsqueeze(-1) * f).sum(0)


def proxy_kernel(proxy: Any, c2w: Tensor, want_grad: bool, per_sample: bool = False,
                 axes: Tensor | None = None, between: Callable[[], None] | None = None
                 ) -> tuple[Tensor, Tensor | None]:
    """What :meth:`ProxyPsi._kernel` returns, by the Triton kernels, every pose at once
    (``between()``, the cancellation check, once before): ψ [B] (or the per-sample terms
    [B, S]) in the poses' dtype and, with ``want_grad``, dψ/dc2w [B, 4, 4] (zero in the last
    row); with ``per_sample`` and ``axes`` [S, 3, 3], the terms and their sum over the poses
    times each direction factor [S, 7]."""
    if between is not None:
        between()
    dt, dev = c2w.dtype, c2w.device
    b = c2w.shape[0]
    val, grad = proxy_launch(proxy, c2w, want_grad=want_grad and not per_sample,
                             per_sample=per_sample)
    if per_sample:
        terms = val.to(dt)
        if axes is None:
            return terms, None
        return terms, _factor_sums(terms, proxy.means.to(dt), c2w.detach()[:, :3, 3],
                                   axes.to(dt))
    out = val.to(dt)
    if grad is None:
        return out, None
    g = torch.zeros(b, 4, 4, dtype=dt, device=dev)
    g[:, :3, :3] = grad[:, :9].reshape(b, 3, 3).to(dt)
    g[:, :3, 3] = grad[:, 9:].to(dt)
    return out, g
