"""A differentiable Gaussian rasterizer in pure torch (CPU and CUDA alike), and ``render``.

On the CPU, :func:`render` hands the projection and the compositing to the compiled kernels
(:mod:`agilegs.service.nbv.kernels.backend`, :mod:`agilegs.service.nbv.kernels`) wherever they
apply; the pure-torch code below is their reference, and serves everything else.

It follows the reference 3D Gaussian Splatting rasterizer (Kerbl et al. 2023). The
Gaussians are projected by :mod:`agilegs.service.nbv.projection` (EWA, low-pass, culling, SH
colour); then, with the reference's rules:

- a Gaussian reaches the pixels of every ``tile_size``² tile its square [u - r, u + r]
  overlaps (the reference binning), front to back in camera depth;
- per pixel: α = min(0.99, o·exp(-σ)); σ < 0 and α < 1/255 are skipped; compositing stops
  before the Gaussian that would bring the transmittance below 1e-4 (that Gaussian is not
  composited, as in the reference).

How: the (pixel, Gaussian) pairs that composite are listed explicitly (:func:`build_pairs`).
A Gaussian's candidate pixels are those of its binned tiles that also lie in the bounding box
of its α ≥ 1/255 ellipse (outside it no pixel can pass the 1/255 test, so the box changes
nothing), α is evaluated there and the pairs that pass are kept, sorted by pixel and depth,
and cut at each pixel's transmittance stop. Transmittances are exponentials of segmented
cumulative sums of log(1 - α) (in float64) along each pixel's pairs; colours, alpha and depth
are scatter-added per pixel. No padding: the work is proportional to the pairs that count.

Documented deviations: the background enters as C += T_final · bg (same as the reference);
``depth`` is the expected depth Σ w_i z_i / Σ w_i (0 where nothing was hit).

The compositing has two interchangeable implementations sharing one forward formula
(:func:`composite_pairs`): a plain autograd path (``backward="autograd"``, the slow obvious
reference, twice differentiable) and a custom ``torch.autograd.Function`` whose backward
applies the closed-form derivatives to the forward's saved per-pair terms
(``backward="analytic"``, default). Tests check one against the other and against a
per-pixel loop.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import torch
from torch import Tensor

from agilegs.service.nbv.camera import Camera
from agilegs.service.nbv.gaussians import GaussianMap
from agilegs.service.nbv.kernels.backend import Backend, resolve
from agilegs.service.nbv.kernels.ops import kernel_composite, kernel_project
from agilegs.service.nbv.projection import Projected, project_map

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4

BackwardMode = Literal["analytic", "autograd"]


@dataclass
class RenderResult:
    """Output of :func:`render`.

    Attributes:
        rgb: composited colour [H, W, 3].
        alpha: accumulated opacity 1 - T_final [H, W].
        depth: expected depth Σ w z / Σ w [H, W] (0 where alpha is 0).
        features: composited per-Gaussian features [H, W, C] when ``features`` was given.
        means2d: screen-space centres [N, 2] (call ``retain_grad()`` before backward to read
            the screen-space gradient used for densification).
        radii: screen radius in pixels [N], 0 for culled Gaussians.
        depths: camera-space depth of every Gaussian [N].
    """

    rgb: Tensor
    alpha: Tensor
    depth: Tensor
    features: Tensor | None
    means2d: Tensor
    radii: Tensor
    depths: Tensor


# ----------------------------------------------------------------------------- pairs
@dataclass
class Pairs:
    """The (pixel, Gaussian) pairs that composite, sorted by pixel, front to back in each.

    Attributes:
        gauss: Gaussian index of each pair [Q].
        pix: flat pixel index (y * width + x) of each pair [Q].
        first: index of the first pair of each pair's pixel [Q].
        width, height: image size.
    """

    gauss: Tensor
    pix: Tensor
    first: Tensor
    width: int
    height: int

    @property
    def num_pixels(self) -> int:
        return self.width * self.height

    def __len__(self) -> int:
        return int(self.gauss.numel())


def _pair_alpha(px: Tensor, py: Tensor, m2d: Tensor, con: Tensor, op: Tensor
                ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """dx, dy, σ and the unclamped α = o·exp(-σ) of pairs (pixel centres px, py; attributes
    already gathered per pair)."""
    dx = px - m2d[:, 0]
    dy = py - m2d[:, 1]
    sigma = 0.5 * (con[:, 0] * dx * dx + con[:, 2] * dy * dy) + con[:, 1] * dx * dy
    return dx, dy, sigma, op * torch.exp(-sigma)


def _segment_cumsum(values: Tensor, first: Tensor) -> Tensor:
    """Inclusive cumulative sums of ``values`` [Q] within each pixel's run (float64)."""
    v = values.to(torch.float64)
    cs = torch.cumsum(v, 0)
    return cs - (cs[first] - v[first])


