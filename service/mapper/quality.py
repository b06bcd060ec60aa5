"""Image quality metrics: PSNR, SSIM (and the D-SSIM training loss), LPIPS availability.

Images are ``[H, W, 3]`` tensors with values in [0, 1] (data range 1).

SSIM follows the reference 3D Gaussian Splatting code (``utils/loss_utils.py``): an 11x11
Gaussian window with sigma 1.5 (normalised, applied as two separable 1D passes, which is the
same window), constants C1 = 0.01², C2 = 0.03², zero padding at the border, the map averaged
over every pixel and channel. ``ssim(..., crop_border=True)`` averages only the pixels at least
5 pixels away from the border, where no window touches the padding: that is exactly what
``skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=1, channel_axis=-1)`` computes (its reflect padding
only reaches the cropped band).

LPIPS needs a network backbone whose weights are downloaded by its packages on first use; this
module never downloads anything: :func:`lpips_available` reports whether an implementation and
its weights are present locally, and :func:`lpips` refuses otherwise.
"""

from __future__ import annotations

import importlib.util
import logging
import math
from functools import lru_cache
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

log = logging.getLogger(__name__)

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2

__all__ = [
    "psnr",
    "ssim",
    "ssim_map",
    "ssim_loss",
    "gaussian_window_1d",
    "lpips_available",
    "lpips",
]


def _check_pair(pred: Tensor, ref: Tensor) -> None:
    if not isinstance(pred, Tensor) or not isinstance(ref, Tensor):
        raise TypeError("pred and ref must be torch tensors")
    if pred.ndim != 3 or pred.shape[-1] != 3:
        raise ValueError(f"pred must have shape [H, W, 3], got {list(pred.shape)}")
    if ref.shape != pred.shape:
        raise ValueError(
            f"ref must have the shape of pred {list(pred.shape)}, got {list(ref.shape)}"
        )


def psnr(pred: Tensor, ref: Tensor) -> float:
    """Peak signal-to-noise ratio in dB for images in [0, 1].

    Args:
        pred: rendered image [H, W, 3].
        ref: reference image [H, W, 3].

    Returns:
        ``-10 log10(MSE)`` over every pixel and channel; ``inf`` for identical images.
    """
    _check_pair(pred, ref)
    dt = torch.promote_types(pred.dtype, ref.dtype)
    mse = float(((pred.detach().to(dt) - ref.detach().to(dt)) ** 2).mean())
    if mse <= 0.0:
        return float("inf")
    return -10.0 * math.log10(mse)


