"""PSNR / SSIM against independent references (numpy, scikit-image, scipy)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from agilegs.service.mapper.quality import lpips_available, psnr, ssim, ssim_loss, ssim_map

skimage_metrics = pytest.importorskip("skimage.metrics")
ndimage = pytest.importorskip("scipy.ndimage")


def _pair(h: int, w: int, *, seed: int = 0, noise: float = 0.1, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    # smooth-ish image plus noise so SSIM is far from 0 and 1
    base = torch.rand(h // 4 + 1, w // 4 + 1, 3, generator=g, dtype=dtype)
    ref = torch.nn.functional.interpolate(
        base.permute(2, 0, 1)[None], size=(h, w), mode="bilinear", align_corners=False
    )[0].permute(1, 2, 0)
    pred = (ref + noise * torch.randn(h, w, 3, generator=g, dtype=dtype)).clamp(0, 1)
    return pred, ref


def test_psnr_matches_numpy() -> None:
    pred, ref = _pair(20, 30)
    mse = np.mean((pred.numpy() - ref.numpy()) ** 2)
    assert psnr(pred, ref) == pytest.approx(-10 * math.log10(mse), rel=1e-10)
    assert psnr(ref, ref) == float("inf")
    # 0.1 uniform error -> 20 dB
    assert psnr(torch.full((4, 4, 3), 0.6), torch.full((4, 4, 3), 0.5)) == pytest.approx(
        20.0, abs=1e-4
    )


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(32, 32), (48, 37)])
def test_ssim_matches_skimage(dtype, shape) -> None:
    pred, ref = _pair(*shape, dtype=dtype)
    ours = ssim(pred, ref, crop_border=True)
    theirs = skimage_metrics.structural_similarity(
        pred.double().numpy(),
        ref.double().numpy(),
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        data_range=1.0,
        channel_axis=-1,
    )
    assert 0.1 < theirs < 0.99
    assert ours == pytest.approx(theirs, abs=1e-4 if dtype == torch.float32 else 1e-9)


def test_ssim_full_map_is_zero_padded_gaussian_filter() -> None:
    """The default (3DGS) SSIM: moments from a zero-padded 11x11, sigma 1.5 Gaussian."""
    pred, ref = _pair(24, 28, seed=3)
    x, y = pred.numpy(), ref.numpy()

    def filt(a):
        return np.stack(
            [
                ndimage.gaussian_filter(a[..., c], 1.5, truncate=3.5, mode="constant", cval=0.0)
                for c in range(3)
            ],
            axis=-1,
        )

    mx, my = filt(x), filt(y)
    sxx = filt(x * x) - mx * mx
    syy = filt(y * y) - my * my
    sxy = filt(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    ref_map = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))
    np.testing.assert_allclose(ssim_map(pred, ref).numpy(), ref_map, atol=1e-10)
    assert ssim(pred, ref) == pytest.approx(float(ref_map.mean()), abs=1e-10)


def test_ssim_identity_and_loss_gradient() -> None:
    pred, ref = _pair(16, 16, seed=1, dtype=torch.float32)
    assert ssim(ref, ref) == pytest.approx(1.0, abs=1e-6)
    p = pred.clone().requires_grad_(True)
    loss = ssim_loss(p, ref)
    loss.backward()
    assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0
    # a small step along -grad lowers the loss
    with torch.no_grad():
        p2 = p - 0.5 * p.grad / p.grad.norm()
    assert float(ssim_loss(p2, ref)) < float(loss.detach())


@pytest.mark.gradcheck
def test_ssim_gradcheck() -> None:
    pred, ref = _pair(12, 12, seed=2)
    p = pred.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a: ssim_map(a, ref).mean(), (p,))


def test_shape_errors() -> None:
    with pytest.raises(ValueError, match="pred"):
        psnr(torch.zeros(4, 4), torch.zeros(4, 4))
    with pytest.raises(ValueError, match="ref"):
        ssim(torch.zeros(4, 4, 3), torch.zeros(4, 5, 3))


def test_lpips_not_available_here() -> None:
    # no LPIPS weights ship with this project or its test machines; nothing is downloaded
    assert isinstance(lpips_available(), bool)
    if not lpips_available():
        from agilegs.service.mapper.quality import lpips

        with pytest.raises(RuntimeError, match="not available"):
            lpips(torch.zeros(8, 8, 3), torch.zeros(8, 8, 3))
