"""A differentiable tile-based Gaussian rasterizer in pure torch (CPU and CUDA alike).

It follows the reference 3D Gaussian Splatting rasterizer (Kerbl et al. 2023). The
Gaussians are projected by :mod:`agilegs.service.nbv.projection` (EWA, low-pass, culling, SH
colour); then:

- a Gaussian is binned into every ``tile_size``² tile its square [u - r, u + r] overlaps
  (reference rule), front to back in camera depth;
- per pixel: α = min(0.99, o·exp(-σ)); σ < 0 and α < 1/255 are skipped; compositing stops
  before the Gaussian that would bring the transmittance below 1e-4 (that Gaussian is not
  composited, as in the reference).

Documented deviations: the background enters as C += T_final · bg (same as the reference);
``depth`` is the expected depth Σ w_i z_i / Σ w_i (0 where nothing was hit); tiles are processed
in chunks of similar list length, which changes nothing numerically.

The compositing has two interchangeable implementations sharing one forward formula
(``composite_chunk``): a plain autograd path (``backward="autograd"``, the slow obvious
reference, twice differentiable) and a custom ``torch.autograd.Function`` whose backward
recomputes the per-pixel terms chunk by chunk and applies the closed-form derivatives
(``backward="analytic"``, default: far less memory and faster). Tests check one against the other.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import torch
from torch import Tensor

from agilegs.service.nbv.camera import Camera
from agilegs.service.nbv.gaussians import GaussianMap
from agilegs.service.nbv.projection import project_map

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


# ----------------------------------------------------------------------------- binning
@dataclass
class Binning:
    """Gaussian lists per screen tile, sorted front to back.

    Attributes:
        gauss_ids: Gaussian index of every (tile, Gaussian) pair, grouped by tile [M].
        offsets: start of each tile's run in ``gauss_ids`` [n_tiles + 1].
        tiles_x, tiles_y: tile grid size; tile_size: tile edge in pixels.
        width, height: image size.
    """

    gauss_ids: Tensor
    offsets: Tensor
    tiles_x: int
    tiles_y: int
    tile_size: int
    width: int
    height: int

    @property
    def counts(self) -> Tensor:
        return self.offsets[1:] - self.offsets[:-1]

    def chunks(self, max_elements: int) -> list[tuple[Tensor, int]]:
        """Groups of non-empty tiles of similar list length: [(tile_ids [Tc], L_max)].

        Each group holds at most ``max_elements`` pixel-Gaussian pairs (Tc·P·L_max).
        """
        counts = self.counts
        nonempty = torch.nonzero(counts > 0).flatten()
        if nonempty.numel() == 0:
            return []
        c = counts[nonempty]
        order = torch.argsort(c, stable=True)
        tiles = nonempty[order]
        c_sorted = c[order].tolist()
        p = self.tile_size * self.tile_size
        out: list[tuple[Tensor, int]] = []
        start = 0
        n = len(c_sorted)
        while start < n:
            end = start
            lmax = c_sorted[start]
            while end < n:
                lm = max(lmax, c_sorted[end])
                if (end - start + 1) * p * lm > max_elements and end > start:
                    break
                lmax = lm
                end += 1
            out.append((tiles[start:end], lmax))
            start = end
        return out


def bin_gaussians(
    means2d: Tensor,
    radii: Tensor,
    depths: Tensor,
    width: int,
    height: int,
    tile_size: int = 8,
) -> Binning:
    """Assign each visible Gaussian to the tiles its 3σ square overlaps, front to back."""
    dev = means2d.device
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    with torch.no_grad():
        vis = torch.nonzero(radii > 0).flatten()
        if vis.numel() == 0:
            return Binning(
                torch.zeros(0, dtype=torch.long, device=dev),
                torch.zeros(tiles_x * tiles_y + 1, dtype=torch.long, device=dev),
                tiles_x,
                tiles_y,
                tile_size,
                width,
                height,
            )
        vis = vis[torch.argsort(depths.detach()[vis], stable=True)]  # front to back
        m = means2d.detach()[vis]
        r = radii[vis].to(m.dtype)
        x0 = torch.clamp(torch.floor((m[:, 0] - r) / tile_size), 0, tiles_x - 1).long()
        x1 = torch.clamp(torch.floor((m[:, 0] + r) / tile_size), 0, tiles_x - 1).long()
        y0 = torch.clamp(torch.floor((m[:, 1] - r) / tile_size), 0, tiles_y - 1).long()
        y1 = torch.clamp(torch.floor((m[:, 1] + r) / tile_size), 0, tiles_y - 1).long()
        nx = x1 - x0 + 1
        ny = y1 - y0 + 1
        n_pairs = nx * ny
        total = int(n_pairs.sum())
        owner = torch.repeat_interleave(torch.arange(vis.numel(), device=dev), n_pairs)
        start = torch.cumsum(n_pairs, 0) - n_pairs
        local = torch.arange(total, device=dev) - start[owner]
        tx = x0[owner] + local % nx[owner]
        ty = y0[owner] + torch.div(local, nx[owner], rounding_mode="floor")
        tile = ty * tiles_x + tx
        order = torch.argsort(tile, stable=True)  # stable: keeps depth order within a tile
        gauss_ids = vis[owner[order]]
        counts = torch.bincount(tile, minlength=tiles_x * tiles_y)
        offsets = torch.zeros(tiles_x * tiles_y + 1, dtype=torch.long, device=dev)
        offsets[1:] = torch.cumsum(counts, 0)
    return Binning(gauss_ids, offsets, tiles_x, tiles_y, tile_size, width, height)


def tile_pixels(
    binning: Binning, tile_ids: Tensor, dtype: torch.dtype
) -> tuple[Tensor, Tensor, Tensor]:
    """Pixel layout of the given tiles.

    Returns:
        local: pixel centres relative to the tile centre [P, 2] (shared by every tile; small
            numbers keep the moment sums of the backward accurate),
        centres: tile centres in image coordinates [Tc, 2],
        flat: flat image index of each tile pixel [Tc, P], -1 outside the image.
    """
    ts = binning.tile_size
    dev = tile_ids.device
    ly, lx = torch.meshgrid(
        torch.arange(ts, device=dev), torch.arange(ts, device=dev), indexing="ij"
    )
    lx, ly = lx.reshape(-1), ly.reshape(-1)
    ox = (tile_ids % binning.tiles_x) * ts
    oy = torch.div(tile_ids, binning.tiles_x, rounding_mode="floor") * ts
    px = ox[:, None] + lx[None, :]
    py = oy[:, None] + ly[None, :]
    inside = (px < binning.width) & (py < binning.height)
    flat = torch.where(inside, py * binning.width + px, torch.full_like(px, -1))
    half = ts / 2.0
    local = torch.stack([lx.to(dtype) + 0.5 - half, ly.to(dtype) + 0.5 - half], dim=-1)
    centres = torch.stack([ox.to(dtype) + half, oy.to(dtype) + half], dim=-1)
    return local, centres, flat


def gather_lists(binning: Binning, tile_ids: Tensor, lmax: int) -> tuple[Tensor, Tensor]:
    """Gaussian ids [Tc, L] of the given tiles' lists (padded with 0) and validity mask."""
    dev = tile_ids.device
    ar = torch.arange(lmax, device=dev)
    starts = binning.offsets[tile_ids]
    cnt = binning.offsets[tile_ids + 1] - starts
    valid = ar[None, :] < cnt[:, None]
    idx = (starts[:, None] + ar[None, :]).clamp_max(max(binning.gauss_ids.numel() - 1, 0))
    ids = torch.where(valid, binning.gauss_ids[idx], torch.zeros_like(idx))
    return ids, valid


