"""The Fisher's moments by the Triton kernel (kernels/gpu.py) against the torch pairs: on the
CPU through Triton's interpreter (in a subprocess: the interpreter is chosen when Triton is
first imported), on CUDA compiled (skipped without a GPU); the tile binning; which path serves."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from conftest import ROOT, camera, random_map

from agilegs.config.selection import FIELD_NAMES
from agilegs.service.nbv import fisher_diag
from agilegs.service.nbv.information import pair_moments, screen_second_moments
from agilegs.service.nbv.kernels.gpu import (
    bin_tiles,
    gpu_moments_apply,
    tile_moments,
    triton_available,
)
from agilegs.service.nbv.projection import project_map
from agilegs.service.nbv.rasterize import pairs_of

F64, F32 = torch.float64, torch.float32
HERE = ROOT / "tests"

_COMPARE = textwrap.dedent("""
    import json, sys, torch
    sys.path.insert(0, {here!r})
    from agilegs.service.nbv.projection import project_map
    from agilegs.service.nbv.information import pair_moments
    from agilegs.service.nbv.kernels.gpu import tile_moments
    from conftest import camera, random_map
    out = []
    for dtype, tile, res, bg in {cases!r}:
        dt = getattr(torch, dtype)
        gm = random_map(24, seed=2, deg=2, dtype=dt)
        cam = camera(w=13, h=11, dtype=dt)
        b = torch.tensor(bg, dtype=dt)
        p = project_map(gm, cam)
        ref = pair_moments(p, cam.width, cam.height, b, tile_size=tile, residuals=res)
        got = tile_moments(p.means2d, p.conics, p.opacities, p.colors, p.cov2d, p.radii,
                           p.depths, cam.width, cam.height, background=b, tile_size=tile,
                           residuals=res)
        err = float((got.double() - ref.double()).abs().max() / ref.abs().max())
        cols = [float((got[:, c].double() - ref[:, c].double()).abs().max()
                      / ref[:, c].abs().max()) for c in (0, 14, 20, 33)]
        out.append(dict(err=err, cols=cols, dtype=str(got.dtype), nonzero=int((ref[:, 0] > 0).sum())))
    print(json.dumps(out))
""")


@pytest.mark.skipif(not triton_available(), reason="needs triton (the dev extra installs it)")
def test_interpreted_kernel_matches_the_pairs() -> None:
    cases = [("float64", 8, "channels", [0.1, 0.2, 0.3]),
             ("float32", 5, "pixels", [1.0, 1.0, 1.0])]
    env = {**os.environ, "TRITON_INTERPRET": "1"}
    proc = subprocess.run([sys.executable, "-c", _COMPARE.format(here=str(HERE), cases=cases)],
                          capture_output=True, text=True, env=env, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads(proc.stdout.strip().splitlines()[-1])
    (f64, f32) = results
    assert f64["dtype"] == "torch.float64" and f32["dtype"] == "torch.float32"
    assert f64["nonzero"] > 5 and f32["nonzero"] > 5
    assert f64["err"] < 1e-12 and max(f64["cols"]) < 1e-11
    assert f32["err"] < 5e-6 and max(f32["cols"]) < 5e-5


_COMPILE = textwrap.dedent("""
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource
    from agilegs.service.nbv.kernels.gpu_kernel import moments_kernel
    for ft, pixels in (("fp32", False), ("fp64", True)):
        sig = {"attr_ptr": "*" + ft, "box_ptr": "*i64", "ent_ptr": "*i64", "off_ptr": "*i64",
               "const_ptr": "*fp64", "out_ptr": "*" + ft, "width": "i32", "height": "i32",
               "tiles_x": "i32", "TILE": "constexpr", "BLOCK": "constexpr", "PIXELS": "constexpr"}
        src = ASTSource(fn=moments_kernel, signature=sig,
                        constexprs={"TILE": 8, "BLOCK": 64, "PIXELS": pixels})
        k = triton.compile(src, target=GPUTarget("cuda", 90, 32), options={"num_warps": 1})
        assert len(k.asm["cubin"]) > 1000
        print(ft, "ok")
