"""Training through gsplat: the choice of rasterizer (everywhere) and gsplat against the built-in
rasterizer on the same map and camera (on a GPU with gsplat installed; skipped elsewhere)."""

from __future__ import annotations

import math

import pytest
import torch
from pydantic import ValidationError

from agilegs.config.mapper import MapperConfig
from agilegs.service.mapper.gsplat_render import (
    gsplat_status,
    render_gsplat,
    resolve_rasterizer,
)
from agilegs.service.mapper.mapper import Mapper
from agilegs.service.nbv import Camera, GaussianMap, look_at, render

# The two rasterizers agree up to the reach of a Gaussian's footprint (see
# agilegs.service.mapper.gsplat_render): on these maps, over the image,
RGB_MEAN_ABS = 2e-3  # mean |rgb difference|
RGB_MAX_ABS = 0.1  # largest |rgb difference| of one pixel channel
GRAD_COSINE = 0.99  # cosine between the two gradients of every field


def _map(n: int, seed: int = 0, device: str = "cpu", sh_degree: int = 3) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    k = (sh_degree + 1) ** 2
    sh = torch.randn(n, k, 3, generator=g) * 0.2
    sh[:, 0] = torch.randn(n, 3, generator=g) * 0.8
    gm = GaussianMap(
        means=torch.rand(n, 3, generator=g) - 0.5,
        log_scales=torch.log(torch.rand(n, 3, generator=g) * 0.04 + 0.01),
        quats=torch.randn(n, 4, generator=g),
        opacity_logits=torch.randn(n, generator=g) * 2.0,
        sh=sh,
    )
    return gm.to(device=device)


def _camera(width: int, height: int, device: str = "cpu", seed: int = 0) -> Camera:
    g = torch.Generator().manual_seed(seed)
    eye = torch.randn(3, generator=g)
    eye = 1.8 * eye / eye.norm()
    c2w = look_at(eye, torch.zeros(3))
    f = 0.9 * width
    return Camera.from_c2w(c2w, fx=f, fy=f * 1.05, cx=width / 2 + 0.3, cy=height / 2 - 0.2,
                           width=width, height=height).to(device=device)


# ----------------------------------------------------------------------------- the choice
def test_auto_takes_the_builtin_rasterizer_where_gsplat_cannot_run() -> None:
    assert resolve_rasterizer("builtin", "cpu", torch.float32) == "builtin"
    assert resolve_rasterizer("auto", "cpu", torch.float32) == "builtin"
    assert resolve_rasterizer("auto", "cpu", torch.float64) == "builtin"


def test_gsplat_where_it_cannot_run_is_an_error_saying_why() -> None:
    with pytest.raises(ValueError, match=r"rasterizer='gsplat'.*CUDA only"):
        resolve_rasterizer("gsplat", "cpu", torch.float32)
    with pytest.raises(ValueError, match="rasterizer must be one of"):
        resolve_rasterizer("cuda", "cpu", torch.float32)


def test_the_mapper_setting_is_validated_and_names_the_field() -> None:
    with pytest.raises(ValidationError, match="rasterizer"):
        MapperConfig(rasterizer="fast")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="rasterizer='gsplat'"):
        Mapper(_map(10), MapperConfig(rasterizer="gsplat"))
    assert Mapper(_map(10), MapperConfig()).rasterizer == "builtin"


def test_float64_maps_on_cuda_keep_the_builtin_rasterizer() -> None:
    if not torch.cuda.is_available():
        pytest.skip("needs CUDA")
    assert resolve_rasterizer("auto", "cuda", torch.float64) == "builtin"
    with pytest.raises(ValueError, match="float32 only"):
        resolve_rasterizer("gsplat", "cuda", torch.float64)


# ----------------------------------------------------------------------------- on a GPU
needs_gsplat = [
    pytest.mark.cuda,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA"),
]


def _skip_without_gsplat() -> None:
    why = gsplat_status()
    if why is not None:
        pytest.skip(f"gsplat: {why}")


@pytest.mark.parametrize(("n", "width", "height"), [(2000, 64, 48), (20000, 160, 120)])
@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_gsplat_renders_what_the_builtin_rasterizer_renders(n: int, width: int,
                                                             height: int) -> None:
    _skip_without_gsplat()
    gm, cam = _map(n, device="cuda"), _camera(width, height, "cuda")
    bg = torch.tensor([0.2, 0.4, 0.1], device="cuda")
    ours = render(gm, cam, background=bg)
    theirs = render_gsplat(gm, cam, background=bg)
    d = (ours.rgb - theirs.rgb).abs()
    print(f"N={n} {width}x{height}: rgb mean {float(d.mean()):.2e} max {float(d.max()):.2e}, "
          f"alpha mean {float((ours.alpha - theirs.alpha).abs().mean()):.2e}")
    assert float(d.mean()) < RGB_MEAN_ABS
    assert float(d.max()) < RGB_MAX_ABS
    assert float((ours.alpha - theirs.alpha).abs().mean()) < RGB_MEAN_ABS
    both = (ours.alpha > 0.5) & (theirs.alpha > 0.5)
    rel = ((ours.depth - theirs.depth).abs() / ours.depth.clamp_min(1e-6))[both]
    assert float(rel.mean()) < 1e-2
    assert torch.equal(ours.radii > 0, theirs.radii > 0) or float(
        ((ours.radii > 0) != (theirs.radii > 0)).float().mean()) < 0.02


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_gsplat_gradients_point_where_the_builtin_ones_do() -> None:
    _skip_without_gsplat()
    gm, cam = _map(3000, seed=1, device="cuda"), _camera(96, 80, "cuda", seed=1)
    w = torch.rand(80, 96, 3, generator=torch.Generator().manual_seed(2)).cuda()
    grads = {}
    for name, fn in (("ours", render), ("gsplat", render_gsplat)):
        g = gm.clone().requires_grad_()
        (fn(g, cam).rgb * w).sum().backward()
        grads[name] = {k: v.grad for k, v in g.tensors().items()}
    for k, a in grads["ours"].items():
        b = grads["gsplat"][k]
        assert a is not None and b is not None
        cos = float(torch.nn.functional.cosine_similarity(a.flatten(), b.flatten(), dim=0))
        print(f"{k}: cosine {cos:.5f}")
        assert cos > GRAD_COSINE, k


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_the_mapper_trains_and_densifies_with_gsplat() -> None:
    _skip_without_gsplat()
    gt = _map(3000, seed=3, device="cuda", sh_degree=0)
    cams = [_camera(96, 96, "cuda", seed=s) for s in range(6)]
    cfg = MapperConfig(rasterizer="gsplat", sh_degree=0, sh_degree_interval=None,
                       scene_extent=1.0, densify_from=10, densify_every=10,
                       densify_grad_threshold=1e-5, lr_means=1.6e-3, lr_sh_dc=2.5e-2)
    m = Mapper(_map(800, seed=4, sh_degree=0), cfg, device="cuda")
    assert m.rasterizer == "gsplat"
    changes = []
    m.on_topology_change.append(changes.append)
    for c in cams:
        m.add_view(c, render(gt, c).rgb.detach())
    before = sum(m.loss_on_view(i)["loss"] for i in range(6))
    infos = [m.step() for _ in range(60)]
    after = sum(m.loss_on_view(i)["loss"] for i in range(6))
    assert math.isfinite(after) and after < 0.8 * before
    assert any(ch.reason == "densify" and ch.num_new > ch.num_old for ch in changes)
    assert all(math.isfinite(i["loss"]) for i in infos)
