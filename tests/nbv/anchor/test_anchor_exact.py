"""The exact psi on the compiled Fisher: its values against the torch path, its difference
gradients against autograd, the ascent with them against the reference ascent (float64)."""

from __future__ import annotations

import pytest
import torch
from conftest import TINY_INTR as INTR
from conftest import tiny_scene

from agilegs.config.selection import FIELD_NAMES, AnchorConfig
from agilegs.service.nbv.anchor import exact
from agilegs.service.nbv.anchor.ascent import _exp_at_zero, ascend, optimize_anchor
from agilegs.service.nbv.anchor.envelope import PoolEnvelope
from agilegs.service.nbv.anchor.exact import ExactPsi
from agilegs.service.nbv.kernels.backend import kernels_available, set_default_backend

pytestmark = pytest.mark.skipif(not kernels_available(), reason="numba kernels unavailable")

POSES = [1, 3, 5, 12, 17, 20]


@pytest.fixture(scope="module")
def sparse():
    """20 Gaussians: at these poses no cut-off of the rasterizer lies within 1e-7 of them,
    so psi is smooth there and differences converge to autograd."""
    gmap, pool, acq, h = tiny_scene(n=20)
    env = PoolEnvelope.from_pool(pool, gmap.means.median(dim=0).values)
    return gmap, pool, acq, h, env


def autograd_twist(psi: ExactPsi, poses: torch.Tensor, env: PoolEnvelope) -> torch.Tensor:
    xi = torch.zeros(poses.shape[0], 6, dtype=poses.dtype, requires_grad=True)
    val = psi(env.project(poses @ _exp_at_zero(xi)))
    (g,) = torch.autograd.grad(val.sum(), xi)
    return g


def test_compiled_values_equal_the_torch_path() -> None:
    gmap, pool, _, h = tiny_scene()
    cfg = AnchorConfig(psi="exact", resolution=24)
    fast = ExactPsi(gmap, h, INTR, cfg, FIELD_NAMES, backend="numba")
    ref = ExactPsi(gmap, h, INTR, cfg, FIELD_NAMES, backend="torch")
    assert fast.compiled(pool) and not ref.compiled(pool)
    with torch.no_grad():
        got, want = fast(pool[POSES]), ref(pool[POSES])
    torch.testing.assert_close(got, want, rtol=1e-10, atol=0.0)


@pytest.mark.parametrize("gradient", ["central", "forward"])
def test_difference_gradient_equals_autograd_where_psi_is_smooth(sparse, gradient) -> None:
    gmap, pool, _, h, env = sparse
    cfg = AnchorConfig(psi="exact", resolution=24)
    psi = ExactPsi(gmap, h, INTR, cfg, FIELD_NAMES, gradient=gradient, step=1e-7)
    poses = env.project(pool[POSES])
    want = autograd_twist(psi, poses, env)
    val, got = psi.twist_gradient(poses, envelope=env, radius=env.radius)
    w = torch.tensor([env.radius] * 3 + [1.0] * 3, dtype=torch.float64)  # the ascent's metric
    rel = ((got - want) * w).norm(dim=1) / (want * w).norm(dim=1)
    assert float(rel.max()) < 1e-4, rel
    with torch.no_grad():
        torch.testing.assert_close(val, psi(poses), rtol=1e-12, atol=0.0)


def test_difference_ascent_takes_the_reference_steps(sparse) -> None:
    """With a step at which the differences equal autograd, the ascent on compiled values
    and differences accepts the reference's steps (torch values, autograd). Without the
    envelope: on its bounds a difference is one-sided (the projection clamps the outward
    trial) where autograd passes the clamp's gradient or not by the last bit."""
    gmap, pool, _, h, env = sparse
    cfg = AnchorConfig(psi="exact", resolution=24, iterations=3, backtracks=3)
    starts = pool[[3, 12, 20]]
    fast = ExactPsi(gmap, h, INTR, cfg, FIELD_NAMES, gradient="forward", step=1e-7)
    ref = ExactPsi(gmap, h, INTR, cfg, FIELD_NAMES, backend="torch")
    split: dict[str, float] = {}
    calls: list[int] = []
    differences = fast.twist_gradient

    def counted(poses: torch.Tensor, **kw: object) -> tuple[torch.Tensor, torch.Tensor]:
        calls.append(poses.shape[0])
        return differences(poses, **kw)  # type: ignore[arg-type]

    fast.twist_gradient = counted  # type: ignore[method-assign]
    p_fast, v_fast, t_fast, _ = ascend(fast, starts, config=cfg, envelope=None,
                                       radius=env.radius, batched=False, split=split)
    p_ref, v_ref, t_ref, _ = ascend(ref, starts, config=cfg, envelope=None, radius=env.radius,
                                    batched=False, compiled=False)
    assert [len(t) for t in t_fast] == [len(t) for t in t_ref]
    assert max(len(t) for t in t_ref) > 1  # steps were taken
    torch.testing.assert_close(v_fast, v_ref, rtol=1e-5, atol=0.0)
    torch.testing.assert_close(p_fast, p_ref, rtol=0.0, atol=1e-5)
    assert calls and sum(calls) == split["gradient_evaluations"]  # differences, not autograd


def test_default_ascent_keeps_close_to_the_reference(monkeypatch) -> None:
    """At the default step the differences smooth over the rasterizer's cut-offs, so the two
    ascents part; on this map the anchor's psi stays within 5% of the reference's."""
    gmap, pool, acq, h = tiny_scene(n=120, seed=1)
    env = PoolEnvelope.from_pool(pool, gmap.means.median(dim=0).values)
    cfg = AnchorConfig(psi="exact", iterations=3, num_starts=2, resolution=24, anchors=1,
                       model="fitted", unexplored=False)

    def run() -> float:
        res = optimize_anchor(gmap, h, pool, INTR, config=cfg, num_acquired=3, envelope=env,
                              acquired=acq, generator=torch.Generator().manual_seed(0))
        assert all(b >= a for a, b in zip(res.psi_trace, res.psi_trace[1:]))
        return res.psi

    fast = run()
    set_default_backend("torch")
    try:
        ref = run()
    finally:
        set_default_backend(None)
    assert fast == pytest.approx(ref, rel=0.05)


def test_step_and_gradient_are_checked(sparse) -> None:
    gmap, pool, _, h, env = sparse
    cfg = AnchorConfig(psi="exact", resolution=24)
    with pytest.raises(ValueError, match="gradient"):
        ExactPsi(gmap, h, INTR, cfg, FIELD_NAMES, gradient="sideways")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="step"):
        ExactPsi(gmap, h, INTR, cfg, FIELD_NAMES, step=0.0)
    auto = ExactPsi(gmap, h, INTR, cfg, FIELD_NAMES, gradient="autograd")
    assert not auto.differences(pool)
    with pytest.raises(ValueError, match="autograd"):
        auto.twist_gradient(pool[:1], envelope=env, radius=env.radius)
    assert ExactPsi(gmap, h, INTR, cfg, FIELD_NAMES).step(torch.float64) == exact.MIN_STEP
    assert ExactPsi(gmap, h, INTR, cfg, FIELD_NAMES, gradient="central").step(
        torch.float32) == pytest.approx(torch.finfo(torch.float32).eps ** (1 / 3))