@torch.no_grad()
def pixel_boxes(means2d: Tensor, opacities: Tensor, cov2d: Tensor, radii: Tensor, depths: Tensor,
                width: int, height: int, tile_size: int = 8
                ) -> tuple[Tensor, tuple[Tensor, Tensor, Tensor, Tensor]]:
    """The visible Gaussians (radius > 0) front to back (a stable sort of the depths) [V], and
    each one's pixel box x0, x1, y0, y1 (inclusive, int64 [V] each; empty: x1 < x0 or y1 < y0):
    the box of its α ≥ 1/255 ellipse within the tiles its square [m ± r] is binned to."""
    vis = torch.nonzero(radii > 0).flatten()
    vis = vis[torch.argsort(depths.detach()[vis], stable=True)]  # front to back
    m = means2d.detach()[vis]
    r = radii[vis].to(m.dtype)
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    # the binned tiles' pixels: the tiles the square [m - r, m + r] overlaps (clamped)
    tx0 = torch.clamp(torch.floor((m[:, 0] - r) / tile_size), 0, tiles_x - 1)
    tx1 = torch.clamp(torch.floor((m[:, 0] + r) / tile_size), 0, tiles_x - 1)
    ty0 = torch.clamp(torch.floor((m[:, 1] - r) / tile_size), 0, tiles_y - 1)
    ty1 = torch.clamp(torch.floor((m[:, 1] + r) / tile_size), 0, tiles_y - 1)
    x_lo, x_hi = tx0 * tile_size, torch.clamp((tx1 + 1) * tile_size, max=width) - 1
    y_lo, y_hi = ty0 * tile_size, torch.clamp((ty1 + 1) * tile_size, max=height) - 1
    # the bounding box of the ellipse α >= 1/255 (half-widths sqrt(k Σ_aa), k = 2 ln(255 o));
    # widened by a hair so that rounding never drops a pixel the test would keep
    op = opacities.detach()[vis].to(m.dtype)
    k = 2.0 * torch.log(torch.clamp(op / ALPHA_MIN, min=1.0))
    cov = cov2d.detach()[vis].to(m.dtype)
    hx = torch.sqrt(k * cov[:, 0].clamp_min(0)) * (1 + 1e-6) + 1e-3
    hy = torch.sqrt(k * cov[:, 2].clamp_min(0)) * (1 + 1e-6) + 1e-3
    x0 = torch.maximum(x_lo, torch.ceil(m[:, 0] - hx - 0.5)).long()
    x1 = torch.minimum(x_hi, torch.floor(m[:, 0] + hx - 0.5)).long()
    y0 = torch.maximum(y_lo, torch.ceil(m[:, 1] - hy - 0.5)).long()
    y1 = torch.minimum(y_hi, torch.floor(m[:, 1] + hy - 0.5)).long()
    return vis, (x0, x1, y0, y1)


