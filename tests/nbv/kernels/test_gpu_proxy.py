"""The anchor's proxy ψ by the Triton kernels (kernels/gpu_proxy.py) against the pure-torch
reference: values, per-sample terms and gradients in the pose of every form the anchor
builds, on the CPU through Triton's interpreter (in a subprocess: the interpreter is chosen
when Triton is first imported), compiled for an sm_90 GPU without one, on CUDA (skipped
without a GPU: through ``ProxyPsi``'s dispatch, and the ascent's decisions); which path
serves."""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from conftest import ROOT, proxy_scene

from agilegs.config.selection import AnchorConfig
from agilegs.service.nbv.anchor.ascent import ascend
from agilegs.service.nbv.anchor.proxy import ProxyPsi
from agilegs.service.nbv.kernels import backend
from agilegs.service.nbv.kernels.gpu import triton_available
from agilegs.service.nbv.kernels.gpu_proxy import gpu_proxy_applies, proxy_kernel

F64, F32 = torch.float64, torch.float32
HERE = ROOT / "tests"
needs_triton = pytest.mark.skipif(not triton_available(),
                                  reason="needs triton (the dev extra installs it)")

_COMPARE = textwrap.dedent("""
    import json, sys, torch
    sys.path.insert(0, {here!r})
    from agilegs.service.nbv.kernels.gpu_proxy import proxy_kernel
    from conftest import proxy_scene

    def rel(a, b):
        return float((a.double() - b.double()).abs().max() / b.double().abs().max())

    dt = getattr(torch, {dtype!r})
    poses, proxies = proxy_scene(dt)
    out = {{}}
    for name, proxy in proxies:
        c2w = poses.clone().requires_grad_(True)
        ref = proxy.reference(c2w)
        (g_ref,) = torch.autograd.grad(ref.sum(), c2w)
        got, g_got = proxy_kernel(proxy, poses, want_grad=True)
        val, none = proxy_kernel(proxy, poses, want_grad=False)
        terms, acc = proxy_kernel(proxy, poses, want_grad=False, per_sample=True,
                                  axes=proxy.axes)
        with torch.no_grad():
            t_ref = proxy.reference(poses, per_sample=True)
            seen = proxy.seen(poses)
        out[name] = dict(
            psi=rel(got, ref.detach()), grad=rel(g_got, g_ref), terms=rel(terms, t_ref),
            per_pose=max(max(rel(got[i], ref[i].detach()), rel(g_got[i], g_ref[i]))
                         for i in range(len(got))),
            same=bool(torch.equal(val, got)) and none is None,
            acc=None if acc is None else list(acc.shape),
            dtype=str(got.dtype), grad_dtype=str(g_got.dtype),
            last_row=float(g_got[:, 3].abs().max()),
            hidden=float((seen < 0.9).double().mean()), shown=float((seen > 0.5).double().mean()))
    print(json.dumps(out))
""")

TOLERANCE = {"float64": 1e-12, "float32": 2e-6}
"""The largest difference allowed, relative to the reference's largest value (ψ, its
gradient, the per-sample terms): float64's rounding, float32's (measured: 2e-15 and
6e-7); each pose's ψ and gradient relative to their own within ten times that (measured:
3e-15 and 5e-6: the pose inside the cloud, whose ψ is small)."""


