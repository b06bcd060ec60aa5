"""The compiled kernels behind torch: autograd functions for the projection and the
compositing, and the one-pass Fisher, over :mod:`agilegs.service.nbv.kernels` (which path
serves a call is :mod:`agilegs.service.nbv.kernels.backend`'s choice: these functions assume the
kernels apply).

Every call holds the backend's lock while it uses the shared scratch buffers and runs each
kernel in parts on the backend's threads.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
import torch
from torch import Tensor

from agilegs.config.selection import FIELD_NAMES
from agilegs.service.nbv.camera import Camera
from agilegs.service.nbv.gaussians import GaussianMap
from agilegs.service.nbv.kernels.backend import (
    LOCK,
    WORKSPACE,
    as_numpy,
    camera_vector,
    kernel_threads,
    load_kernels,
    map_arrays,
    parallel,
    pixel_centres,
    scalars,
)
from agilegs.service.nbv.projection import Projected

__all__ = [
    "kernel_composite",
    "kernel_fisher",
    "kernel_jacobians",
    "kernel_moments",
    "kernel_project",
]


# ----------------------------------------------------------------------------- projection
class _ProjectFn(torch.autograd.Function):
    """The kernels' projection with its analytic vector-Jacobian product."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any, means: Tensor, log_scales: Tensor, quats: Tensor, logits: Tensor, sh: Tensor,
        cam: np.ndarray,
    ) -> tuple[Tensor, ...]:
        k = load_kernels()
        arrs = tuple(as_numpy(t) for t in (means, log_scales, quats, logits, sh))
        n = means.shape[0]
        dt = means.dtype
        m2 = torch.empty(n, 2, dtype=dt)
        con = torch.empty(n, 3, dtype=dt)
        z = torch.empty(n, dtype=dt)
        radii = torch.empty(n, dtype=torch.int64)
        col = torch.empty(n, 3, dtype=dt)
        op = torch.empty(n, dtype=dt)
        cov = torch.empty(n, 3, dtype=dt)
        if n:
            outs = (m2.numpy(), con.numpy(), z.numpy(), radii.numpy(), col.numpy(), op.numpy(),
                    cov.numpy())
            with LOCK:
                nth = kernel_threads()
                parallel(lambda part: k.project(*arrs, cam, part, nth, *outs), nth)
        ctx.arrs = arrs
        ctx.cam = cam
        ctx.mark_non_differentiable(radii, cov)
        return m2, con, z, col, op, radii, cov

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(  # type: ignore[override]
        ctx: Any, g_m2: Tensor | None, g_con: Tensor | None, g_z: Tensor | None,
        g_col: Tensor | None, g_op: Tensor | None, _g_radii: Any, _g_cov: Any,
    ) -> tuple[Tensor | None, ...]:
        k = load_kernels()
        means, log_scales, quats, logits, sh = ctx.arrs
        n = means.shape[0]
        dt = torch.float32 if means.dtype == np.float32 else torch.float64
        gs = torch.zeros(n, 10, dtype=dt)
        if g_m2 is not None:
            gs[:, 0:2] = g_m2
        if g_con is not None:
            gs[:, 2:5] = g_con
        if g_op is not None:
            gs[:, 5] = g_op
        if g_col is not None:
            gs[:, 6:9] = g_col
        if g_z is not None:
            gs[:, 9] = g_z
        outs = [torch.zeros(a.shape, dtype=dt) for a in ctx.arrs]
        if n:
            gsn = gs.numpy()
            outn = [o.numpy() for o in outs]
            with LOCK:
                nth = kernel_threads()
                parallel(lambda part: k.project_backward(*ctx.arrs, ctx.cam, part, nth, gsn,
                                                          *outn), nth)
        return (*outs, None)


def kernel_project(gmap: GaussianMap, camera: Camera, *, near: float = 0.01) -> Projected:
    """:func:`~agilegs.service.nbv.projection.project_map` by the kernels (differentiable in
    the Gaussians; not in the pose)."""
    cam = camera_vector(camera, gmap.dtype, near)
    m2, con, z, col, op, radii, cov = _ProjectFn.apply(
        gmap.means, gmap.log_scales, gmap.quats, gmap.opacity_logits, gmap.sh, cam)
    return Projected(means2d=m2, conics=con, depths=z, radii=radii, colors=col, opacities=op,
                     cov2d=cov)


