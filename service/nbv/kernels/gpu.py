"""The Fisher's per-Gaussian moments on a GPU: a Triton kernel over the image's tiles.

The pure-torch Fisher lists every composited (pixel, Gaussian) pair, evaluates each pair's
terms as a tensor row and sums the rows per Gaussian: tens of millions of rows at 1024×768,
written to and read back from memory. This kernel does what the CPU's ``fisher_tiles`` does
instead: one program per image tile, one lane per pixel, a front-to-back walk over the tile's
Gaussians (the transmittance and where it stops), then a back-to-front walk that unwinds the
transmittance pair by pair and sums the :data:`~agilegs.service.nbv.kernels.common.MOMENTS`
terms of each Gaussian over the tile's pixels, added into the Gaussian's row.

It computes what :func:`~agilegs.service.nbv.information.screen_second_moments`' torch path
computes (the same pairs: the same tile binning, ellipse boxes, α rule, 1/255 cut and 1e-4
transmittance stop; the transmittance in float64, the pair terms in the map's dtype), so the
two agree up to the order of the additions. The torch path stays the reference; tests run this
kernel on the CPU through Triton's interpreter (``TRITON_INTERPRET=1``, slow) and compiled on
CUDA.

Triton is optional (it comes with CUDA builds of torch); :func:`triton_available` says
whether it imports.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..rasterize import ALPHA_MAX, ALPHA_MIN, T_MIN, pixel_boxes
from .backend import default_backend

log = logging.getLogger(__name__)

MOMENTS = 34

_triton: Any = None
_import_error: str | None = None


def _load_triton() -> Any:
    global _triton, _import_error
    if _triton is None and _import_error is None:
        try:
            import triton  # noqa: PLC0415 (optional)
            import triton.language  # noqa: F401,PLC0415
            _triton = triton
        except Exception as exc:  # absent or broken: the torch path serves
            _import_error = f"{type(exc).__name__}: {exc}"
            log.info("triton unavailable, the GPU Fisher uses the torch path (%s)",
                     _import_error)
    return _triton


def triton_available() -> bool:
    """Whether Triton imports (its compiler then serves CUDA tensors; its interpreter any)."""
    return _load_triton() is not None


def gpu_moments_apply(backend: str | None, like: Tensor) -> bool:
    """Whether :func:`tile_moments` serves the Fisher's moments of tensors like ``like``: on
    CUDA, float32 or float64, Triton importable, and the backend not ``"torch"`` (the pure
    reference; None: the default backend, see :mod:`.backend`)."""
    b = default_backend() if backend is None else backend
    return (b != "torch" and like.device.type == "cuda"
            and like.dtype in (torch.float32, torch.float64) and triton_available())


@dataclass
class TileBins:
    """The visible Gaussians binned to tiles, front to back in each tile.

    Attributes:
        vis: the visible Gaussians in depth order [V] (indices into the map).
        attrs: their rows [V, 9] (the map's dtype): mean x, mean y, conic a, b, c, opacity,
            colour (3).
        boxes: their pixel boxes x0, x1, y0, y1 (inclusive; empty: x0 > x1) [V, 4] int64.
        entries: each tile's list, the compact index into ``vis`` of every entry [M] int64.
        offsets: where tile t's list starts in ``entries`` [n_tiles + 1] int64.
        tiles_x, tiles_y: the tile grid.
    """

    vis: Tensor
    attrs: Tensor
    boxes: Tensor
    entries: Tensor
    offsets: Tensor
    tiles_x: int
    tiles_y: int


@torch.no_grad()
def bin_tiles(means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor, cov2d: Tensor,
              radii: Tensor, depths: Tensor, width: int, height: int, tile: int) -> TileBins:
    """Bin the visible Gaussians (radius > 0) to the tiles their α ≥ 1/255 box meets, as
    :func:`~agilegs.service.nbv.rasterize.build_pairs` bins them: depth order (stable), the
    binned tiles of the square [m ± r], the ellipse's box within them.

    Args: the projection's outputs for N Gaussians (means2d [N, 2], conics [N, 3],
    opacities [N], colors [N, 3], cov2d [N, 3], radii [N], depths [N]); the image and tile
    size in pixels.
    """
    dev = means2d.device
    dt = means2d.dtype
    tiles_x = (width + tile - 1) // tile
    tiles_y = (height + tile - 1) // tile
    n_tiles = tiles_x * tiles_y
    vis, (x0, x1, y0, y1) = pixel_boxes(means2d, opacities, cov2d, radii, depths, width,
                                         height, tile)
    m = means2d.detach()[vis]
    op = opacities.detach()[vis].to(dt)
    empty = (x1 < x0) | (y1 < y0)
    ntx = torch.where(empty, 0, torch.div(x1, tile, rounding_mode="floor")
                      - torch.div(x0, tile, rounding_mode="floor") + 1)
    nty = torch.where(empty, 0, torch.div(y1, tile, rounding_mode="floor")
                      - torch.div(y0, tile, rounding_mode="floor") + 1)
    counts = ntx * nty
    total = int(counts.sum()) if counts.numel() else 0
    attrs = torch.cat([m, conics.detach()[vis].to(dt), op[:, None],
                       colors.detach()[vis].to(dt)], dim=1).contiguous()
    boxes = torch.stack([x0, x1, y0, y1], dim=1).contiguous()
    if total == 0:
        return TileBins(vis, attrs, boxes, torch.zeros(0, dtype=torch.long, device=dev),
                        torch.zeros(n_tiles + 1, dtype=torch.long, device=dev), tiles_x, tiles_y)
    owner = torch.repeat_interleave(torch.arange(vis.numel(), device=dev), counts,
                                    output_size=total)
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(total, device=dev) - first[owner]
    wide = ntx[owner]
    tx = torch.div(x0[owner], tile, rounding_mode="floor") + local % wide
    ty = torch.div(y0[owner], tile, rounding_mode="floor") + torch.div(
        local, wide, rounding_mode="floor")
    tile_id = ty * tiles_x + tx
    tile_id, perm = torch.sort(tile_id, stable=True)  # stable: front to back in each tile
    entries = owner[perm].contiguous()
    offsets = torch.zeros(n_tiles + 1, dtype=torch.long, device=dev)
    offsets[1:] = torch.cumsum(torch.bincount(tile_id, minlength=n_tiles), 0)
    return TileBins(vis, attrs, boxes, entries, offsets, tiles_x, tiles_y)


def _kernel() -> Any:
    if _load_triton() is None:
        raise RuntimeError(f"triton is unavailable ({_import_error})")
    from .gpu_kernel import moments_kernel  # noqa: PLC0415 (needs triton)

    return moments_kernel


def _interpreting() -> bool:
    triton = _load_triton()
    return bool(triton is not None and triton.knobs.runtime.interpret)


def tile_moments(means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor,
                 cov2d: Tensor, radii: Tensor, depths: Tensor, width: int, height: int, *,
                 background: Tensor | None = None, tile_size: int = 8,
                 residuals: str = "channels") -> Tensor:
    """The Fisher's per-Gaussian moments [N, MOMENTS] (the map's dtype; the layout of
    ``kernels.common.MOMENTS``: Σ f4·dx^a dy^b over the 15 monomials, C2 channel-major, Σ w²)
    by the Triton kernel, from the projection's outputs (see :func:`bin_tiles`).

    Compiled for CUDA tensors; tensors elsewhere need Triton's interpreter (slow: for tests),
    which ``TRITON_INTERPRET=1`` in the environment turns on before Triton is first imported.
    ``residuals``: "channels" or "pixels" (as
    :func:`~agilegs.service.nbv.information.screen_second_moments`).
    """
    if residuals not in ("channels", "pixels"):
        raise ValueError(f"residuals must be 'channels' or 'pixels', got {residuals!r}")
    dt, dev = means2d.dtype, means2d.device
    interpret = _interpreting()
    if dev.type != "cuda" and not interpret:
        raise ValueError(f"tile_moments: the tensors are on {dev}; the kernel runs on CUDA, or "
                         "anywhere under Triton's interpreter (TRITON_INTERPRET=1)")
    n = means2d.shape[0]
    out = torch.zeros(n, MOMENTS, dtype=dt, device=dev)
    if n == 0:
        return out
    bins = bin_tiles(means2d, conics, opacities, colors, cov2d, radii, depths, width, height,
                     tile_size)
    if bins.entries.numel() == 0:
        return out
    bg = (torch.zeros(3, dtype=torch.float64) if background is None
          else torch.as_tensor(background).detach().to(dt).reshape(3).cpu().to(torch.float64))
    consts = torch.cat([torch.tensor([ALPHA_MIN, ALPHA_MAX, T_MIN], dtype=torch.float64),
                        bg]).to(dev)
    block = 1 << max(0, (tile_size * tile_size - 1).bit_length())
    part = torch.zeros(bins.vis.numel(), MOMENTS, dtype=dt, device=dev)
    kern = _kernel()
    grid = (bins.tiles_x * bins.tiles_y,)
    extra: dict[str, Any] = {} if interpret else {"num_warps": max(1, min(8, block // 64))}
    kern[grid](bins.attrs, bins.boxes, bins.entries, bins.offsets, consts, part, width, height,
               bins.tiles_x, TILE=tile_size, BLOCK=block, PIXELS=residuals == "pixels", **extra)
    out[bins.vis] = part
    return out