@needs_triton
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_interpreted_kernel_matches_the_torch_path(dtype: str) -> None:
    env = {**os.environ, "TRITON_INTERPRET": "1"}
    proc = subprocess.run(
        [sys.executable, "-c", _COMPARE.format(here=str(HERE), dtype=dtype)],
        capture_output=True, text=True, env=env, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads(proc.stdout.strip().splitlines()[-1])
    assert set(results) == {"linear/grid", "log/grid", "directional/grid", "linear/none",
                            "log/none", "directional/none", "directional/extended"}
    tol = TOLERANCE[dtype]
    for name, r in results.items():
        assert r["psi"] < tol and r["grad"] < tol and r["terms"] < tol, (name, r)
        assert r["per_pose"] < 10 * tol, (name, r)  # each pose's ψ and gradient alike
        assert r["same"], name  # ψ alone is ψ of the gradient's launch
        assert r["dtype"] == r["grad_dtype"] == f"torch.{dtype}", name
        assert r["last_row"] == 0.0, name
        assert (r["acc"] is not None) == name.startswith("directional"), name
    # the scene reaches every branch: samples off the image and behind occluders
    assert results["linear/grid"]["hidden"] > 0.2 and results["linear/grid"]["shown"] > 0.2


_DISPATCH = textwrap.dedent("""
    import json, sys, torch
    sys.path.insert(0, {here!r})
    from agilegs.config.selection import AnchorConfig
    from agilegs.service.nbv import se3_exp
    from agilegs.service.nbv.anchor.ascent import ascend
    from agilegs.service.nbv.kernels import backend, gpu_proxy
    from conftest import proxy_scene

    calls = []
    launch = gpu_proxy.proxy_launch

    def counted(*args, **kwargs):
        calls.append(args[1].shape[0])
        return launch(*args, **kwargs)

    # what serves CUDA tensors serves these, through the interpreter
    gpu_proxy.gpu_proxy_applies = lambda backend_, c2w, means: (
        (backend_ or backend.default_backend()) != "torch")
    gpu_proxy.proxy_launch = counted
    poses, proxies = proxy_scene(torch.float64, n=60, samples=30, poses=3)
    proxy = dict(proxies)["directional/grid"]
    out = dict(uses=proxy.uses_kernel(poses))
    xi = torch.zeros(3, 6, dtype=torch.float64, requires_grad=True)
    got = proxy(poses @ se3_exp(xi))
    (g_got,) = torch.autograd.grad(got.sum(), xi)
    xi = torch.zeros(3, 6, dtype=torch.float64, requires_grad=True)
    ref = proxy.reference(poses @ se3_exp(xi))
    (g_ref,) = torch.autograd.grad(ref.sum(), xi)
    out["psi"] = float((got - ref).abs().max() / ref.abs().max())
    out["twist"] = float((g_got - g_ref).abs().max() / g_ref.abs().max())
    checks = []
    calls.clear()
    whole = proxy.values_in_parts(poses, 1, lambda: checks.append(1))
    out.update(parts_launches=list(calls), parts_checks=len(checks),
               parts=float((whole - got.detach()).abs().max()))
    terms, acc = proxy.terms_and_factors(poses, proxy.axes)
    w = proxy.reference(poses, per_sample=True)
    f = proxy.direction_factors(poses)
    out["acc"] = float(((w.unsqueeze(-1) * f).sum(0) - acc).abs().max() / acc.abs().max())
    cfg = AnchorConfig(iterations=2, backtracks=2, step_size=0.3, min_rel_gain=1e-3)
    runs = []
    for b in ("auto", "torch"):
        backend.set_default_backend(b)
        calls.clear()
        p, v, t, e = ascend(proxy, poses[:2], config=cfg, envelope=None, radius=1.0,
                            compiled=False)
        runs.append(dict(v=v.tolist(), t=t, e=e, launches=len(calls)))
    backend.set_default_backend(None)
    out["ascents"] = runs
    print(json.dumps(out))
""")


@needs_triton
def test_the_proxy_dispatches_to_the_kernels_and_the_ascent_steps_alike() -> None:
    # ProxyPsi's hook, its autograd function, the pool's single launch, the directional
    # fit's sums and the ascent, with the kernels serving CPU tensors through the interpreter
    # as they serve CUDA tensors compiled
    env = {**os.environ, "TRITON_INTERPRET": "1"}
    proc = subprocess.run([sys.executable, "-c", _DISPATCH.format(here=str(HERE))],
                          capture_output=True, text=True, env=env, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    assert r["uses"]
    assert r["psi"] < 1e-12 and r["twist"] < 1e-12 and r["acc"] < 1e-12, r
    assert r["parts_launches"] == [3] and r["parts_checks"] == 1 and r["parts"] < 1e-12, r
    kern, ref = r["ascents"]
    assert kern["launches"] > 0 and ref["launches"] == 0
    # the same steps taken, ψ alike along them
    assert [len(t) for t in kern["t"]] == [len(t) for t in ref["t"]] and kern["e"] == ref["e"]
    for tk, tr in zip(kern["t"] + [kern["v"]], ref["t"] + [ref["v"]], strict=True):
        assert max(abs(a - b) / abs(b) for a, b in zip(tk, tr, strict=True)) < 1e-12, r
    assert sum(len(t) - 1 for t in ref["t"]) > 0, r  # steps were taken


_COMPILE = textwrap.dedent("""
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource
    from agilegs.service.nbv.kernels import gpu_proxy_kernel as k

    target = GPUTarget("cuda", 90, 32)

    def build(fn, sig, const, name):
        src = ASTSource(fn=fn, signature=dict(sig, **dict.fromkeys(const, "constexpr")),
                        constexprs=const)
        out = triton.compile(src, target=target, options={"num_warps": 4})
        assert len(out.asm["cubin"]) > 1000
        print(name, "ok")

    ptrs = ("cam_ptr", "prm_ptr", "means_ptr", "sig_ptr", "w_ptr", "rate_ptr", "axes_ptr",
            "cum_ptr", "part_ptr", "terms_ptr")
    sig = {p: "*fp64" for p in ptrs}
    sig.update(kinds_ptr="*i32", S="i32", Q="i32", CHUNK="i32", CELLS="i32", BINS="i32")
    for mode, grid, grad, per in ((2, True, True, False), (2, True, False, False),
                                  (2, True, False, True), (1, True, True, False),
                                  (0, False, True, False)):
        build(k.psi_kernel, sig, dict(MODE=mode, HAS_GRID=grid, WANT_GRAD=grad,
                                      PER_SAMPLE=per, BLOCK=128), "psi" + str(mode))
    build(k.deposit_kernel, {"cam_ptr": "*fp64", "prm_ptr": "*fp64", "occ_ptr": "*fp64",
                              "mass_ptr": "*fp64", "grid_ptr": "*fp64", "M": "i32",
                              "CELLS": "i32", "BINS": "i32"}, {"BLOCK": 256}, "deposit")
    build(k.cumulate_kernel, {"grid_ptr": "*fp64", "cum_ptr": "*fp64", "CELLS": "i32",
                               "BINS": "i32"}, {"LANES": 256}, "cumulate")
""")


@needs_triton
def test_the_kernels_compile_for_a_hopper_gpu_without_one(tmp_path: Path) -> None:
    # Triton's frontend, its passes and its bundled ptxas run on any machine: the kernels'
    # typing is checked here, where no GPU runs them (the interpreter does not type them)
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    env["TRITON_CACHE_DIR"] = str(tmp_path)  # compiled here, not read from a cache
    proc = subprocess.run([sys.executable, "-c", _COMPILE], capture_output=True, text=True,
                          env=env, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.split() == ["psi2", "ok"] * 3 + ["psi1", "ok", "psi0", "ok", "deposit",
                                                         "ok", "cumulate", "ok"]


def test_the_cpu_paths_serve_off_cuda() -> None:
    poses, proxies = proxy_scene(F64, n=40, samples=20, poses=2)
    proxy = dict(proxies)["directional/grid"]
    assert not gpu_proxy_applies(None, poses, proxy.means)
    assert not gpu_proxy_applies("torch", poses, proxy.means)
    assert proxy.uses_kernel(poses) == backend.kernels_available()  # numba, as before


@needs_triton
def test_off_cuda_the_kernel_asks_for_the_interpreter() -> None:
    if os.environ.get("TRITON_INTERPRET") == "1":
        pytest.skip("this process runs Triton's interpreter")
    poses, proxies = proxy_scene(F64, n=40, samples=20, poses=2)
    with pytest.raises(ValueError, match="TRITON_INTERPRET"):
        proxy_kernel(dict(proxies)["linear/grid"], poses, want_grad=False)


cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


def _on_cuda(proxy: ProxyPsi) -> ProxyPsi:
    """The proxy with its tensors on the GPU."""
    def dev(t: torch.Tensor | None) -> torch.Tensor | None:
        return None if t is None else t.cuda()

    grid = proxy.grid
    if grid is not None:
        grid = dataclasses.replace(grid, means=grid.means.cuda(), mass=grid.mass.cuda(),
                                   center=grid.center.cuda())
    return dataclasses.replace(proxy, means=proxy.means.cuda(), cov=proxy.cov.cuda(),
                               weight=proxy.weight.cuda(), grid=grid, rate=dev(proxy.rate),
                               slot_kinds=dev(proxy.slot_kinds), axes=dev(proxy.axes))


@pytest.mark.cuda
@cuda
@pytest.mark.parametrize("dtype", [F64, F32])
def test_the_proxy_runs_the_triton_kernels_on_cuda(dtype: torch.dtype) -> None:
    assert triton_available(), "CUDA builds of torch bring triton"
    poses, proxies = proxy_scene(dtype, n=400, samples=300, poses=12)
    poses = poses.cuda()
    tol = 1e-11 if dtype == F64 else 1e-5
    for name, cpu_proxy in proxies:
        proxy = _on_cuda(cpu_proxy)
        assert proxy.uses_kernel(poses), name
        c2w = poses.clone().requires_grad_(True)
        got = proxy(c2w)
        (g_got,) = torch.autograd.grad(got.sum(), c2w)
        c2w = poses.clone().requires_grad_(True)
        ref = proxy.reference(c2w)
        (g_ref,) = torch.autograd.grad(ref.sum(), c2w)
        assert float((got - ref).abs().max() / ref.abs().max()) < tol, name
        assert float((g_got - g_ref).abs().max() / g_ref.abs().max()) < tol, name
        with torch.no_grad():
            t = proxy(poses, per_sample=True)
            t_ref = proxy.reference(poses, per_sample=True)
        assert float((t - t_ref).abs().max() / t_ref.abs().max()) < tol, name
        calls: list[int] = []
        whole = proxy.values_in_parts(poses, 4, functools.partial(calls.append, 1))
        assert len(calls) == 1  # every pose in one launch, one check before it
        torch.testing.assert_close(whole, got.detach(), rtol=tol, atol=0)  # atomic adds
        # the ascent from three starts takes the same steps either way
        cfg = AnchorConfig(iterations=4, backtracks=3, step_size=0.3, min_rel_gain=1e-3)
        runs = []
        for b in ("auto", "torch"):
            try:
                backend.set_default_backend(b)  # type: ignore[arg-type]
                runs.append(ascend(proxy, poses[:3].detach(), config=cfg, envelope=None,
                                   radius=1.0))
            finally:
                backend.set_default_backend(None)
        (p_k, v_k, t_k, _), (p_r, v_r, t_r, _) = runs
        assert [len(t) for t in t_k] == [len(t) for t in t_r], name
        torch.testing.assert_close(v_k, v_r, rtol=1e-9 if dtype == F64 else 1e-4, atol=0)
