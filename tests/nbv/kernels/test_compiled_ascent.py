"""The anchor's ascent compiled (:class:`agilegs.service.nbv.anchor.compiled_ascent.
CompiledAscent`) against the reference (:class:`agilegs.service.nbv.anchor.ascent.Ascent`):
the projection's derivatives in the twist against torch's autograd, the ascent's poses, ψ and
evaluations against the reference's, and the anchor's decision with either."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_proxy_kernel import INTR, _envelope, _proxies, _scene

from agilegs.config.selection import AnchorConfig
from agilegs.service.nbv import cancel, se3_exp
from agilegs.service.nbv.anchor import ascent as ascent_mod
from agilegs.service.nbv.anchor.ascent import Ascent, _exp_at_zero, optimize_anchor
from agilegs.service.nbv.anchor.compiled_ascent import CompiledAscent
from agilegs.service.nbv.anchor.line_search import envelope_vector
from agilegs.service.nbv.kernels import backend

pytestmark = pytest.mark.skipif(not backend.kernels_available(), reason="numba unavailable")

F64 = torch.float64


def _torch_tangents(pose: torch.Tensor, env: object) -> tuple[torch.Tensor, torch.Tensor]:
    """The camera row [12] of the projected pose and its Jacobian in the twist [6, 12] by
    torch's autograd (the reference's operations)."""
    def row(xi: torch.Tensor) -> torch.Tensor:
        moved = pose.unsqueeze(0) @ _exp_at_zero(xi.unsqueeze(0))
        out = env.project(moved)[0] if env is not None else moved[0]  # type: ignore[attr-defined]
        return torch.cat([out[:3, :3].reshape(9), out[:3, 3]])

    xi = torch.zeros(6, dtype=pose.dtype)
    jac = torch.autograd.functional.jacobian(row, xi)  # [12, 6]
    return row(xi).detach(), jac.T


@pytest.mark.parametrize("with_envelope", [True, False])
def test_the_projected_tangents_equal_torch_s_autograd(with_envelope: bool) -> None:
    gmap, _, pool, _ = _scene()
    env = _envelope(pool, gmap) if with_envelope else None
    vec = envelope_vector(env, F64)
    kern = backend.kernel_module()
    g = torch.Generator().manual_seed(4)
    # poses in the pool, moved off it (beyond its radius and elevation, turned away from
    # the aim: every clamp of the envelope acts), and projected back onto its bounds
    moved = pool @ se3_exp(torch.randn(pool.shape[0], 6, generator=g, dtype=F64)
                           * torch.tensor([1.5, 1.5, 1.5, 0.8, 0.8, 0.8], dtype=F64))
    poses = torch.cat([pool, moved] + ([env.project(moved)] if env is not None else []))
    cams, dcams = np.empty((1, 12)), np.empty((6, 12))
    compared = 0
    for p in poses:
        kern.projected_tangents(p.numpy().copy(), vec, cams, dcams)
        row, jac = _torch_tangents(p, env)
        np.testing.assert_allclose(cams[0], row.numpy(), rtol=0, atol=1e-12)
        if env is not None and _on_a_bound(p, env):
            continue  # a clamp's gradient passes there or not by the last bit of the radius
        np.testing.assert_allclose(dcams, jac.numpy(), rtol=1e-9, atol=1e-9)
        compared += 1
    assert compared >= 2 * pool.shape[0]  # the pool and the moved poses at least


def _on_a_bound(pose: torch.Tensor, env: object) -> bool:
    """Whether a pose's distance or elevation lies within rounding of the envelope's bound."""
    rel = pose[:3, 3] - env.centre  # type: ignore[attr-defined]
    r = float(rel.norm())
    elev = float(torch.asin((rel @ env.up) / r))  # type: ignore[attr-defined]
    bounds = [(r, env.r_min), (r, env.r_max), (elev, env.elev_min),  # type: ignore[attr-defined]
              (elev, env.elev_max)]  # type: ignore[attr-defined]
    return any(abs(a - b) <= 1e-12 * max(1.0, abs(b)) for a, b in bounds)


def _both(dtype: torch.dtype, with_envelope: bool, iterations: int, name: str
          ) -> tuple[CompiledAscent, Ascent]:
    gmap, acquired, pool, h = _scene(dtype)
    env = _envelope(pool, gmap) if with_envelope else None
    radius = env.radius if env is not None else 1.0
    cfg = AnchorConfig(iterations=iterations, backtracks=4, step_size=0.3, min_rel_gain=1e-3)
    starts = pool[torch.tensor([0, 5, 9, 14])]
    proxy = dict(_proxies(gmap, acquired, h))[name]
    assert CompiledAscent.serves(proxy, starts)
    fast = CompiledAscent(proxy, starts, config=cfg, envelope=env, radius=radius).run()
    ref = Ascent(proxy, starts, config=cfg, envelope=env, radius=radius).run()
    return fast, ref


NAMES = ["linear/transmittance", "log/none", "directional/transmittance",
         "directional/extended"]


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize(("dtype", "iterations"),
                         [(F64, 3), (F64, 8), (torch.float32, 3), (torch.float32, 8)])
def test_the_compiled_ascent_takes_the_reference_s_steps(
        name: str, dtype: torch.dtype, iterations: int) -> None:
    # without the envelope: steps accepted, trials rejected and halved, starts stopping by
    # the gain rule and by a failed line search, all as the reference's
    fast, ref = _both(dtype, False, iterations, name)
    assert fast.poses.dtype == fast.cur.dtype == dtype
    tol = 1e-9 if dtype == F64 else 2e-6
    assert [len(t) for t in fast.traces] == [len(t) for t in ref.traces], name
    assert fast.evaluations == ref.evaluations, name
    assert fast.tally.gradient_evaluations == ref.tally.gradient_evaluations
    assert fast.tally.value_evaluations == ref.tally.value_evaluations
    for tf, tr in zip(fast.traces, ref.traces):
        np.testing.assert_allclose(tf, tr, rtol=tol, atol=0)
    torch.testing.assert_close(fast.poses, ref.poses, rtol=tol, atol=tol)
    torch.testing.assert_close(fast.cur, ref.cur, rtol=tol, atol=0)
    assert sum(len(t) - 1 for t in ref.traces) > 0  # steps were taken
    assert ref.tally.value_evaluations > sum(len(t) for t in ref.traces)  # and trials halved
    assert fast.tally.gradient_s > 0 and fast.tally.value_s > 0


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_within_the_envelope_the_compiled_ascent_is_the_reference_to_its_own_spread(
        name: str, dtype: torch.dtype) -> None:
    # The ascent is not continuous in the pose at the envelope's bounds: a pose projected
    # onto a bound passes a clamp's gradient or not by the last bit of its recomputed
    # radius, so a start that reaches a bound may take another way in either path, as the
    # reference itself does from starts moved by one ulp. Every start still ascends within
    # the envelope, and the best start's psi stays within that spread of the reference's.
    fast, ref = _both(dtype, True, 3, name)
    gmap, _, pool, _ = _scene(dtype)
    env = _envelope(pool, gmap)
    assert bool(env.contains(fast.poses, tol=1e-5).all())
    for t in fast.traces:
        assert all(b >= a for a, b in zip(t, t[1:]))
    assert float(fast.cur.max()) == pytest.approx(float(ref.cur.max()), rel=0.03)


def test_the_reference_ascent_itself_moves_at_the_envelope_s_bounds() -> None:
    """The spread the test above allows: the reference from starts moved by one ulp."""
    gmap, acquired, pool, h = _scene(torch.float32)
    env = _envelope(pool, gmap)
    cfg = AnchorConfig(iterations=3, backtracks=4, step_size=0.3, min_rel_gain=1e-3)
    starts = pool[torch.tensor([0, 5, 9, 14])]
    nudged = torch.nextafter(starts, torch.full_like(starts, float("inf")))
    proxy = dict(_proxies(gmap, acquired, h))["directional/transmittance"]
    a = Ascent(proxy, starts, config=cfg, envelope=env, radius=env.radius).run()
    b = Ascent(proxy, nudged, config=cfg, envelope=env, radius=env.radius).run()
    assert float((a.cur - b.cur).abs().max() / a.cur.abs().max()) > 1e-3


def test_the_anchor_decides_alike_with_the_compiled_ascent(
        monkeypatch: pytest.MonkeyPatch) -> None:
    gmap, acquired, pool, h = _scene()
    cfg = AnchorConfig(num_gaussians=150, occluders=150, unexplored_cells=6)

    def anchor() -> object:
        return optimize_anchor(gmap, h, pool, INTR, config=cfg, acquired=acquired,
                               generator=torch.Generator().manual_seed(0), lam=1e-6)

    fast = anchor()
    monkeypatch.setattr(ascent_mod.CompiledAscent, "serves", staticmethod(lambda *a: False))
    ref = anchor()
    assert fast.diagnostics.start_indices == ref.diagnostics.start_indices  # type: ignore[attr-defined]
    assert fast.evaluations == ref.evaluations  # type: ignore[attr-defined]
    torch.testing.assert_close(fast.c2w, ref.c2w, rtol=0, atol=1e-9)  # type: ignore[attr-defined]
    assert fast.psi == pytest.approx(ref.psi, rel=1e-9)  # type: ignore[attr-defined]


def test_the_compiled_ascent_checks_for_cancellation_before_every_step() -> None:
    fast, _ = _both(F64, True, 3, "directional/transmittance")
    calls: list[int] = []
    gmap, acquired, pool, h = _scene()
    env = _envelope(pool, gmap)
    proxy = dict(_proxies(gmap, acquired, h))["directional/transmittance"]
    cfg = AnchorConfig(iterations=3, backtracks=4, step_size=0.3, min_rel_gain=1e-3)
    run = CompiledAscent(proxy, pool[torch.tensor([0, 5, 9, 14])], config=cfg, envelope=env,
                         radius=env.radius)
    with cancel.scope(lambda: calls.append(1)):
        run.run()
    assert len(calls) >= sum(len(t) - 1 for t in run.traces) + 1