@torch.no_grad()
def build_pairs(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    cov2d: Tensor,
    radii: Tensor,
    depths: Tensor,
    width: int,
    height: int,
    tile_size: int = 8,
    max_elements: int = 1 << 22,
) -> Pairs:
    """List the pairs that composite (see the module docstring). ``max_elements`` bounds the
    candidate pairs evaluated at once (memory)."""
    dev = means2d.device
    empty = torch.zeros(0, dtype=torch.long, device=dev)
    vis, (x0, x1, y0, y1) = pixel_boxes(means2d, opacities, cov2d, radii, depths, width,
                                         height, tile_size)
    if vis.numel() == 0:
        return Pairs(empty, empty, empty, width, height)
    m = means2d.detach()[vis]
    op = opacities.detach()[vis].to(m.dtype)
    nx = (x1 - x0 + 1).clamp_min(0)
    ny = (y1 - y0 + 1).clamp_min(0)
    counts = nx * ny
    con_all = conics.detach()[vis].to(m.dtype)
    attrs = torch.cat([m, con_all, op[:, None]], dim=1)  # one gather per candidate
    ints = torch.stack([x0, y0, nx], dim=1)
    keep_g: list[Tensor] = []
    keep_p: list[Tensor] = []
    keep_a: list[Tensor] = []
    csum = torch.cumsum(counts, 0)
    start = 0
    n = vis.numel()
    while start < n:
        # Gaussians [start, end) whose candidates fit in max_elements (at least one)
        base = int(csum[start - 1]) if start else 0
        end = int(torch.searchsorted(csum, base + max_elements, right=True))
        end = max(end, start + 1)
        cnt = counts[start:end]
        total = int(cnt.sum())
        if total:
            owner = torch.repeat_interleave(torch.arange(start, end, device=dev), cnt)
            off = torch.cumsum(cnt, 0) - cnt
            local = torch.arange(total, device=dev) - off[owner - start]
            oi = ints.index_select(0, owner)
            px = oi[:, 0] + local % oi[:, 2]
            py = oi[:, 1] + torch.div(local, oi[:, 2], rounding_mode="floor")
            at = attrs.index_select(0, owner)
            _, _, sigma, raw = _pair_alpha(px.to(m.dtype) + 0.5, py.to(m.dtype) + 0.5,
                                           at[:, 0:2], at[:, 2:5], at[:, 5])
            ok = (sigma >= 0) & (raw >= ALPHA_MIN)
            keep_g.append(owner[ok])
            keep_p.append((py * width + px)[ok])
            keep_a.append(raw[ok])
        start = end
    if not keep_g:
        return Pairs(empty, empty, empty, width, height)
    pix = torch.cat(keep_p)
    order = torch.argsort(pix, stable=True)  # stable: front to back within a pixel
    pix = pix[order]
    gid = torch.cat(keep_g)[order]
    alpha = torch.clamp_max(torch.cat(keep_a)[order], ALPHA_MAX)
    first = _first_of_runs(pix)
    # the transmittance stop: keep each pixel's pairs while T stays >= T_MIN
    t_incl = torch.exp(_segment_cumsum(torch.log1p(-alpha.to(torch.float64)), first))
    live = t_incl >= T_MIN
    if not bool(live.all()):
        pix, gid = pix[live], gid[live]
        first = _first_of_runs(pix)
    return Pairs(vis[gid], pix, first, width, height)


def _first_of_runs(pix: Tensor) -> Tensor:
    """For sorted keys [Q], the index of the first element of each element's run."""
    if pix.numel() == 0:
        return pix.clone()
    new = torch.ones_like(pix, dtype=torch.bool)
    new[1:] = pix[1:] != pix[:-1]
    starts = torch.nonzero(new).flatten()
    run = torch.cumsum(new.long(), 0) - 1
    return starts[run]


# ----------------------------------------------------------------------------- compositing
@dataclass
class PairTerms:
    """Per-pair terms of the compositing ([Q] unless noted)."""

    dx: Tensor  # pixel centre minus the Gaussian's centre
    dy: Tensor
    raw: Tensor  # o·exp(-σ), unclamped
    alpha: Tensor  # min(0.99, raw)
    raw_ok: Tensor  # bool: α not clamped (derivatives flow)
    trans: Tensor  # transmittance in front of the pair
    weight: Tensor  # trans * alpha
    t_final: Tensor  # [HW]
    color: Tensor  # [HW, C] (background included)
    depth_acc: Tensor  # [HW]  Σ w z


