"""The compiled kernel of the anchor's proxy psi against its pure-torch reference: values,
per-sample terms and gradients in the pose (float64), the ascent's decisions, threads, the
dispatch, and the anchor's cancellation points; the compiled line search of the ascent
against the reference ascent."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from agilegs.config.selection import FIELD_NAMES, AnchorConfig
from agilegs.service.nbv import (
    Camera,
    GaussianMap,
    Intrinsics,
    accumulate_information,
    cancel,
    fisher_diag,
    init_information,
    se3_exp,
)
from agilegs.service.nbv.anchor.ascent import _exp_at_zero, ascend, optimize_anchor
from agilegs.service.nbv.anchor.envelope import PoolEnvelope
from agilegs.service.nbv.anchor.fitting import directional_rates, lower_median
from agilegs.service.nbv.anchor.line_search import CompiledLineSearch
from agilegs.service.nbv.anchor.proxy import ProxyPsi, direction_factors
from agilegs.service.nbv.anchor.visibility import OpacityMaps
from agilegs.service.nbv.candidates import capture_pool, scene_center_radius
from agilegs.service.nbv.kernels import backend

pytestmark = pytest.mark.skipif(not backend.kernels_available(), reason="numba unavailable")

INTR = Intrinsics.from_fov(55.0, 40, 32)
F64 = torch.float64


def _scene(dtype: torch.dtype = F64) -> tuple[GaussianMap, torch.Tensor, torch.Tensor,
                                             dict[str, torch.Tensor]]:
    g = torch.Generator().manual_seed(0)
    n = 300
    pts = 0.3 * torch.randn(n, 3, generator=g, dtype=F64)
    gmap = GaussianMap.from_points(pts, torch.rand(n, 3, generator=g, dtype=F64), scale=0.05,
                                   opacity=0.7)
    # anisotropic, rotated Gaussians: every term of the footprint matters
    gmap = GaussianMap(means=gmap.means, log_scales=gmap.log_scales
                       + 0.5 * torch.randn(n, 3, generator=g, dtype=F64),
                       quats=torch.randn(n, 4, generator=g, dtype=F64),
                       opacity_logits=gmap.opacity_logits, sh=gmap.sh).to(dtype=dtype)
    centre, r98 = scene_center_radius(gmap.means)
    poses = capture_pool(centre, 2.6 * r98, 24, seed=0).to(dtype)
    acquired, pool = poses[:3], poses[3:]
    h = init_information(gmap, 1e-6)
    with torch.no_grad():
        for p in acquired:
            h = accumulate_information(h, fisher_diag(gmap, Camera(c2w=p, intrinsics=INTR)))
    return gmap, acquired, pool, h


def _proxies(gmap: GaussianMap, acquired: torch.Tensor, h: dict[str, torch.Tensor]
             ) -> list[tuple[str, ProxyPsi]]:
    centre, r98 = scene_center_radius(gmap.means)
    gen = torch.Generator().manual_seed(1)
    grid = OpacityMaps.build(gmap, INTR, centre, r98, max_occluders=150, generator=gen)
    near, edge = 0.05 * r98, 2.0
    dr = directional_rates(gmap, h, acquired, INTR, FIELD_NAMES, near=near, edge=edge,
                           grid=grid)
    c = torch.log1p(dr.rate * dr.typical).sum(1)
    out = []
    for vis in ("transmittance", "none"):
        kw = dict(near=near, edge=edge, generator=gen, grid=grid if vis != "none" else None)
        out += [
            (f"linear/{vis}", ProxyPsi.build(gmap, c, INTR, num_samples=120, **kw)),
            (f"log/{vis}", ProxyPsi.build(gmap, c, INTR, num_samples=120,
                                          rate=dr.rate[:, 0], slots=3, **kw)),
            (f"directional/{vis}", ProxyPsi.build(gmap, c, INTR, num_samples=120,
                                                  rate=dr.rate, slot_kinds=dr.kinds, **kw)),
        ]
    # with extra samples appended (unexplored space: world axes)
    name, last = out[2]
    extra = last.means[:5] + 0.05
    out.append(("directional/extended", last.extended(
        extra, 1e-3 * torch.eye(3, dtype=extra.dtype).expand(5, 3, 3),
        torch.ones(5, dtype=extra.dtype), last.rate[:5] if last.rate is not None else None)))
    return out


def _moved(pool: torch.Tensor, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    xi = (0.1 * torch.randn(pool.shape[0], 6, generator=g, dtype=F64)).to(pool.dtype)
    xi.requires_grad_(True)
    return xi, pool @ se3_exp(xi)


def test_kernel_equals_the_reference_float64() -> None:
    gmap, acquired, pool, h = _scene()
    for name, proxy in _proxies(gmap, acquired, h):
        xi, moved = _moved(pool, 2)
        assert proxy.uses_kernel(moved), name
        got = proxy(moved)
        (g_got,) = torch.autograd.grad(got.sum(), xi)
        xi2, moved2 = _moved(pool, 2)
        ref = proxy.reference(moved2)
        (g_ref,) = torch.autograd.grad(ref.sum(), xi2)
        assert float(ref.detach().abs().max()) > 0 and float(g_ref.abs().max()) > 0, name
        torch.testing.assert_close(got, ref, rtol=1e-10,
                                   atol=1e-12 * float(ref.detach().abs().max()))
        torch.testing.assert_close(g_got, g_ref, rtol=1e-8,
                                   atol=1e-10 * float(g_ref.abs().max()))
        with torch.no_grad():
            torch.testing.assert_close(proxy(pool, per_sample=True),
                                       proxy.reference(pool, per_sample=True),
                                       rtol=1e-10, atol=1e-14)


def test_kernel_gradcheck() -> None:
    gmap, acquired, pool, h = _scene()
    # without the deep opacity map: its deposit is piecewise constant in the pose and held
    # fixed in the gradient (as by the reference), which finite differences would see
    proxy = dict(_proxies(gmap, acquired, h))["directional/none"]
    base = pool[:3]

    def psi(xi: torch.Tensor) -> torch.Tensor:
        return proxy(base @ se3_exp(xi))

    xi = (0.05 * torch.randn(3, 6, generator=torch.Generator().manual_seed(3), dtype=F64))
    assert torch.autograd.gradcheck(psi, (xi.requires_grad_(True),), eps=1e-7, atol=1e-5,
                                    rtol=1e-4)


def test_kernel_float32_is_close() -> None:
    gmap, acquired, pool, h = _scene(torch.float32)
    for name, proxy in _proxies(gmap, acquired, h):
        with torch.no_grad():
            got, ref = proxy(pool), proxy.reference(pool)
        assert got.dtype == torch.float32, name
        torch.testing.assert_close(got, ref, rtol=2e-4, atol=1e-5 * float(ref.abs().max()))


def test_threads_do_not_change_the_result() -> None:
    gmap, acquired, pool, h = _scene()
    proxy = dict(_proxies(gmap, acquired, h))["directional/transmittance"]
    try:
        backend.set_kernel_threads(1)
        one = proxy(pool)
        backend.set_kernel_threads(3)
        three = proxy(pool)
    finally:
        backend.set_kernel_threads(None)
    assert torch.equal(one, three)


def test_dispatch() -> None:
    gmap, acquired, pool, h = _scene()
    proxy = dict(_proxies(gmap, acquired, h))["log/transmittance"]
    try:
        backend.set_default_backend("torch")
        assert not proxy.uses_kernel(pool)
    finally:
        backend.set_default_backend(None)
    assert proxy.uses_kernel(pool)
    # the point z-buffer has no kernel
    zb = ProxyPsi.build(gmap, torch.ones(gmap.num_gaussians, dtype=F64), INTR, num_samples=0,
                        near=0.05, edge=2.0, generator=None, num_occluders=50)
    assert zb.occluders is not None and not zb.uses_kernel(pool)


def test_the_ascent_decides_alike_with_either_path() -> None:
    gmap, acquired, pool, h = _scene()
    cfg = AnchorConfig(num_gaussians=150, occluders=150, unexplored_cells=6)
    results = {}
    for b in ("torch", "numba"):
        try:
            backend.set_default_backend(b)  # type: ignore[arg-type]
            results[b] = optimize_anchor(gmap, h, pool, INTR, config=cfg, acquired=acquired,
                                         generator=torch.Generator().manual_seed(0), lam=1e-6)
        finally:
            backend.set_default_backend(None)
    t, k = results["torch"], results["numba"]
    assert t.diagnostics.start_indices == k.diagnostics.start_indices
    assert t.evaluations == k.evaluations
    torch.testing.assert_close(k.c2w, t.c2w, rtol=0, atol=1e-9)
    assert k.psi == pytest.approx(t.psi, rel=1e-10)
    assert set(k.diagnostics.timings_s) == {"visibility", "rates", "unexplored", "starts",
                                         "ascent"}


class _Stop(Exception):
    pass


def test_the_anchor_checks_for_cancellation_at_every_stage_and_step() -> None:
    gmap, acquired, pool, h = _scene()
    cfg = AnchorConfig(num_gaussians=150, occluders=150, unexplored_cells=6)
    calls: list[int] = []

    def count() -> None:
        calls.append(1)

    with cancel.scope(count):
        res = optimize_anchor(gmap, h, pool, INTR, config=cfg, acquired=acquired,
                              generator=torch.Generator().manual_seed(0), lam=1e-6)
    steps = sum(len(t) - 1 for t in res.traces)
    # the five stages, and the ascent's every iteration and step
    assert len(calls) >= 5 + steps + 1

    def stop() -> None:
        raise _Stop

    with cancel.scope(stop), pytest.raises(_Stop):
        optimize_anchor(gmap, h, pool, INTR, config=cfg, acquired=acquired, lam=1e-6)


def test_terms_and_direction_factors_equal_the_reference() -> None:
    gmap, acquired, pool, h = _scene()
    proxy = dict(_proxies(gmap, acquired, h))["directional/transmittance"]
    assert proxy.axes is not None
    w, wf = proxy.terms_and_factors(pool, proxy.axes)
    ref_w = proxy.reference(pool, per_sample=True)
    f = direction_factors(proxy.means, pool[:, :3, 3], proxy.axes)
    torch.testing.assert_close(w, ref_w, rtol=1e-10, atol=1e-14)
    torch.testing.assert_close(wf, (ref_w.unsqueeze(-1) * f).sum(0), rtol=1e-10, atol=1e-13)
    assert float(wf[:, 3].sum()) < float(wf[:, 0].sum())  # a factor is at most 1


@pytest.mark.parametrize("n", [1, 2, 7, 10])
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_lower_median_is_torch_median(n: int, dtype: torch.dtype) -> None:
    x = torch.randn(n, generator=torch.Generator().manual_seed(n), dtype=dtype)
    x[0] = x[-1]  # a tie
    got = lower_median(x)
    assert got.dtype == dtype and torch.equal(got, x.median())
    x[1 % n] = float("nan")
    assert torch.isnan(lower_median(x)) == torch.isnan(x.median())


def _envelope(pool: torch.Tensor, gmap: GaussianMap) -> PoolEnvelope:
    centre, _ = scene_center_radius(gmap.means)
    return PoolEnvelope.from_pool(pool, centre.to(pool.dtype), 0.05)


def test_the_line_search_kernels_pose_maths_equals_torch() -> None:
    gmap, _, pool, _ = _scene()
    env = _envelope(pool, gmap)
    kern = backend.kernel_module()
    g = torch.Generator().manual_seed(4)
    # twists on both sides of se3_exp's Taylor branch (t^2 < 1e-2)
    xi = torch.randn(40, 6, generator=g, dtype=F64) * torch.tensor([0.02, 0.5]).repeat_interleave(
        20).unsqueeze(1)
    got = np.zeros((4, 4))
    for x, ref in zip(xi, se3_exp(xi)):
        kern.se3_exp_into(x.numpy().copy(), got)
        np.testing.assert_allclose(got, ref.numpy(), rtol=0, atol=1e-15)
    # poses moved off the pool, far out and turned away: every clamp of the envelope acts
    moved = pool @ se3_exp(torch.randn(pool.shape[0], 6, generator=g, dtype=F64)
                           * torch.tensor([1.5, 1.5, 1.5, 0.8, 0.8, 0.8], dtype=F64))
    ref = env.project(moved)
    assert not bool(env.contains(moved).all())
    prm = CompiledLineSearch(dict(_proxies(gmap, _scene()[1], _scene()[3]))["linear/none"],
                      AnchorConfig(), env, env.radius, F64).env
    for m, r in zip(moved, ref):
        kern.envelope_project_into(m.numpy().copy(), prm, got)
        np.testing.assert_allclose(got, r.numpy(), rtol=0, atol=1e-12)
    kern.envelope_project_into(moved[0].numpy().copy(), np.zeros(15), got)  # no envelope
    np.testing.assert_array_equal(got, moved[0].numpy())


def _ascents(dtype: torch.dtype, with_envelope: bool, iterations: int
             ) -> list[tuple[str, tuple, dict, tuple, dict]]:
    """The compiled and the reference ascent of every proxy form from four pool starts."""
    gmap, acquired, pool, h = _scene(dtype)
    env = _envelope(pool, gmap) if with_envelope else None
    radius = env.radius if env is not None else 1.0
    cfg = AnchorConfig(iterations=iterations, backtracks=4, step_size=0.3, min_rel_gain=1e-3)
    starts = pool[torch.tensor([0, 5, 9, 14])]
    out = []
    for name, proxy in _proxies(gmap, acquired, h):
        runs = []
        for compiled in (True, False):
            split: dict[str, float] = {}
            runs += [ascend(proxy, starts, config=cfg, envelope=env, radius=radius,
                            split=split, compiled=compiled), split]
        out.append((name, *runs))
    return out


@pytest.mark.parametrize(("dtype", "with_envelope", "iterations"),
                         [(F64, True, 8), (F64, False, 8), (torch.float32, True, 3)])
def test_the_compiled_line_search_equals_the_reference_ascent(
        dtype: torch.dtype, with_envelope: bool, iterations: int) -> None:
    # long ascents from several starts: steps accepted, trials rejected and halved, starts
    # stopping by the gain rule and by a failed line search. The ascent is not continuous
    # in the pose at the envelope's bounds (a pose the projection put on a bound passes the
    # clamp's gradient or not by the last bit), so only the same numbers bit for bit are
    # the same ascent: the compiled search only finds the accepted trial, which the
    # reference's operations then compute
    backtracked = 0
    for name, (p_k, v_k, t_k, e_k), s_k, (p_r, v_r, t_r, e_r), s_r in _ascents(
            dtype, with_envelope, iterations):
        assert e_k == e_r, name
        assert s_k["value_evaluations"] == s_r["value_evaluations"], name
        assert s_k["gradient_evaluations"] == s_r["gradient_evaluations"], name
        assert t_k == t_r, name
        assert torch.equal(p_k, p_r), name
        assert torch.equal(v_k, v_r), name
        assert p_k.dtype == v_k.dtype == dtype
        assert sum(len(t) - 1 for t in t_r) > 0, name  # steps were taken
        backtracked += int(s_r["value_evaluations"]) - sum(len(t) - 1 for t in t_r)
    assert backtracked > 0  # some trials were rejected


def test_a_trial_the_reference_rejects_is_searched_again_by_the_reference(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # a compiled search that claims the first trial of every start: where the reference's
    # check rejects it, that start's line search is the reference's
    search = CompiledLineSearch.search

    def first(self: CompiledLineSearch, *args: object) -> tuple[list[int], list[int]]:
        found, counts = search(self, *args)  # type: ignore[arg-type]
        return [1] * len(found), counts

    monkeypatch.setattr(CompiledLineSearch, "search", first)
    redone = 0
    for name, (p_k, v_k, t_k, e_k), _, (p_r, v_r, t_r, e_r), s_r in _ascents(F64, True, 8):
        assert t_k == t_r and torch.equal(p_k, p_r) and torch.equal(v_k, v_r), name
        assert e_k == e_r, name
        redone += int(s_r["value_evaluations"]) > sum(len(t) - 1 for t in t_r)
    assert redone > 0


def test_the_compiled_line_search_serves_only_the_proxy_kernel() -> None:
    gmap, acquired, pool, h = _scene()
    proxy = dict(_proxies(gmap, acquired, h))["directional/transmittance"]
    assert CompiledLineSearch.serves(proxy, pool)
    assert not CompiledLineSearch.serves(lambda c2w: c2w[:, 0, 3], pool)
    assert not CompiledLineSearch.serves(proxy, pool.to(torch.float16))
    try:
        backend.set_default_backend("torch")
        assert not CompiledLineSearch.serves(proxy, pool)
    finally:
        backend.set_default_backend(None)


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_the_twist_gradient_at_zero_equals_the_exponentials(dtype: torch.dtype) -> None:
    # the ascent differentiates psi(project(T exp(xi))) at xi = 0 through I + hat(xi): the
    # same value and gradient, bit for bit, as through se3_exp
    gmap, acquired, pool, h = _scene(dtype)
    env = _envelope(pool, gmap)
    xi0 = 0.3 * torch.randn(pool.shape[0], 6, generator=torch.Generator().manual_seed(1),
                            dtype=F64)
    poses = env.project(pool @ se3_exp(xi0.to(dtype)))
    for name, proxy in _proxies(gmap, acquired, h):
        out = []
        for exp in (se3_exp, _exp_at_zero):
            xi = torch.zeros(poses.shape[0], 6, dtype=dtype, requires_grad=True)
            val = proxy(env.project(poses @ exp(xi)))
            (g,) = torch.autograd.grad(val.sum(), xi)
            out.append((val.detach(), g))
        assert float(out[0][1].abs().max()) > 0, name
        assert torch.equal(out[0][0], out[1][0]) and torch.equal(out[0][1], out[1][1]), name


def test_values_in_parts_are_the_values_with_a_check_before_each_part() -> None:
    gmap, acquired, pool, h = _scene()
    calls: list[int] = []

    def between() -> None:
        calls.append(1)

    parts = -(-pool.shape[0] // 8)
    for name, proxy in _proxies(gmap, acquired, h):
        calls.clear()
        with torch.no_grad():
            whole = proxy(pool)
            got = proxy.values_in_parts(pool, 8, between)
        assert torch.equal(got, whole), name
        assert len(calls) == parts, name
        try:
            backend.set_default_backend("torch")
            calls.clear()
            ref = proxy.values_in_parts(pool, 8, between)
        finally:
            backend.set_default_backend(None)
        assert len(calls) == parts, name
        torch.testing.assert_close(ref, whole, rtol=1e-10, atol=1e-12 * float(whole.abs().max()))