# ----------------------------------------------------------------------------- compositing
@dataclass
class ChunkTerms:
    """Per (tile, pixel, list slot) terms of one chunk; shapes [Tc, P, L] unless noted."""

    dx: Tensor
    dy: Tensor
    alpha: Tensor  # effective alpha (0 where skipped or after the stop)
    raw_ok: Tensor  # bool: alpha not clamped at 0.99 and composited (derivatives flow)
    trans: Tensor  # transmittance before each Gaussian
    weight: Tensor  # trans * alpha
    t_final: Tensor  # [Tc, P]
    color: Tensor  # [Tc, P, C]
    acc_alpha: Tensor  # [Tc, P]
    depth_acc: Tensor  # [Tc, P]  sum w z
    raw: Tensor  # o·exp(-σ) before the clamp and the skips
    composited: Tensor  # bool: the pair was composited (not skipped, before the stop)


def composite_chunk(
    local: Tensor,
    m2d: Tensor,
    con: Tensor,
    op: Tensor,
    col: Tensor,
    z: Tensor,
    valid: Tensor,
    bg: Tensor,
) -> ChunkTerms:
    """Front-to-back compositing of one chunk of tiles (plain torch, differentiable).

    Args:
        local: pixel centres relative to the tile centre [P, 2].
        m2d: Gaussian centres relative to their tile's centre [Tc, L, 2].
        con: conics [Tc, L, 3]. op: opacities [Tc, L]. col: colours/features [Tc, L, C].
        z: depths [Tc, L]. valid: list validity [Tc, L]. bg: background [C].
    """
    dx = local[None, :, None, 0] - m2d[:, None, :, 0]
    dy = local[None, :, None, 1] - m2d[:, None, :, 1]
    a = con[:, None, :, 0]
    b = con[:, None, :, 1]
    c = con[:, None, :, 2]
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    raw = op[:, None, :] * torch.exp(-sigma)
    with torch.no_grad():
        keep = valid[:, None, :] & (sigma >= 0) & (raw >= ALPHA_MIN)
    alpha = torch.where(keep, torch.clamp_max(raw, ALPHA_MAX), torch.zeros_like(raw))
    with torch.no_grad():
        t_incl = torch.cumprod(1.0 - alpha, dim=-1)
        live = t_incl >= T_MIN  # the Gaussian that would drop T below 1e-4 is not composited
        raw_ok = keep & live & (raw <= ALPHA_MAX)
    alpha = torch.where(live, alpha, torch.zeros_like(alpha))
    t_incl = torch.cumprod(1.0 - alpha, dim=-1)
    trans = torch.cat([torch.ones_like(t_incl[..., :1]), t_incl[..., :-1]], dim=-1)
    weight = trans * alpha
    t_final = t_incl[..., -1]
    color = torch.matmul(weight, col) + t_final[..., None] * bg
    acc_alpha = 1.0 - t_final
    depth_acc = torch.matmul(weight, z[..., None])[..., 0]
    return ChunkTerms(dx, dy, alpha, raw_ok, trans, weight, t_final, color, acc_alpha, depth_acc,
                      raw, keep & live)