def composite_pairs(
    pairs: Pairs,
    m2d: Tensor,
    con: Tensor,
    op: Tensor,
    col: Tensor,
    z: Tensor,
    bg: Tensor,
) -> PairTerms:
    """Front-to-back compositing of the pairs (plain torch, differentiable).

    Args:
        pairs: from :func:`build_pairs`.
        m2d: screen centres [N, 2]; con: conics [N, 3]; op: opacities [N]; col: colours or
            features [N, C]; z: depths [N]; bg: background [C].
    """
    dt = col.dtype
    g = pairs.gauss
    w_img = pairs.width
    px = (pairs.pix % w_img).to(dt) + 0.5
    py = torch.div(pairs.pix, w_img, rounding_mode="floor").to(dt) + 0.5
    dx, dy, _, raw = _pair_alpha(px, py, m2d[g], con[g], op[g])
    alpha = torch.clamp_max(raw, ALPHA_MAX)
    with torch.no_grad():
        raw_ok = raw <= ALPHA_MAX
    lg = torch.log1p(-alpha.to(torch.float64))
    incl = _segment_cumsum(lg, pairs.first)
    trans = torch.exp(incl - lg).to(dt)
    weight = trans * alpha
    hw = pairs.num_pixels
    log_final = torch.zeros(hw, dtype=torch.float64, device=col.device).index_add(0, pairs.pix, lg)
    t_final = torch.exp(log_final).to(dt)
    color = torch.zeros(hw, col.shape[1], dtype=dt, device=col.device).index_add(
        0, pairs.pix, weight[:, None] * col[g]) + t_final[:, None] * bg
    depth_acc = torch.zeros(hw, dtype=dt, device=col.device).index_add(0, pairs.pix, weight * z[g])
    return PairTerms(dx, dy, raw, alpha, raw_ok, trans, weight, t_final, color, depth_acc)


def dcolor_dalpha(pairs: Pairs, terms: PairTerms, col: Tensor, bg: Tensor) -> Tensor:
    """∂C_c/∂α_i = T_i c_i - S_i / (1 - α_i) per pair [Q, C], S_i the colour composited
    behind pair i (later pairs of its pixel, and the background)."""
    wc = terms.weight[:, None] * col[pairs.gauss]
    behind = _suffix(pairs, wc) + terms.t_final[pairs.pix, None] * bg
    return terms.trans[:, None] * col[pairs.gauss] - behind / (1.0 - terms.alpha)[:, None]


def _suffix(pairs: Pairs, values: Tensor) -> Tensor:
    """Σ over the later pairs of each pair's pixel, of ``values`` [Q] or [Q, C]."""
    squeeze = values.ndim == 1
    v = values[:, None] if squeeze else values
    v64 = v.to(torch.float64)
    cs = torch.cumsum(v64, 0)
    incl = cs - (cs[pairs.first] - v64[pairs.first])
    total = torch.zeros(pairs.num_pixels, v.shape[1], dtype=torch.float64,
                        device=v.device).index_add(0, pairs.pix, v64)
    out = (total[pairs.pix] - incl).to(values.dtype)
    return out[:, 0] if squeeze else out


