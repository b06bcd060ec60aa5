"""Exact diagonal Fisher information of a rendering, and the information maths built on it.

``fisher_diag(gmap, camera)`` returns diag(JᵀJ), J the Jacobian of ``render(gmap, camera).rgb``
flattened (every pixel and channel one residual) with respect to each parameter block, in one
pass (paper eqs. hessian-def and diag-fisher). How:

1. Every parameter of Gaussian i reaches the image only through its screen-space attributes
   s_i = (mean2d [2], conic [3], opacity [1], colour [3]), so ∂C_pc/∂θ_i = g_pcᵀ (∂s_i/∂θ_i)
   with g_pc = ∂C_pc/∂s_i, and Σ_pc (∂C_pc/∂θ_ij)² = (∂s_i/∂θ_ij)ᵀ M_i (∂s_i/∂θ_ij) where
   M_i = Σ_pc g_pc g_pcᵀ is a 9x9 second-moment matrix per Gaussian.
2. g_pc has closed form: the colour entry is w = Tα on channel c, and the geometric entries are
   (∂C_c/∂α_i)·∂α/∂(mean2d, conic, opacity), where ∂α/∂· is α times a polynomial of degree ≤ 2
   in the pixel offset (dx, dy). So M_i = A_i Φ_i A_iᵀ with Φ_i the f-weighted outer products
   of the monomials φ = (1, dx, dy, dx², dxdy, dy²) summed over the Gaussian's composited
   pairs (one scatter-add over the rasterizer's pair list).
3. ∂s_i/∂θ_i (the projection Jacobian) comes from autograd on the per-Gaussian projection
   (one backward per screen attribute; Gaussians are independent, so summing over them and
   differentiating gives every Gaussian's own row).

Everything is plain torch, so the result is differentiable w.r.t. the camera pose (the
anchor ascends a function of it). ``fisher_diag_bruteforce`` is the slow reference: one
autograd backward per pixel and channel.

Information state Ĥ is a dict keyed by the field names, each the field's shape; it is
Σ_views H_v + λ (``init_information`` gives λ, ``accumulate_information`` adds a view).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Literal

import torch
from torch import Tensor

from agilegs.config.selection import FIELD_NAMES
from agilegs.service.nbv.camera import Camera, Intrinsics
from agilegs.service.nbv.gaussians import GaussianMap
from agilegs.service.nbv.kernels.backend import Backend, resolve
from agilegs.service.nbv.kernels.gpu import gpu_moments_apply, tile_moments
from agilegs.service.nbv.kernels.ops import kernel_fisher, kernel_jacobians, kernel_moments
from agilegs.service.nbv.projection import Projected, project_map
from agilegs.service.nbv.rasterize import (
    composite_pairs,
    dcolor_dalpha,
    pairs_of,
    render,
)

Residuals = Literal["channels", "pixels"]

def _screen_basis(con: Tensor, op: Tensor) -> Tensor:
    """A [.., 6, 6] with ∂α/∂(mx, my, a, b, c, o) = α · A φ, φ = (1, dx, dy, dx², dxdy, dy²)."""
    a, b, c = con.unbind(-1)
    z = torch.zeros_like(a)
    one = torch.ones_like(a)
    rows = [
        [z, a, b, z, z, z],
        [z, b, c, z, z, z],
        [z, z, z, -0.5 * one, z, z],
        [z, z, z, z, -one, z],
        [z, z, z, z, z, -0.5 * one],
        [1.0 / op.clamp_min(1e-30), z, z, z, z, z],
    ]
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def screen_second_moments(
    gmap: GaussianMap,
    camera: Camera,
    *,
    background: Tensor | None = None,
    tile_size: int = 8,
    near: float = 0.01,
    max_elements: int = 1 << 22,
    residuals: Residuals = "channels",
    backend: Backend | None = None,
) -> Tensor:
    """M_i = Σ_r g_r g_rᵀ over the screen attributes of every Gaussian [N, 9, 9].

    Attribute order: mean_x, mean_y, conic_a, conic_b, conic_c, opacity, r, g, b.
    ``residuals``: "channels" (every pixel and channel a residual r, g_r = ∂C_pc/∂s_i: the
    exact Fisher) or "pixels" (one residual per pixel, the channel sum: g_r = ∂(Σ_c C_pc)/∂s_i
    with the derivatives of α taken through its 0.99 clamp, as FisherRF's rasterizer does).
    Differentiable in whatever ``gmap`` and ``camera.c2w`` carry a graph for (then always by
    the torch path; otherwise by the compiled kernels where ``backend`` allows, see
    :mod:`agilegs.service.nbv.kernels.backend`).
    """
    if residuals not in ("channels", "pixels"):
        raise ValueError(f"residuals must be 'channels' or 'pixels', got {residuals!r}")
    dt, dev = gmap.means.dtype, gmap.means.device
    graph = torch.is_grad_enabled() and (
        bool(camera.c2w.requires_grad) or any(t.requires_grad for t in gmap.tensors().values()))
    if resolve(backend, [*gmap.tensors().values(), camera.c2w], pose_grad=graph):
        big_phi, c2, mcc = kernel_moments(gmap, camera, background=background,
                                          tile_size=tile_size, near=near, residuals=residuals)
        with torch.no_grad():
            proj = project_map(gmap, camera, near=near)
        return _assemble(big_phi.to(dt), c2.to(dt), mcc.to(dt), proj.conics, proj.opacities,
                         residuals)
    proj = project_map(gmap, camera, near=near)
    bg = (
        torch.zeros(3, dtype=dt, device=dev)
        if background is None
        else torch.as_tensor(background, dtype=dt, device=dev).reshape(3)
    )
    n = gmap.num_gaussians
    if not graph and gpu_moments_apply(backend, proj.means2d):
        sums = tile_moments(proj.means2d, proj.conics, proj.opacities, proj.colors, proj.cov2d,
                            proj.radii, proj.depths, camera.width, camera.height, background=bg,
                            tile_size=tile_size, residuals=residuals)
    else:
        sums = pair_moments(proj, camera.width, camera.height, bg, tile_size=tile_size,
                            max_elements=max_elements, residuals=residuals)
    big_phi = sums[:, :15][:, _PHI_OUTER.to(sums.device)].reshape(n, 6, 6)
    c2 = sums[:, 15:33].reshape(n, 3, 6)
    mcc = sums[:, 33]
    return _assemble(big_phi, c2, mcc, proj.conics, proj.opacities, residuals)


MONOMIALS: tuple[tuple[int, int], ...] = (
    (0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2),
    (3, 0), (2, 1), (1, 2), (0, 3), (4, 0), (3, 1), (2, 2), (1, 3), (0, 4),
)
"""The exponents (a, b) of dx^a dy^b for a + b <= 4; the first six are φ's entries."""
_PHI_OUTER = torch.tensor([
    MONOMIALS.index((MONOMIALS[i][0] + MONOMIALS[j][0], MONOMIALS[i][1] + MONOMIALS[j][1]))
    for i in range(6) for j in range(6)])
"""Entry (i, j) of φφᵀ [36] as an index into :data:`MONOMIALS`."""


def pair_moments(proj: Projected, width: int, height: int, bg: Tensor, *, tile_size: int = 8,
                 max_elements: int = 1 << 22, residuals: Residuals = "channels") -> Tensor:
    """The Fisher's per-Gaussian moments [N, 34] by listing the composited pairs (the torch
    reference; differentiable in whatever the projection carries a graph for): Σ f4·dx^a dy^b
    over :data:`MONOMIALS`, Σ f2 ⊗ φ channel-major, Σ w² (the layout of
    ``kernels.common.MOMENTS``)."""
    n = proj.means2d.shape[0]
    pairs = pairs_of(proj, width, height, tile_size, max_elements)
    # screen quantities: detached from the Gaussian parameters (their Jacobian is chained
    # separately) but still attached to the camera pose when it requires grad
    col = proj.colors
    t = composite_pairs(pairs, proj.means2d, proj.conics, proj.opacities, col, proj.depths, bg)
    dcda = dcolor_dalpha(pairs, t, col, bg)  # [Q, 3]
    w = t.weight
    if residuals == "channels":
        al = torch.where(t.raw_ok, t.alpha, torch.zeros_like(t.alpha))
        f4 = (dcda * dcda).sum(-1) * al * al  # [Q]
        f2 = dcda * (w * al)[:, None]  # [Q, 3]
    else:
        al = t.raw  # ∂α/∂screen of o·G whether or not α was clamped at 0.99
        dsum = dcda.sum(-1)
        f4 = dsum * dsum * al * al
        f2 = (dsum * w * al)[:, None].expand(-1, 3)
    dx, dy = t.dx, t.dy
    # φφᵀ holds 15 distinct monomials dx^a dy^b (a + b <= 4): sum those, not its 36 entries
    px = [torch.ones_like(dx), dx, dx * dx]
    py = [torch.ones_like(dy), dy, dy * dy]
    px += [px[2] * dx, px[2] * px[2]]
    py += [py[2] * dy, py[2] * py[2]]
    mono = torch.stack([px[a] * py[b] for a, b in MONOMIALS], dim=1)  # [Q, 15]
    phi = mono[:, :6]  # (1, dx, dy, dx², dxdy, dy²) [Q, 6]
    per_pair = torch.cat([f4[:, None] * mono, (f2[:, :, None] * phi[:, None, :]).reshape(-1, 18),
                          (w * w)[:, None]], dim=1)  # [Q, 34]
    return per_gaussian_sums(pairs.gauss, per_pair, n)  # [N, 34]


Reduction = Literal["auto", "index_add", "segments"]


def per_gaussian_sums(gauss: Tensor, values: Tensor, n: int, *,
                      how: Reduction = "auto") -> Tensor:
    """Σ over the pairs of each Gaussian: values [Q, C] summed by ``gauss`` [Q] into [n, C].

    ``"index_add"`` scatters with additions (the CPU's way); ``"segments"`` sorts the pairs by
    Gaussian and sums each Gaussian's run (no atomic additions: on a GPU the many pairs of
    one Gaussian would otherwise contend for the same addresses); ``"auto"``: segments on
    CUDA unless ``values`` carries a graph, index_add elsewhere. Both give the same sums up to
    the order of the additions.
    """
    if how == "auto":
        how = "segments" if values.is_cuda and not values.requires_grad else "index_add"
    if how == "index_add":
        return torch.zeros(n, values.shape[1], dtype=values.dtype,
                           device=values.device).index_add(0, gauss, values)
    if how != "segments":
        raise ValueError(f"how must be auto, index_add or segments, got {how!r}")
    order = torch.argsort(gauss, stable=True)
    lengths = torch.bincount(gauss, minlength=n)
    return torch.segment_reduce(values.index_select(0, order), "sum", lengths=lengths, axis=0,
                                unsafe=True)


def _assemble(big_phi: Tensor, c2: Tensor, mcc: Tensor, conics: Tensor, opacities: Tensor,
              residuals: Residuals) -> Tensor:
    """M [N, 9, 9] from Φ [N, 6, 6], C2 [N, 3, 6] and Σ w² [N] (see the module docstring)."""
    dt, dev = big_phi.dtype, big_phi.device
    amat = _screen_basis(conics, opacities)  # [N, 6, 6]
    mgg = amat @ big_phi @ amat.transpose(-1, -2)
    mgc = c2 @ amat.transpose(-1, -2)  # [N, 3, 6]
    top = torch.cat([mgg, mgc.transpose(1, 2)], dim=2)  # [N, 6, 9]
    # colour block: Σ w² on the diagonal (one residual per channel), or in every entry
    # (the three channels of a pixel are one residual)
    pattern = (torch.eye(3, dtype=dt, device=dev) if residuals == "channels"
               else torch.ones(3, 3, dtype=dt, device=dev))
    bottom = torch.cat([mgc, mcc[:, None, None] * pattern], dim=2)  # [N, 3, 9]
    return torch.cat([top, bottom], dim=1)


def _screen_outputs(p: Projected) -> list[Tensor]:
    return [
        p.means2d[:, 0],
        p.means2d[:, 1],
        p.conics[:, 0],
        p.conics[:, 1],
        p.conics[:, 2],
        p.opacities,
        p.colors[:, 0],
        p.colors[:, 1],
        p.colors[:, 2],
    ]


def fisher_diag(
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
    """Exact diag(JᵀJ) of the rendered RGB w.r.t. each parameter block, in one pass.

    Args:
        gmap: the Gaussians (N).
        camera: the view; if ``camera.c2w`` requires grad the result is differentiable in it
            (twice: the torch path).
        background: background colour [3] used by the render (default black).
        fields: which blocks to return (default all five).
        tile_size, near, max_elements: as in :func:`render`.
        backend: "auto", "numba" or "torch" (:mod:`agilegs.service.nbv.kernels.backend`); the
        kernels
            serve every call whose pose does not require grad.

    Returns:
        {field name: diag Fisher of that field, same shape as the field}.
    """
    want = _check_fields(fields, FIELD_NAMES)
    pose_grad = bool(camera.c2w.requires_grad) and torch.is_grad_enabled()
    if resolve(backend, [*gmap.tensors().values(), camera.c2w], pose_grad=pose_grad):
        return kernel_fisher(gmap, camera, want, background=background, tile_size=tile_size,
                             near=near)
    with torch.set_grad_enabled(pose_grad):
        m = screen_second_moments(
            gmap.detach(),
            camera,
            background=background,
            tile_size=tile_size,
            near=near,
            max_elements=max_elements,
            backend=backend,
        )
    jac = projection_jacobians(gmap, camera, want, near=near, create_graph=pose_grad,
                               backend="torch")
    result: dict[str, Tensor] = {}
    for f in want:
        h = jacobian_sandwich(jac[f], m)
        shape = getattr(gmap, f).shape
        result[f] = h.reshape(shape) if pose_grad else h.reshape(shape).detach()
    return result


def jacobian_sandwich(j: Tensor, m: Tensor) -> Tensor:
    """diag(Jᵀ M J) per Gaussian: J [N, 9, P], M [N, 9, 9] -> [N, P]."""
    return (torch.bmm(m, j) * j).sum(1)


def _check_fields(fields: Iterable[str] | None, known: tuple[str, ...]) -> tuple[str, ...]:
    want = tuple(known if fields is None else fields)
    for f in want:
        if f not in known:
            raise ValueError(f"fields: unknown parameter block {f!r} (known: {known})")
    return want


def projection_jacobians(
    gmap: GaussianMap,
    camera: Camera,
    fields: tuple[str, ...],
    *,
    near: float = 0.01,
    create_graph: bool = False,
    backend: Backend | None = None,
) -> dict[str, Tensor]:
    """∂s_i/∂θ_i of every Gaussian's 9 screen attributes w.r.t. its own parameters.

    Returns {field: [N, 9, P_f]} (P_f the field's entries per Gaussian). The torch path: one
    backward per screen attribute (each Gaussian's attributes depend on its own parameters
    only, so the gradient of Σ_i s_i,a w.r.t. θ holds every Gaussian's own row); the kernels:
    the closed-form Jacobian (not differentiable, so never with ``create_graph`` or a pose
    that requires grad).
    """
    graph = create_graph or (bool(camera.c2w.requires_grad) and torch.is_grad_enabled())
    if resolve(backend, [*gmap.tensors().values(), camera.c2w], pose_grad=graph):
        return kernel_jacobians(gmap, camera, fields, near=near)
    leaves = {k: v.requires_grad_(True) for k, v in gmap.detach().items()}
    jac: dict[str, list[Tensor]] = {f: [] for f in fields}
    with torch.enable_grad():
        proj = project_map(GaussianMap(**leaves), camera, near=near)
        wanted_leaves = [leaves[f] for f in fields]
        for out in _screen_outputs(proj):
            grads = torch.autograd.grad(
                out.sum(),
                wanted_leaves,
                create_graph=create_graph,
                retain_graph=True,
                allow_unused=True,
            )
            for f, g in zip(fields, grads):
                shape = (leaves[f].shape[0], math.prod(leaves[f].shape[1:]))
                jac[f].append(
                    torch.zeros_like(leaves[f]).reshape(shape) if g is None else g.reshape(shape)
                )
    return {f: torch.stack(jac[f], dim=1) for f in fields}


def fisher_diag_bruteforce(
    gmap: GaussianMap,
    camera: Camera,
    *,
    background: Tensor | None = None,
    tile_size: int = 8,
) -> dict[str, Tensor]:
    """Reference: diag(JᵀJ) from one autograd backward per pixel and channel (slow)."""
    leaves = {k: v.detach().clone().requires_grad_(True) for k, v in gmap.items()}
    g = GaussianMap(**leaves)
    rgb = render(g, camera, background=background, tile_size=tile_size, backward="autograd").rgb
    flat = rgb.reshape(-1)
    acc = {k: torch.zeros_like(v) for k, v in leaves.items()}
    names = list(leaves)
    for i in range(flat.numel()):
        if not flat[i].requires_grad:
            continue
        grads = torch.autograd.grad(flat[i], [leaves[k] for k in names], retain_graph=True)
        for k, gr in zip(names, grads):
            acc[k] += gr * gr
    return acc


def eig_scores(
    gmap: GaussianMap,
    h_acc: Mapping[str, Tensor],
    poses: Tensor,
    intrinsics: Intrinsics,
    *,
    fields: tuple[str, ...] = FIELD_NAMES,
    background: Tensor | None = None,
) -> Tensor:
    """phi(v) = sum_q log(1 + H_v,qq / Hhat_qq) for every pose [V, 4, 4] -> [V].

    One exact ``fisher_diag`` pass per view, only for the blocks in ``fields``; 1 / Hhat is
    formed once and each view's Fisher is turned into its log1p-sum in place (no copies).
    """
    g = gmap.detach()
    inv = {f: h_acc[f].detach().to(g.dtype).reciprocal() for f in fields}
    out = torch.empty(poses.shape[0], dtype=torch.float64)
    with torch.no_grad():
        for i, pose in enumerate(poses.detach().to(g.dtype)):
            h = fisher_diag(
                g, Camera(c2w=pose, intrinsics=intrinsics), fields=fields, background=background
            )
            total = 0.0
            for f in fields:
                total += float(h[f].mul_(inv[f]).log1p_().sum(dtype=torch.float64))
            out[i] = total
    return out


# ----------------------------------------------------------------------------- information maths
def init_information(gmap: GaussianMap, lam: float = 1e-6) -> dict[str, Tensor]:
    """λI as a per-field dict (the prior term of Ĥ)."""
    if not lam > 0:
        raise ValueError(f"lam must be > 0, got {lam}")
    return {k: torch.full_like(v.detach(), lam) for k, v in gmap.items()}


def accumulate_information(
    h_acc: Mapping[str, Tensor], h_view: Mapping[str, Tensor]
) -> dict[str, Tensor]:
    """Ĥ + H_v, field by field (shapes must match)."""
    out = {}
    for k, v in h_acc.items():
        if k not in h_view:
            raise ValueError(f"h_view is missing field {k!r}")
        if h_view[k].shape != v.shape:
            raise ValueError(
                f"h_view[{k!r}] has shape {list(h_view[k].shape)}, h_acc has {list(v.shape)}"
            )
        out[k] = v + h_view[k].detach().to(v.dtype)
    return out


def _field_terms(
    h_view: Mapping[str, Tensor],
    h_acc: Mapping[str, Tensor],
    fields: Iterable[str] | None,
    fn: str,
) -> Tensor:
    names = list(h_acc) if fields is None else list(fields)
    total: Tensor | None = None
    for k in names:
        if k not in h_acc or k not in h_view:
            raise ValueError(f"fields: {k!r} missing from h_view or h_acc")
        hv, ha = h_view[k], h_acc[k]
        extra = hv.ndim - ha.ndim
        if extra < 0 or tuple(hv.shape[extra:]) != tuple(ha.shape):
            raise ValueError(
                f"h_view[{k!r}] shape {list(hv.shape)} does not end with h_acc shape "
                f"{list(ha.shape)}"
            )
        ratio = hv / ha
        term = torch.log1p(ratio) if fn == "eig" else ratio
        s = term.reshape(*hv.shape[:extra], -1).sum(-1)
        total = s if total is None else total + s
    if total is None:
        raise ValueError("fields: no parameter block selected")
    return total


def expected_information_gain(
    h_view: Mapping[str, Tensor],
    h_acc: Mapping[str, Tensor],
    fields: Iterable[str] | None = None,
) -> Tensor:
    """φ = Σ_q log(1 + H_v,qq / Ĥ_qq) (paper eq. plus_diagonal).

    Args:
        h_view: per-field diagonal Fisher of the view(s); each may carry leading batch dims
            [V, *field_shape] to score many views at once.
        h_acc: accumulated information Ĥ (including λ), per field [*field_shape].
        fields: blocks to include (default: every block of h_acc).

    Returns:
        EIG, a scalar tensor or [V].
    """
    return _field_terms(h_view, h_acc, fields, "eig")


def trace_surrogate(
    h_view: Mapping[str, Tensor],
    h_acc: Mapping[str, Tensor],
    fields: Iterable[str] | None = None,
) -> Tensor:
    """ψ = Σ_q H_v,qq / Ĥ_qq = tr(H_v Ĥ⁻¹) (paper eq. trace-surrogate); batched like the EIG."""
    return _field_terms(h_view, h_acc, fields, "trace")


__all__ = [
    "accumulate_information",
    "eig_scores",
    "expected_information_gain",
    "fisher_diag",
    "fisher_diag_bruteforce",
    "init_information",
    "jacobian_sandwich",
    "projection_jacobians",
    "screen_second_moments",
    "trace_surrogate",
]