def suffix_sum(x: Tensor, dim: int) -> Tensor:
    """Σ over the elements strictly after each position along ``dim``."""
    rev = torch.flip(x, dims=[dim]).cumsum(dim)
    return torch.flip(rev, dims=[dim]) - x


def dalpha_dscreen(terms: ChunkTerms, con: Tensor, op: Tensor) -> Tensor:
    """∂α/∂(mean_x, mean_y, conic_a, conic_b, conic_c, opacity) per pair [Tc, P, L, 6]."""
    a = con[:, None, :, 0]
    b = con[:, None, :, 1]
    c = con[:, None, :, 2]
    dx, dy = terms.dx, terms.dy
    al = torch.where(terms.raw_ok, terms.alpha, torch.zeros_like(terms.alpha))
    opb = op[:, None, :].expand_as(al)
    return torch.stack(
        [
            al * (a * dx + b * dy),
            al * (b * dx + c * dy),
            -0.5 * al * dx * dx,
            -al * dx * dy,
            -0.5 * al * dy * dy,
            al / opb.clamp_min(1e-30),
        ],
        dim=-1,
    )


def dcolor_dalpha(terms: ChunkTerms, col: Tensor, bg: Tensor) -> Tensor:
    """∂C_c/∂α_i = T_i c_i - S_i / (1 - α_i), S_i the colour composited behind i [Tc,P,L,C]."""
    wc = terms.weight[..., None] * col[:, None, :, :]
    behind = suffix_sum(wc, dim=2) + (terms.t_final[..., None, None] * bg)
    return terms.trans[..., None] * col[:, None, :, :] - behind / (1.0 - terms.alpha)[..., None]