class _Composite(torch.autograd.Function):
    """Compositing with a closed-form backward on the forward's per-pair terms."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        means2d: Tensor,
        conics: Tensor,
        opacities: Tensor,
        colors: Tensor,
        depths: Tensor,
        bg: Tensor,
        pairs: Pairs,
    ) -> tuple[Tensor, Tensor, Tensor]:
        t = composite_pairs(pairs, means2d, conics, opacities, colors, depths, bg)
        ctx.save_for_backward(conics, opacities, colors, depths, bg, t.dx, t.dy, t.alpha,
                              t.raw_ok, t.trans, t.t_final)
        ctx.pairs = pairs
        h, w = pairs.height, pairs.width
        return (t.color.reshape(h, w, -1), (1.0 - t.t_final).reshape(h, w),
                t.depth_acc.reshape(h, w))

    @staticmethod
    def backward(  # type: ignore[override]
        ctx: Any, g_color: Tensor, g_alpha: Tensor, g_depth: Tensor
    ) -> tuple[Tensor | None, ...]:
        (conics, opacities, colors, depths, bg, dx, dy, alpha, raw_ok, trans,
         t_final) = ctx.saved_tensors
        pairs: Pairs = ctx.pairs
        n_ch = colors.shape[1]
        g = pairs.gauss
        g_c = g_color.reshape(-1, n_ch)
        g_a = g_alpha.reshape(-1)
        g_d = g_depth.reshape(-1)
        gc = g_c[pairs.pix]
        gd = g_d[pairs.pix]
        weight = trans * alpha
        col = colors[g]
        z = depths[g]
        # dC/dc_i = w_i ; dC/dbg = T_final ; dD_acc/dz_i = w_i
        gcol = torch.zeros_like(colors).index_add_(0, g, weight[:, None] * gc)
        gz = torch.zeros_like(depths).index_add_(0, g, weight * gd)
        gbg = (t_final[:, None] * g_c).sum(0)
        # dL/dα_i = T_i u_i - (Σ_{j>i} w_j u_j + T_final (bg·gC - gA)) / (1 - α_i)
        # with u_i = c_i·gC + z_i gD (colour, alpha and depth outputs in one pass)
        u = (col * gc).sum(-1) + gd * z
        tail = t_final * ((g_c * bg).sum(-1) - g_a)
        gal = trans * u - (_suffix(pairs, weight * u) + tail[pairs.pix]) / (1.0 - alpha)
        gp = torch.where(raw_ok, gal * alpha, torch.zeros_like(gal))
        con = conics[g]
        a, b, c = con[:, 0], con[:, 1], con[:, 2]
        gs = torch.stack([
            gp * (a * dx + b * dy),
            gp * (b * dx + c * dy),
            -0.5 * gp * dx * dx,
            -gp * dx * dy,
            -0.5 * gp * dy * dy,
            gp / opacities[g].clamp_min(1e-30),
        ], dim=1)
        acc = torch.zeros(conics.shape[0], 6, dtype=gs.dtype, device=gs.device).index_add_(0, g, gs)
        # dα/dmean = -dα/ddx: dσ/dmean_x = -(a dx + b dy), so dα/dmean_x = α (a dx + b dy)
        return acc[:, 0:2], acc[:, 2:5], acc[:, 5], gcol, gz, gbg, None


def composite(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    depths: Tensor,
    bg: Tensor,
    pairs: Pairs,
    *,
    backward: BackwardMode = "analytic",
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite the pairs into images.

    Returns:
        colour [H, W, C], accumulated alpha [H, W], expected depth [H, W].
    """
    h, w = pairs.height, pairs.width
    if backward == "analytic":
        out_c, out_a, out_dacc = _Composite.apply(
            means2d, conics, opacities, colors, depths, bg, pairs
        )
    elif backward == "autograd":
        t = composite_pairs(pairs, means2d, conics, opacities, colors, depths, bg)
        out_c = t.color.reshape(h, w, -1)
        out_a = (1.0 - t.t_final).reshape(h, w)
        out_dacc = t.depth_acc.reshape(h, w)
    else:
        raise ValueError(f"backward must be 'analytic' or 'autograd', got {backward!r}")
    return out_c, out_a, expected_depth(out_a, out_dacc)


def expected_depth(alpha: Tensor, depth_acc: Tensor) -> Tensor:
    """Σ w z / Σ w from the accumulated alpha [H, W] and Σ w z [H, W] (0 where alpha is 0)."""
    has = alpha > 0
    return torch.where(has, depth_acc / torch.where(has, alpha, torch.ones_like(alpha)), 0.0)


def _check_inputs(gmap: GaussianMap, camera: Camera) -> None:
    if not isinstance(gmap, GaussianMap):
        raise TypeError(f"gmap must be a GaussianMap, got {type(gmap).__name__}")
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a Camera, got {type(camera).__name__}")