def gaussian_window_1d(
    size: int = SSIM_WINDOW,
    sigma: float = SSIM_SIGMA,
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Tensor:
    """Normalised 1D Gaussian window [size] centred on the middle sample."""
    x = torch.arange(size, dtype=torch.float64) - (size // 2)
    g = torch.exp(-(x**2) / (2.0 * sigma**2))
    return (g / g.sum()).to(dtype=dtype, device=device)


def _blur(x: Tensor, win: Tensor) -> Tensor:
    """Separable Gaussian filter with zero padding of x [B, C, H, W] (same size out)."""
    c = x.shape[1]
    k = win.numel()
    pad = k // 2
    wx = win.reshape(1, 1, 1, k).expand(c, 1, 1, k)
    wy = win.reshape(1, 1, k, 1).expand(c, 1, k, 1)
    x = F.conv2d(x, wx, padding=(0, pad), groups=c)
    return F.conv2d(x, wy, padding=(pad, 0), groups=c)


def ssim_map(
    pred: Tensor,
    ref: Tensor,
    *,
    window_size: int = SSIM_WINDOW,
    sigma: float = SSIM_SIGMA,
) -> Tensor:
    """Per-pixel, per-channel SSIM map [H, W, 3], differentiable in both images.

    Args:
        pred: image [H, W, 3] in [0, 1].
        ref: image [H, W, 3] in [0, 1].
        window_size: Gaussian window edge in pixels (odd; 11 as in 3DGS).
        sigma: Gaussian window standard deviation in pixels (1.5 as in 3DGS).

    Returns:
        SSIM map [H, W, 3] with zero padding at the border (the 3DGS reference).
    """
    _check_pair(pred, ref)
    if window_size < 1 or window_size % 2 == 0:
        raise ValueError(f"window_size must be a positive odd integer, got {window_size}")
    dt = torch.promote_types(pred.dtype, ref.dtype)
    if not dt.is_floating_point:
        dt = torch.float32
    x = pred.to(dt).permute(2, 0, 1)[None]
    y = ref.to(dt).permute(2, 0, 1)[None]
    win = gaussian_window_1d(window_size, sigma, dtype=dt, device=x.device)
    # one batched blur of the five moments
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    m = _blur(stack, win)
    mu_x, mu_y, e_xx, e_yy, e_xy = m.split(3, dim=1)
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    s_xx = e_xx - mu_xx
    s_yy = e_yy - mu_yy
    s_xy = e_xy - mu_xy
    num = (2.0 * mu_xy + SSIM_C1) * (2.0 * s_xy + SSIM_C2)
    den = (mu_xx + mu_yy + SSIM_C1) * (s_xx + s_yy + SSIM_C2)
    return (num / den)[0].permute(1, 2, 0)


def ssim(
    pred: Tensor,
    ref: Tensor,
    *,
    crop_border: bool = False,
    window_size: int = SSIM_WINDOW,
    sigma: float = SSIM_SIGMA,
) -> float:
    """Mean structural similarity of two images [H, W, 3] in [0, 1].

    Args:
        pred: image [H, W, 3].
        ref: image [H, W, 3].
        crop_border: average only pixels ``window_size // 2`` or more from the border
            (scikit-image's convention) instead of the whole zero-padded map (3DGS's).

    Returns:
        The mean SSIM as a Python float.
    """
    with torch.no_grad():
        m = ssim_map(pred.detach(), ref.detach(), window_size=window_size, sigma=sigma)
    if crop_border:
        r = window_size // 2
        if m.shape[0] <= 2 * r or m.shape[1] <= 2 * r:
            raise ValueError(
                f"image {list(m.shape[:2])} too small to crop a {r}-pixel border for SSIM"
            )
        m = m[r:-r, r:-r]
    return float(m.mean())


def ssim_loss(pred: Tensor, ref: Tensor) -> Tensor:
    """D-SSIM training loss ``1 - mean SSIM`` (a differentiable scalar tensor)."""
    return 1.0 - ssim_map(pred, ref).mean()


# ----------------------------------------------------------------------------- LPIPS
_ALEXNET_FILES = ("alexnet-owt-7be5be79.pth", "alexnet-owt-4df8aa71.pth")


def _torch_hub_checkpoints() -> Path:
    return Path(torch.hub.get_dir()) / "checkpoints"


@lru_cache(maxsize=1)
def lpips_available() -> bool:
    """True only if the ``lpips`` package, torchvision and the AlexNet backbone weights are
    all present locally (nothing is ever downloaded)."""
    try:
        if importlib.util.find_spec("lpips") is None:
            return False
        if importlib.util.find_spec("torchvision") is None:
            return False
    except (ImportError, ValueError):
        return False
    ckpt = _torch_hub_checkpoints()
    if not any((ckpt / f).is_file() for f in _ALEXNET_FILES):
        return False
    spec = importlib.util.find_spec("lpips")
    if spec is None or spec.origin is None:
        return False
    lin = Path(spec.origin).parent / "weights" / "v0.1" / "alex.pth"
    return lin.is_file()


@lru_cache(maxsize=2)
def _lpips_net(device: str) -> Any:
    import lpips as lpips_pkg  # type: ignore[import-not-found]

    net = lpips_pkg.LPIPS(net="alex", verbose=False)
    return net.eval().to(device)


def lpips(pred: Tensor, ref: Tensor) -> float:
    """LPIPS (AlexNet) distance of two images [H, W, 3] in [0, 1].

    Raises:
        RuntimeError: when :func:`lpips_available` is False (no implementation or weights
            locally; nothing is downloaded).
    """
    _check_pair(pred, ref)
    if not lpips_available():
        raise RuntimeError(
            "LPIPS is not available: it needs the 'lpips' package, torchvision and the AlexNet "
            "weights in the local torch hub cache (nothing is downloaded)"
        )
    net = _lpips_net(str(pred.device))
    with torch.no_grad():
        x = pred.detach().float().permute(2, 0, 1)[None] * 2 - 1
        y = ref.detach().float().permute(2, 0, 1)[None] * 2 - 1
        return float(net(x, y).mean())