# ----------------------------------------------------------------------------- binning
class _Tiles:
    """The depth-sorted visible Gaussians binned to tiles as records (numpy; see
    ``kernels.bin_count`` and ``kernels.bin_fill``). With ``scratch`` the arrays live in the
    workspace (valid until the next kernel call: only inside one locked call)."""

    def __init__(self, m2: np.ndarray, con: np.ndarray, op: np.ndarray, col: np.ndarray,
                 z: np.ndarray, radii: np.ndarray, cov: np.ndarray, width: int, height: int,
                 tile: int, *, scratch: bool = False) -> None:
        k = load_kernels()
        dt = m2.dtype
        n = m2.shape[0]
        nc = col.shape[1]

        def buf(name: str, shape: tuple[int, ...], dtype: Any, zero: bool = False
                ) -> np.ndarray:
            if scratch:
                return WORKSPACE.take("tiles." + name, shape, dtype, zero=zero)
            return np.zeros(shape, dtype) if zero else np.empty(shape, dtype)

        tiles_x = (width + tile - 1) // tile
        n_tiles = tiles_x * ((height + tile - 1) // tile)
        own = buf("own", (n, k.REC + nc + 5), dt)
        counts = np.zeros(n_tiles + 1, np.int64)
        areas = np.zeros(n_tiles + 1, np.int64)
        nvis = k.bin_count(m2, con, op, z, col, radii, radii.astype(dt), cov, width, height,
                           tile, dt.type(tile), own, counts, areas)
        bits = (z.view(np.uint32).astype(np.uint64) if dt == np.float32
                else z.view(np.uint64))
        self.order = np.empty(nvis, np.int64)
        k.visible_order(radii, bits, dt.itemsize, nvis, self.order)
        self.offsets = np.cumsum(counts)
        self.slots = np.cumsum(areas)
        m = int(self.offsets[-1])
        self.rec = buf("rec", (m, k.REC + nc), dt)
        self.rbox = buf("rbox", (m, 4), np.int32)
        self.rg = buf("rg", (m,), np.int32)
        self.ent_off = buf("ent_off", (nvis + 1,), np.int64)
        self.ent = buf("ent", (m,), np.int32)
        k.bin_fill(self.order, own, self.offsets, width, tile,
                   buf("sorted_own", (nvis, own.shape[1]), dt), self.rec, self.rbox, self.rg,
                   self.ent_off, self.ent)
        self.xs = pixel_centres(width, dt)
        self.ys = pixel_centres(height, dt)
        self.width, self.height, self.tile = width, height, tile
        self.channels = nc
        self.n = n

    @property
    def num_visible(self) -> int:
        return int(self.order.shape[0])

    def common(self) -> tuple[Any, ...]:
        return (self.offsets, self.rec, self.rbox, self.xs, self.ys, self.width, self.height,
                self.tile, *scalars(self.rec.dtype))

    def pair_buffers(self, record: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Slots for every tile's composited pairs (list position, tile pixel, α before the
        clamp), or empty ones when nothing is recorded."""
        size = int(self.slots[-1]) if record else 0
        return (np.empty(size, np.int32), np.empty(size, np.int32),
                np.empty(size, self.rec.dtype))

    def reduce(self, k: Any, per_entry: np.ndarray, out: np.ndarray, nth: int, *,
               compact: bool = False) -> np.ndarray:
        """Sum every visible Gaussian's entries' rows of per_entry into out: row g of out
        [N, K] (the other rows are left as they are), or with ``compact`` row v of out
        [V, K] in depth order."""
        if self.num_visible:
            target = np.arange(self.num_visible) if compact else self.order
            parallel(lambda part: k.reduce_entries(target, self.ent_off, self.ent, per_entry,
                                                    part, nth, out), nth)
        return out


# ----------------------------------------------------------------------------- compositing
class _CompositeFn(torch.autograd.Function):
    """Tile compositing by the kernels, with their backward."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any, means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor,
        depths: Tensor, bg: Tensor, radii: Tensor, cov2d: Tensor, width: int, height: int,
        tile: int,
    ) -> tuple[Tensor, Tensor, Tensor]:
        k = load_kernels()
        dt = colors.dtype
        hw = width * height
        nc = colors.shape[1]
        with LOCK:
            nth = kernel_threads()
            tiles = _Tiles(as_numpy(means2d), as_numpy(conics), as_numpy(opacities),
                           as_numpy(colors), as_numpy(depths), as_numpy(radii).astype(np.int64),
                           as_numpy(cov2d), width, height,
                           tile)
            acc = np.empty((hw, nc), dtype=tiles.rec.dtype)
            tf = np.empty(hw, dtype=np.float64)
            dacc = np.empty(hw, dtype=tiles.rec.dtype)
            record = any(ctx.needs_input_grad)
            pairs = tiles.pair_buffers(record)
            npairs = np.zeros(tiles.offsets.shape[0] - 1, dtype=np.int64)
            common = tiles.common()
            parallel(lambda part: k.composite_forward(*common, part, nth, tiles.slots, record,
                                                       *pairs, npairs, acc, tf, dacc), nth)
        t_final = torch.from_numpy(tf).to(dt)
        color = torch.from_numpy(acc) + t_final[:, None] * bg.detach()
        ctx.tiles = tiles
        ctx.tf = tf
        ctx.pairs = (*pairs, npairs)
        ctx.n = means2d.shape[0]
        ctx.save_for_backward(bg)
        return (color.reshape(height, width, nc), (1.0 - t_final).reshape(height, width),
                torch.from_numpy(dacc).reshape(height, width))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(  # type: ignore[override]
        ctx: Any, g_color: Tensor, g_alpha: Tensor, g_depth: Tensor
    ) -> tuple[Tensor | None, ...]:
        k = load_kernels()
        (bg,) = ctx.saved_tensors
        tiles: _Tiles = ctx.tiles
        dt = bg.dtype
        nc = tiles.channels
        hw = tiles.width * tiles.height
        g_c = g_color.reshape(hw, nc).to(dt).contiguous()
        g_a = g_alpha.reshape(hw).to(dt).contiguous()
        g_d = g_depth.reshape(hw).to(dt).contiguous()
        with LOCK:
            nth = kernel_threads()
            per_entry = np.zeros((tiles.rec.shape[0], 7 + nc), dtype=np.float64)
            common = tiles.common()
            args = (tiles.slots, *ctx.pairs, ctx.tf, as_numpy(bg), g_c.numpy(), g_a.numpy(),
                    g_d.numpy(), per_entry)
            parallel(lambda part: k.composite_backward(*common, part, nth, *args), nth)
            red = tiles.reduce(k, per_entry, np.zeros((ctx.n, 7 + nc), np.float64), nth)
        full = torch.from_numpy(red).to(dt)
        tf = torch.from_numpy(ctx.tf).to(dt)
        gbg = (tf[:, None] * g_c).sum(0)
        return (full[:, 0:2], full[:, 2:5], full[:, 5], full[:, 7:], full[:, 6], gbg,
                None, None, None, None, None)