def render(
    gmap: GaussianMap,
    camera: Camera,
    *,
    background: Tensor | None = None,
    features: Tensor | None = None,
    tile_size: int = 8,
    near: float = 0.01,
    backward: BackwardMode = "analytic",
    max_elements: int = 1 << 22,
    backend: Backend | None = None,
) -> RenderResult:
    """Render ``gmap`` from ``camera``.

    Args:
        gmap: the Gaussians (N of them); every field may require grad.
        camera: the view; a ``c2w`` that requires grad makes the render differentiable in it.
        background: colour [3] composited behind (default black).
        features: optional per-Gaussian features [N, C], composited like colour (zero
            background) into ``RenderResult.features`` [H, W, C].
        tile_size: tile edge in pixels of the reference binning rule.
        near: near-plane depth for culling.
        backward: "analytic" (closed-form backward) or "autograd" (reference, pure torch).
        max_elements: candidate pixel-Gaussian pairs evaluated at once (memory bound; the
            torch path only).
        backend: "auto", "numba" (the compiled CPU kernels) or "torch" (this module's
            pure-torch path); None: :func:`agilegs.service.nbv.kernels.backend.default_backend`. The
            kernels composite whenever they apply (CPU, float32/float64, ``backward=
            "analytic"``) and also project unless the pose requires grad.

    Returns:
        RenderResult with rgb [H, W, 3], alpha [H, W], depth [H, W] and per-Gaussian extras.
    """
    _check_inputs(gmap, camera)
    if backward not in ("analytic", "autograd"):
        raise ValueError(f"backward must be 'analytic' or 'autograd', got {backward!r}")
    if backward == "autograd" and backend == "numba":
        raise ValueError("backend='numba' has no autograd backward: use backward='analytic'")
    dt, dev = gmap.means.dtype, gmap.means.device
    use_kernels = backward == "analytic" and resolve(
        backend, [*gmap.tensors().values(), camera.c2w])
    pose_grad = bool(camera.c2w.requires_grad) and torch.is_grad_enabled()
    if use_kernels and not pose_grad:
        proj = kernel_project(gmap, camera, near=near)
    else:
        proj = project_map(gmap, camera, near=near)
    bg = (
        torch.zeros(3, dtype=dt, device=dev)
        if background is None
        else torch.as_tensor(background, dtype=dt, device=dev).reshape(3)
    )
    colors = proj.colors
    n_feat = 0
    if features is not None:
        if features.ndim == 1:
            features = features[:, None]
        if features.ndim != 2 or features.shape[0] != gmap.num_gaussians:
            raise ValueError(
                f"features must have shape [N, C] with N={gmap.num_gaussians}, "
                f"got {list(features.shape)}"
            )
        n_feat = features.shape[1]
        colors = torch.cat([colors, features.to(dt)], dim=1)
        bg = torch.cat([bg, torch.zeros(n_feat, dtype=dt, device=dev)])
    if use_kernels:
        out_c, out_a, out_dacc = kernel_composite(proj, colors, bg, camera.width,
                                                  camera.height, tile_size)
        depth = expected_depth(out_a, out_dacc)
    else:
        pairs = pairs_of(proj, camera.width, camera.height, tile_size, max_elements)
        out_c, out_a, depth = composite(
            proj.means2d, proj.conics, proj.opacities, colors, proj.depths, bg, pairs,
            backward=backward,
        )
    return RenderResult(
        rgb=out_c[..., :3],
        alpha=out_a,
        depth=depth,
        features=out_c[..., 3:] if n_feat else None,
        means2d=proj.means2d,
        radii=proj.radii,
        depths=proj.depths,
    )


def pairs_of(proj: Projected, width: int, height: int, tile_size: int = 8,
             max_elements: int = 1 << 22) -> Pairs:
    """:func:`build_pairs` of a projection."""
    return build_pairs(proj.means2d, proj.conics, proj.opacities, proj.cov2d, proj.radii,
                       proj.depths, width, height, tile_size, max_elements)


__all__ = [
    "Pairs",
    "PairTerms",
    "RenderResult",
    "build_pairs",
    "composite",
    "composite_pairs",
    "dcolor_dalpha",
    "pairs_of",
    "pixel_boxes",
    "render",
]
