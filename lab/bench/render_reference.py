"""The benchmark's straightforward baselines of the rasterizer and the exact Fisher, in
pure torch, written as one would first write them.

- :func:`baseline_render`: the EWA projection, the reference binning (every visible
  Gaussian in each 8x8 tile its 3σ square overlaps, front to back), then the tiles in chunks:
  every (pixel, list slot) pair of a chunk evaluated densely with the lists padded to the
  chunk's longest, the transmittance by a cumulative product, autograd for the backward.
- :func:`baseline_fisher_diag`: one pass over the same chunks without autograd: per pair the
  closed-form ∂C_c/∂α and the six derivatives of α w.r.t. the 2D mean, conic and opacity,
  their products summed per Gaussian into the 9x9 second moment M of the screen attributes,
  then diag(Jᵀ M J) with the projection Jacobians from autograd.

Chunks group tiles of similar list length (less padding) and hold at most ``max_elements``
(pixel, slot) pairs: 2^19 by default, the fastest of 2^17 to 2^23 for both on this project's
CPU benchmark scenes (``agilegs bench render`` times the baselines beside the kernels).
Same maths as :mod:`agilegs.service.nbv.rasterize` and :mod:`agilegs.service.nbv.information`;
the tests check that they agree.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from agilegs.config.selection import FIELD_NAMES
from agilegs.service.nbv import Camera, GaussianMap
from agilegs.service.nbv.information import jacobian_sandwich, projection_jacobians
from agilegs.service.nbv.projection import Projected, project_map
from agilegs.service.nbv.rasterize import ALPHA_MAX, ALPHA_MIN, T_MIN

__all__ = ["baseline_fisher_diag", "baseline_render"]


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


def dcolor_dalpha(terms: ChunkTerms, col: Tensor, bg: Tensor) -> Tensor:
    """∂C_c/∂α_i = T_i c_i - S_i / (1 - α_i), S_i the colour composited behind i [Tc,P,L,C]."""
    wc = terms.weight[..., None] * col[:, None, :, :]
    behind = suffix_sum(wc, dim=2) + (terms.t_final[..., None, None] * bg)
    return terms.trans[..., None] * col[:, None, :, :] - behind / (1.0 - terms.alpha)[..., None]


def _chunks(gmap: GaussianMap, camera: Camera, bg: Tensor, max_elements: int
            ) -> tuple[Projected, Binning, list[tuple[Tensor, int]]]:
    proj = project_map(gmap, camera)
    binning = bin_gaussians(proj.means2d, proj.radii, proj.depths, camera.width, camera.height)
    return proj, binning, binning.chunks(max_elements)


DEFAULT_MAX_ELEMENTS = 1 << 19


def baseline_render(gmap: GaussianMap, camera: Camera, background: Tensor | None = None,
                    max_elements: int = DEFAULT_MAX_ELEMENTS) -> Tensor:
    """The rendered RGB [H, W, 3], differentiable by autograd."""
    dt = gmap.means.dtype
    bg = torch.zeros(3, dtype=dt) if background is None else background.to(dt)
    proj, binning, chunks = _chunks(gmap, camera, bg, max_elements)
    h, w = camera.height, camera.width
    out = bg.expand(h * w, 3).clone()
    for tile_ids, lmax in chunks:
        local, centres, flat = tile_pixels(binning, tile_ids, dt)
        ids, valid = gather_lists(binning, tile_ids, lmax)
        t = composite_chunk(local, proj.means2d[ids] - centres[:, None, :], proj.conics[ids],
                            proj.opacities[ids], proj.colors[ids], proj.depths[ids], valid, bg)
        sel = flat >= 0
        out = out.index_put((flat[sel],), t.color[sel])
    return out.reshape(h, w, 3)


def baseline_fisher_diag(gmap: GaussianMap, camera: Camera, background: Tensor | None = None,
                         max_elements: int = DEFAULT_MAX_ELEMENTS) -> dict[str, Tensor]:
    """diag(JᵀJ) of the rendered RGB per parameter block: the screen attributes' second
    moment M_i = Σ_pc g gᵀ (g = ∂C_pc/∂(mean2d, conic, opacity, colour)) summed per pair, then
    diag(Jᵀ M J) with the autograd projection Jacobians."""
    g0 = gmap.detach()
    dt = g0.means.dtype
    bg = torch.zeros(3, dtype=dt) if background is None else background.to(dt)
    n = g0.num_gaussians
    mgg = torch.zeros(n, 6, 6, dtype=dt)
    mgc = torch.zeros(n, 6, 3, dtype=dt)
    mcc = torch.zeros(n, dtype=dt)
    with torch.no_grad():
        proj, binning, chunks = _chunks(g0, camera, bg, max_elements)
        for tile_ids, lmax in chunks:
            local, centres, flat = tile_pixels(binning, tile_ids, dt)
            ids, valid = gather_lists(binning, tile_ids, lmax)
            con, op, col = proj.conics[ids], proj.opacities[ids], proj.colors[ids]
            t = composite_chunk(local, proj.means2d[ids] - centres[:, None, :], con, op, col,
                                proj.depths[ids], valid, bg)
            inside = (flat >= 0).to(dt)[..., None]  # [Tc, P, 1]
            al = torch.where(t.raw_ok, t.alpha, torch.zeros_like(t.alpha)) * inside
            a_, b_, c_ = (con[:, None, :, k] for k in range(3))
            dx, dy = t.dx, t.dy
            # ∂α/∂(mean x, mean y, conic a, b, c, opacity) per pair [Tc, P, L, 6]
            dads = torch.stack([al * (a_ * dx + b_ * dy), al * (b_ * dx + c_ * dy),
                                -0.5 * al * dx * dx, -al * dx * dy, -0.5 * al * dy * dy,
                                al / op[:, None, :]], dim=-1)
            dcda = dcolor_dalpha(t, col, bg)  # [Tc, P, L, 3]
            wgt = t.weight * inside
            flat_ids = ids.flatten()
            # Σ_pc (∂C_c/∂α)² ∂α ∂αᵀ, Σ_p ∂C_c/∂α w ∂α and Σ_p w², contracted over the pixels
            root = dads * (dcda * dcda).sum(-1, keepdim=True).sqrt()
            mgg.index_add_(0, flat_ids, torch.einsum("tpla,tplb->tlab", root, root).flatten(0, 1))
            mgc.index_add_(0, flat_ids, torch.einsum("tpla,tplc->tlac", dads,
                                                     dcda * wgt[..., None]).flatten(0, 1))
            mcc.index_add_(0, flat_ids, (wgt * wgt).sum(1).flatten())
    m = torch.zeros(n, 9, 9, dtype=dt)
    m[:, :6, :6] = mgg
    m[:, :6, 6:] = mgc
    m[:, 6:, :6] = mgc.transpose(1, 2)
    m[:, 6:, 6:] = mcc[:, None, None] * torch.eye(3, dtype=dt)
    jac = projection_jacobians(g0, camera, FIELD_NAMES, backend="torch")
    return {f: jacobian_sandwich(jac[f], m).reshape(getattr(g0, f).shape) for f in FIELD_NAMES}