def kernel_composite(proj: Projected, colors: Tensor, bg: Tensor, width: int, height: int,
                     tile_size: int) -> tuple[Tensor, Tensor, Tensor]:
    """Composite a projection by the kernels: colour [H, W, C] (background included),
    accumulated alpha [H, W], Σ w z [H, W]; differentiable in the screen attributes,
    ``colors`` [N, C] and ``bg`` [C]."""
    return _CompositeFn.apply(proj.means2d, proj.conics, proj.opacities, colors, proj.depths,
                              bg, proj.radii, proj.cov2d, int(width), int(height),
                              int(tile_size))


# ----------------------------------------------------------------------------- the Fisher
def _project_np(k: Any, arrs: tuple[np.ndarray, ...], cam: np.ndarray, nth: int,
                scratch: bool = False) -> tuple[np.ndarray, ...]:
    n = arrs[0].shape[0]
    dt = arrs[0].dtype

    def buf(name: str, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
        return (WORKSPACE.take("proj." + name, shape, dtype) if scratch
                else np.empty(shape, dtype))

    out = (buf("m2", (n, 2), dt), buf("con", (n, 3), dt), buf("z", (n,), dt),
           buf("radii", (n,), np.int64), buf("col", (n, 3), dt), buf("op", (n,), dt),
           buf("cov", (n, 3), dt))
    if n:
        parallel(lambda part: k.project(*arrs, cam, part, nth, *out), nth)
    return out


def _moments_np(k: Any, arrs: tuple[np.ndarray, ...], cam: np.ndarray, camera: Camera,
                bg: np.ndarray, tile: int, pixels: bool, nth: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """Project, bin and accumulate the Fisher's moments (in the workspace: valid inside the
    locked call only). Returns the visible Gaussians in depth order [V] and every Gaussian's
    moments [N, MOMENTS] (float64; the rows of Gaussians that are not visible undefined)."""
    m2, con, z, radii, col, op, cov = _project_np(k, arrs, cam, nth, scratch=True)
    tiles = _Tiles(m2, con, op, col, z, radii, cov, camera.width, camera.height, tile,
                   scratch=True)
    per_entry = WORKSPACE.take("fisher.entries", (tiles.rec.shape[0], k.MOMENTS),
                                tiles.rec.dtype, zero=True)
    mom = WORKSPACE.take("fisher.moments", (arrs[0].shape[0], k.MOMENTS), np.float64)
    if tiles.num_visible:
        common = tiles.common()
        parallel(lambda part: k.fisher_tiles(*common, part, nth, tiles.slots, bg, pixels,
                                              per_entry), nth)
        tiles.reduce(k, per_entry, mom, nth)
    return tiles.order, mom


def _background(background: Tensor | None, dtype: torch.dtype) -> np.ndarray:
    if background is None:
        return np.zeros(3, dtype=np.float64)
    return torch.as_tensor(background).detach().to(dtype).reshape(3).to(
        torch.float64).cpu().numpy()


def kernel_moments(gmap: GaussianMap, camera: Camera, *, background: Tensor | None = None,
                   tile_size: int = 8, near: float = 0.01, residuals: str = "channels"
                   ) -> tuple[Tensor, Tensor, Tensor]:
    """The Fisher's per-Gaussian moments by the kernels (float64; zero for Gaussians without a
    composited pair): Φ = Σ f4 φφᵀ [N, 6, 6], C2 = Σ f2 ⊗ φ [N, 3, 6] and Σ w² [N] (see
    ``kernels.fisher_tiles``)."""
    k = load_kernels()
    arrs = map_arrays(gmap)
    n = gmap.num_gaussians
    cam = camera_vector(camera, gmap.dtype, near)
    full = torch.zeros(n, k.MOMENTS, dtype=torch.float64)
    with LOCK:
        order, mom = _moments_np(k, arrs, cam, camera, _background(background, gmap.dtype),
                                 tile_size, residuals == "pixels", kernel_threads())
        idx = torch.from_numpy(order)
        full[idx] = torch.from_numpy(mom)[idx]
    phi = full[:, torch.from_numpy(k.PHI_INDEX).reshape(-1)].reshape(n, 6, 6)
    return phi, full[:, 15:33].reshape(n, 3, 6), full[:, 33]


def kernel_fisher(gmap: GaussianMap, camera: Camera, fields: Iterable[str], *,
                  background: Tensor | None = None, tile_size: int = 8, near: float = 0.01,
                  residuals: str = "channels") -> dict[str, Tensor]:
    """diag(Jᵀ M J) per parameter block by the kernels, in one pass (projection, binning, the
    tiles' moments, the analytic per-Gaussian Jacobian and the sandwich).

    Args:
        gmap: the Gaussians (N); camera: the view (its pose is not differentiated).
        fields: the blocks wanted (names of :data:`FIELD_NAMES`).
        residuals: "channels" (the exact Fisher of the RGB) or "pixels" (the channel sum one
            residual per pixel, α's derivatives through its clamp; FisherRF's).

    Returns:
        {field: the diagonal, the field's shape, the map's dtype}.
    """
    k = load_kernels()
    want_names = tuple(fields)
    arrs = map_arrays(gmap)
    dt = gmap.dtype
    want = np.array([f in want_names for f in FIELD_NAMES], dtype=np.bool_)
    cam = camera_vector(camera, dt, near)
    outs = {f: torch.zeros(getattr(gmap, f).shape, dtype=dt) for f in FIELD_NAMES}
    with LOCK:
        nth = kernel_threads()
        order, mom = _moments_np(k, arrs, cam, camera, _background(background, dt), tile_size,
                                 residuals == "pixels", nth)
        if order.shape[0]:
            hs = [outs[f].numpy() for f in FIELD_NAMES]
            pixels = residuals == "pixels"
            parallel(lambda part: k.fisher_chain(order, mom, *arrs, cam, part, nth, pixels,
                                                  want, *hs), nth)
    return {f: outs[f] for f in want_names}


def kernel_jacobians(gmap: GaussianMap, camera: Camera, fields: Iterable[str], *,
                     near: float = 0.01) -> dict[str, Tensor]:
    """∂s_i/∂θ_i of the 9 screen attributes by the kernels' analytic Jacobian: {field:
    [N, 9, P_f]} (the layout of :func:`~agilegs.service.nbv.information.projection_jacobians`)."""
    k = load_kernels()
    arrs = map_arrays(gmap)
    n = gmap.num_gaussians
    nk = gmap.sh.shape[1]
    dt = gmap.dtype
    cam = camera_vector(camera, dt, near)
    jac = np.zeros((n, 10, 11), dtype=np.float64)
    basis = np.zeros((n, max(nk, 1)), dtype=np.float64)
    mask = np.zeros((n, 3), dtype=np.float64)
    if n:
        with LOCK:
            nth = kernel_threads()
            parallel(lambda part: k.jacobians(*arrs, cam, part, nth, jac, basis, mask), nth)
    j = torch.from_numpy(jac).to(dt)
    out: dict[str, Tensor] = {}
    cols = {"means": (0, 3), "log_scales": (3, 6), "quats": (6, 10), "opacity_logits": (10, 11)}
    for f in fields:
        if f == "sh":
            sh_j = torch.zeros(n, 9, nk, 3, dtype=dt)
            b = torch.from_numpy(basis[:, :nk]).to(dt)
            mk = torch.from_numpy(mask).to(dt)
            for ch in range(3):
                sh_j[:, 6 + ch, :, ch] = b * mk[:, ch:ch + 1]
            out[f] = sh_j.reshape(n, 9, nk * 3)
        else:
            lo, hi = cols[f]
            out[f] = j[:, :9, lo:hi].contiguous()
    return out