def pixel_monomials(local: Tensor, degree: int) -> Tensor:
    """Monomials x^i y^j (i + j ≤ degree) of local pixel coordinates [P, M], graded order."""
    x, y = local[:, 0], local[:, 1]
    cols = [x**i * y ** (k - i) for k in range(degree + 1) for i in range(k, -1, -1)]
    return torch.stack(cols, dim=-1)


def centred_moments_2(mom: Tensor, m: Tensor) -> Tensor:
    """From raw moments [.., 6] of (1, x, y, x², xy, y²) to (1, dx, dy, dx², dxdy, dy²).

    dx = x - m_x, dy = y - m_y with m [.., 2]; exact algebra (binomial expansion).
    """
    s0, sx, sy, sxx, sxy, syy = mom.unbind(-1)
    mx, my = m[..., 0], m[..., 1]
    return torch.stack(
        [
            s0,
            sx - mx * s0,
            sy - my * s0,
            sxx - 2 * mx * sx + mx * mx * s0,
            sxy - mx * sy - my * sx + mx * my * s0,
            syy - 2 * my * sy + my * my * s0,
        ],
        dim=-1,
    )


def screen_grads_from_moments(cm: Tensor, con: Tensor, op: Tensor) -> Tensor:
    """Σ_p g'·∂α/∂screen / α from centred moments of g' = (dL/dα)·α  →  [.., 6].

    Order: mean_x, mean_y, conic_a, conic_b, conic_c, opacity.
    """
    s0, sdx, sdy, sdxx, sdxy, sdyy = cm.unbind(-1)
    a, b, c = con.unbind(-1)
    return torch.stack(
        [
            a * sdx + b * sdy,
            b * sdx + c * sdy,
            -0.5 * sdxx,
            -sdxy,
            -0.5 * sdyy,
            s0 / op.clamp_min(1e-30),
        ],
        dim=-1,
    )