""")


@pytest.mark.skipif(not triton_available(), reason="needs triton (the dev extra installs it)")
def test_the_kernel_compiles_for_a_hopper_gpu_without_one(tmp_path: Path) -> None:
    # Triton's frontend, its passes and its bundled ptxas run on any machine: the kernel's
    # typing is checked here, where no GPU runs it (the interpreter does not type it)
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    env["TRITON_CACHE_DIR"] = str(tmp_path)  # compiled here, not read from a cache
    proc = subprocess.run([sys.executable, "-c", _COMPILE], capture_output=True, text=True,
                          env=env, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.split() == ["fp32", "ok", "fp64", "ok"]


@pytest.mark.parametrize("tile", [8, 5])
def test_bins_hold_every_composited_pair_front_to_back(tile: int) -> None:
    gm = random_map(60, seed=1, deg=1, dtype=F64)
    cam = camera()
    p = project_map(gm, cam)
    bins = bin_tiles(p.means2d, p.conics, p.opacities, p.colors, p.cov2d, p.radii, p.depths,
                     cam.width, cam.height, tile)
    assert bins.vis.numel() == int((p.radii > 0).sum())
    depth = p.depths[bins.vis]
    assert bool((depth[1:] >= depth[:-1]).all())
    pairs = pairs_of(p, cam.width, cam.height, tile)
    assert len(pairs) > 50
    rank = torch.full((gm.num_gaussians,), -1, dtype=torch.long)
    rank[bins.vis] = torch.arange(bins.vis.numel())
    lists = {}
    for t in range(bins.tiles_x * bins.tiles_y):
        ent = bins.entries[bins.offsets[t]:bins.offsets[t + 1]]
        assert bool((ent[1:] > ent[:-1]).all())  # front to back, each Gaussian once
        lists[t] = set(ent.tolist())
    x = pairs.pix % cam.width
    y = pairs.pix // cam.width
    tiles = (y // tile) * bins.tiles_x + x // tile
    for g, t, px, py in zip(pairs.gauss.tolist(), tiles.tolist(), x.tolist(), y.tolist(),
                            strict=True):
        v = int(rank[g])
        assert v in lists[t]
        x0, x1, y0, y1 = bins.boxes[v].tolist()
        assert x0 <= px <= x1 and y0 <= py <= y1


def test_the_torch_path_serves_off_cuda() -> None:
    gm = random_map(30, seed=3, dtype=F32)
    assert not gpu_moments_apply(None, gm.means)
    assert not gpu_moments_apply("torch", gm.means)
    cam = camera(dtype=F32)
    p = project_map(gm, cam)
    # the pair route is what the torch backend sums
    m = screen_second_moments(gm, cam, backend="torch")
    sums = pair_moments(p, cam.width, cam.height, torch.zeros(3, dtype=F32))
    torch.testing.assert_close(m[:, 8, 8], sums[:, 33])


@pytest.mark.skipif(not triton_available(), reason="needs triton (the dev extra installs it)")
def test_off_cuda_the_kernel_asks_for_the_interpreter() -> None:
    if os.environ.get("TRITON_INTERPRET") == "1":
        pytest.skip("this process runs Triton's interpreter")
    gm = random_map(10, seed=5, dtype=F32)
    cam = camera(dtype=F32)
    p = project_map(gm, cam)
    with pytest.raises(ValueError, match="TRITON_INTERPRET"):
        tile_moments(p.means2d, p.conics, p.opacities, p.colors, p.cov2d, p.radii, p.depths,
                     cam.width, cam.height)


cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


@pytest.mark.cuda
@cuda
@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize("residuals", ["channels", "pixels"])
def test_compiled_kernel_matches_the_pairs_on_cuda(dtype: torch.dtype, residuals: str) -> None:
    assert triton_available(), "CUDA builds of torch bring triton"
    gm = random_map(400, seed=4, deg=2, dtype=dtype).to(device="cuda")
    cam = camera(w=64, h=48, dtype=dtype).to(device="cuda")
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=dtype, device="cuda")
    assert gpu_moments_apply(None, gm.means)
    fast = screen_second_moments(gm, cam, background=bg, residuals=residuals)
    ref = screen_second_moments(gm, cam, background=bg, residuals=residuals, backend="torch")
    err = float((fast - ref).abs().max() / ref.abs().max())
    assert err < (1e-11 if dtype == F64 else 1e-5), err
    fd = fisher_diag(gm, cam, background=bg)
    fr = fisher_diag(gm, cam, background=bg, backend="torch")
    for f in FIELD_NAMES:
        e = float((fd[f] - fr[f]).abs().max() / fr[f].abs().max())
        assert e < (1e-10 if dtype == F64 else 1e-4), (f, e)