class _Composite(torch.autograd.Function):
    """Compositing with a closed-form backward that reuses the forward's per-pair terms.

    The forward keeps, per chunk, the effective alpha, the transmittance and the derivative
    mask (about 9 bytes per pixel-Gaussian pair in float32, far below what autograd keeps);
    the backward reduces over pixels with moment sums (one small matmul per chunk).
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        means2d: Tensor,
        conics: Tensor,
        opacities: Tensor,
        colors: Tensor,
        depths: Tensor,
        bg: Tensor,
        binning: Binning,
        max_elements: int,
    ) -> tuple[Tensor, Tensor, Tensor]:
        h, w = binning.height, binning.width
        n_ch = colors.shape[1]
        dt, dev = colors.dtype, colors.device
        out_c = bg.expand(h * w, n_ch).clone()
        out_a = torch.zeros(h * w, dtype=dt, device=dev)
        out_d = torch.zeros(h * w, dtype=dt, device=dev)
        chunks = binning.chunks(max_elements)
        saved = []
        # one packed gather per chunk instead of five
        packed = torch.cat([means2d, conics, opacities[:, None], depths[:, None], colors], dim=1)
        for tile_ids, lmax in chunks:
            local, centres, flat = tile_pixels(binning, tile_ids, dt)
            ids, valid = gather_lists(binning, tile_ids, lmax)
            g = packed.index_select(0, ids.flatten()).view(ids.shape[0], lmax, -1)
            t = composite_chunk(
                local,
                g[..., 0:2] - centres[:, None, :],
                g[..., 2:5],
                g[..., 5],
                g[..., 7:],
                g[..., 6],
                valid,
                bg,
            )
            sel = flat >= 0
            out_c[flat[sel]] = t.color[sel]
            out_a[flat[sel]] = t.acc_alpha[sel]
            out_d[flat[sel]] = t.depth_acc[sel]
            saved.append((tile_ids, ids, t.alpha, t.trans, t.raw_ok, t.t_final))
        ctx.save_for_backward(means2d, conics, opacities, colors, depths, bg)
        ctx.binning = binning
        ctx.saved_chunks = saved
        return out_c.reshape(h, w, n_ch), out_a.reshape(h, w), out_d.reshape(h, w)

    @staticmethod
    def backward(  # type: ignore[override]
        ctx: Any, g_color: Tensor, g_alpha: Tensor, g_depth: Tensor
    ) -> tuple[Tensor | None, ...]:
        means2d, conics, opacities, colors, depths, bg = ctx.saved_tensors
        binning: Binning = ctx.binning
        dt = colors.dtype
        n_ch = colors.shape[1]
        g_c = g_color.reshape(-1, n_ch)
        g_a = g_alpha.reshape(-1)
        g_d = g_depth.reshape(-1)
        gm = torch.zeros_like(means2d)
        gcon = torch.zeros_like(conics)
        gop = torch.zeros_like(opacities)
        gcol = torch.zeros_like(colors)
        gz = torch.zeros_like(depths)
        gbg = torch.zeros_like(bg)
        packed = torch.cat([means2d, conics, opacities[:, None], depths[:, None], colors], dim=1)
        g_out = torch.cat([g_c, g_a[:, None], g_d[:, None]], dim=1)  # [HW, C + 2]
        mono2 = None
        for tile_ids, ids, alpha, trans, raw_ok, t_final in ctx.saved_chunks:
            local, centres, flat = tile_pixels(binning, tile_ids, dt)
            if mono2 is None:
                mono2 = pixel_monomials(local, 2)  # [P, 6], the same for every tile
            inside = flat >= 0
            go = g_out.index_select(0, flat.clamp_min(0).flatten()).view(*flat.shape, -1)
            go = go * inside[..., None].to(dt)
            gc, ga, gdp = go[..., :n_ch], go[..., n_ch], go[..., n_ch + 1]
            g = packed.index_select(0, ids.flatten()).view(ids.shape[0], ids.shape[1], -1)
            m2d, con, op, z, col = g[..., 0:2], g[..., 2:5], g[..., 5], g[..., 6], g[..., 7:]
            weight = trans * alpha
            fid = ids.flatten()
            wt = weight.transpose(1, 2)
            # dC/dc_i = w_i ; dC/dbg = T_final ; dD_acc/dz_i = w_i
            gcol.index_add_(0, fid, torch.matmul(wt, gc).flatten(0, 1))
            gz.index_add_(0, fid, torch.matmul(wt, gdp[..., None]).flatten())
            gbg += torch.einsum("tp,tpc->c", t_final, gc)
            # dL/dα_i = T_i u_i - (Σ_{j>i} w_j u_j + T_final (bg·gC - gA)) / (1 - α_i)
            # with u_i = c_i·gC + z_i gD (colour, alpha and depth outputs in one pass)
            u = torch.matmul(gc, col.transpose(1, 2)) + gdp[..., None] * z[:, None, :]
            tail = t_final * ((gc * bg).sum(-1) - ga)
            gal = trans * u - (suffix_sum(weight * u, dim=2) + tail[..., None]) / (1.0 - alpha)
            gprime = torch.where(raw_ok, gal * alpha, torch.zeros_like(gal))
            mom = torch.matmul(gprime.transpose(1, 2), mono2)  # [Tc, L, 6]
            cm = centred_moments_2(mom, m2d - centres[:, None, :])
            gs = screen_grads_from_moments(cm, con, op).flatten(0, 1)
            gm.index_add_(0, fid, gs[:, 0:2])
            gcon.index_add_(0, fid, gs[:, 2:5])
            gop.index_add_(0, fid, gs[:, 5])
        return gm, gcon, gop, gcol, gz, gbg, None, None


def composite(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    depths: Tensor,
    bg: Tensor,
    binning: Binning,
    *,
    backward: BackwardMode = "analytic",
    max_elements: int = 1 << 21,
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite binned Gaussians into images.

    Returns:
        colour [H, W, C], accumulated alpha [H, W], expected depth [H, W].
    """
    if backward == "analytic":
        out_c, out_a, out_dacc = _Composite.apply(
            means2d, conics, opacities, colors, depths, bg, binning, max_elements
        )
    elif backward == "autograd":
        h, w = binning.height, binning.width
        n_ch = colors.shape[1]
        out_c = bg.expand(h * w, n_ch).clone()
        out_a = torch.zeros(h * w, dtype=colors.dtype, device=colors.device)
        out_dacc = torch.zeros(h * w, dtype=colors.dtype, device=colors.device)
        for tile_ids, lmax in binning.chunks(max_elements):
            local, centres, flat = tile_pixels(binning, tile_ids, colors.dtype)
            ids, valid = gather_lists(binning, tile_ids, lmax)
            m2d = means2d[ids] - centres[:, None, :]
            t = composite_chunk(
                local, m2d, conics[ids], opacities[ids], colors[ids], depths[ids], valid, bg
            )
            sel = flat >= 0
            out_c = out_c.index_put((flat[sel],), t.color[sel])
            out_a = out_a.index_put((flat[sel],), t.acc_alpha[sel])
            out_dacc = out_dacc.index_put((flat[sel],), t.depth_acc[sel])
        out_c = out_c.reshape(h, w, n_ch)
        out_a = out_a.reshape(h, w)
        out_dacc = out_dacc.reshape(h, w)
    else:
        raise ValueError(f"backward must be 'analytic' or 'autograd', got {backward!r}")
    has = out_a > 0
    depth = torch.where(has, out_dacc / torch.where(has, out_a, torch.ones_like(out_a)), 0.0)
    return out_c, out_a, depth


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
    max_elements: int = 1 << 21,
) -> RenderResult:
    """Render ``gmap`` from ``camera``.

    Args:
        gmap: the Gaussians (N of them); every field may require grad.
        camera: the view; a ``c2w`` that requires grad makes the render differentiable in it.
        background: colour [3] composited behind (default black).
        features: optional per-Gaussian features [N, C], composited like colour (zero
            background) into ``RenderResult.features`` [H, W, C].
        tile_size: tile edge in pixels for binning.
        near: near-plane depth for culling.
        backward: "analytic" (chunked closed-form backward) or "autograd" (reference).
        max_elements: pixel-Gaussian pairs per processing chunk (memory bound).

    Returns:
        RenderResult with rgb [H, W, 3], alpha [H, W], depth [H, W] and per-Gaussian extras.
    """
    _check_inputs(gmap, camera)
    dt, dev = gmap.means.dtype, gmap.means.device
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
    binning = bin_gaussians(
        proj.means2d, proj.radii, proj.depths, camera.width, camera.height, tile_size
    )
    out_c, out_a, depth = composite(
        proj.means2d,
        proj.conics,
        proj.opacities,
        colors,
        proj.depths,
        bg,
        binning,
        backward=backward,
        max_elements=max_elements,
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


def tile_pair_count(gmap: GaussianMap, camera: Camera, tile_size: int = 8) -> int:
    """Number of (tile, Gaussian) pairs a render would process (for diagnostics)."""
    with torch.no_grad():
        proj = project_map(gmap, camera)
        b = bin_gaussians(
            proj.means2d, proj.radii, proj.depths, camera.width, camera.height, tile_size
        )
    return int(b.gauss_ids.numel())


__all__ = [
    "Binning",
    "RenderResult",
    "bin_gaussians",
    "composite",
    "composite_chunk",
    "render",
]
