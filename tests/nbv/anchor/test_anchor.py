"""The anchor ascent: monotone psi, the pool envelope, the proxy's parts, the exact psi."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from conftest import TINY_INTR as INTR
from conftest import tiny_scene

from agilegs.config.selection import FIELD_NAMES, AnchorConfig
from agilegs.service.nbv import (
    Camera,
    GaussianMap,
    accumulate_information,
    check_pose,
    fisher_diag,
    init_information,
    look_at,
    se3_exp,
)
from agilegs.service.nbv.anchor.ascent import ascend, optimize_anchor
from agilegs.service.nbv.anchor.envelope import PoolEnvelope
from agilegs.service.nbv.anchor.fitting import (
    information_weights,
    observation_rates,
    typical_fisher_from_h_acc,
    typical_fisher_from_views,
)
from agilegs.service.nbv.anchor.proxy import ProxyPsi


@pytest.fixture(scope="module")
def scene():
    return tiny_scene()


def test_accepted_steps_never_lower_psi(scene) -> None:
    gmap, pool, acq, h = scene
    aim = gmap.means.median(dim=0).values
    env = PoolEnvelope.from_pool(pool, aim)
    cfg = AnchorConfig(iterations=8, step_size=0.3, num_starts=4)
    res = optimize_anchor(
        gmap,
        h,
        pool,
        INTR,
        config=cfg,
        num_acquired=3,
        envelope=env,
        generator=torch.Generator().manual_seed(0),
    )
    assert len(res.traces) == 4
    for trace in res.traces:
        assert all(b >= a for a, b in zip(trace, trace[1:])), trace
    assert res.psi == max(t[-1] for t in res.traces)
    assert res.psi_trace[-1] == res.psi
    assert any(len(t) > 1 for t in res.traces)  # some step was accepted
    check_pose(res.c2w.unsqueeze(0))


def test_line_search_rejects_steps_that_lower_psi() -> None:
    # psi = -(distance of the camera from a target)^2: a huge step overshoots and must be
    # rejected and halved; the trace still never decreases
    target = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)

    def psi(c2w: torch.Tensor) -> torch.Tensor:
        return -((c2w[:, :3, 3] - target) ** 2).sum(-1)

    start = torch.eye(4, dtype=torch.float64).unsqueeze(0)
    cfg = AnchorConfig(iterations=30, step_size=5.0, backtracks=10, min_rel_gain=0.0)
    poses, vals, traces, _ = ascend(psi, start, config=cfg, envelope=None, radius=1.0)
    assert all(b >= a for a, b in zip(traces[0], traces[0][1:]))
    assert float(vals[0]) > -1e-3  # it converged to the target all the same
    torch.testing.assert_close(poses[0, :3, 3], target, atol=0.05, rtol=0)


def test_envelope_projection(scene) -> None:
    _, pool, _, _ = scene
    aim = torch.zeros(3, dtype=torch.float64)
    env = PoolEnvelope.from_pool(pool, aim, margin=0.0)
    assert bool(env.contains(pool).all())
    # pool poses are unchanged by the projection
    torch.testing.assert_close(env.project(pool), pool)
    # poses inside the object, far away, straight above, looking away: all pulled back
    bad = torch.stack(
        [
            look_at(
                torch.tensor([0.05, 0.0, 0.0], dtype=torch.float64),
                torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64),
            ),
            look_at(torch.tensor([0.0, -0.5, -20.0], dtype=torch.float64), aim),
            look_at(torch.tensor([0.0, -3.0, 0.01], dtype=torch.float64), aim),
            look_at(
                torch.tensor([0.0, -0.5, -2.0], dtype=torch.float64),
                torch.tensor([0.0, -0.5, -5.0], dtype=torch.float64),
            ),
        ]
    )
    assert not bool(env.contains(bad).any())
    fixed = env.project(bad)
    check_pose(fixed)
    assert bool(env.contains(fixed).all())


def test_anchor_stays_in_envelope_and_runs_into_the_object_without_it(scene) -> None:
    gmap, pool, _, h = scene
    aim = gmap.means.median(dim=0).values
    env = PoolEnvelope.from_pool(pool, aim)
    cfg = AnchorConfig(iterations=25, step_size=0.5, min_rel_gain=0.0, num_starts=2)
    gen = torch.Generator().manual_seed(0)
    guarded = optimize_anchor(
        gmap, h, pool, INTR, config=cfg, num_acquired=3, envelope=env, generator=gen
    )
    assert bool(env.contains(guarded.c2w.unsqueeze(0)).all())
    free = optimize_anchor(
        gmap,
        h,
        pool,
        INTR,
        config=cfg,
        num_acquired=3,
        envelope=None,
        generator=torch.Generator().manual_seed(0),
    )
    # unguarded, psi rewards closeness: the anchor leaves the pool's radius range
    d_free = float((free.c2w[:3, 3] - env.centre).norm())
    assert d_free < env.r_min or not bool(env.contains(free.c2w.unsqueeze(0)).all())


def test_warm_start_is_one_of_the_starts(scene) -> None:
    gmap, pool, _, h = scene
    warm = pool[5].clone()
    cfg = AnchorConfig(iterations=0, num_starts=2)
    res = optimize_anchor(
        gmap, h, pool, INTR, config=cfg, warm_c2w=warm, generator=torch.Generator().manual_seed(0)
    )
    assert res.starts.shape[0] == 3
    torch.testing.assert_close(res.starts[-1], warm)
    cold = optimize_anchor(
        gmap,
        h,
        pool,
        INTR,
        config=AnchorConfig(iterations=0, num_starts=2, warm_start=False),
        warm_c2w=warm,
    )
    assert cold.starts.shape[0] == 2


@pytest.mark.parametrize("anchors", [1, 3])
def test_starts_are_the_best_pool_candidates_under_the_proxy(scene, anchors: int) -> None:
    from agilegs.service.nbv.anchor.ascent import distinct_best
    from agilegs.service.nbv.candidates import pool_radius

    gmap, pool, _, h = scene
    cfg = AnchorConfig(iterations=0, num_starts=3, anchors=anchors)
    res = optimize_anchor(gmap, h, pool, INTR, config=cfg,
                          generator=torch.Generator().manual_seed(0))
    assert res.pool_psi is not None
    if anchors == 1:  # the top three
        best = torch.topk(res.pool_psi, 3).indices.tolist()
    else:  # the best three of distinct modes
        r = pool_radius(pool)
        best = distinct_best(pool, res.pool_psi, 3, cfg.mode_separation * r, r).tolist()
        assert len(best) == 3 and best != torch.topk(res.pool_psi, 3).indices.tolist()
    assert res.diagnostics.start_indices == best
    assert res.psi == pytest.approx(float(res.pool_psi.max()), rel=1e-9)


def test_proxy_twist_gradient_matches_finite_differences(scene) -> None:
    gmap, pool, _, h = scene
    typical = typical_fisher_from_h_acc(h, 3, FIELD_NAMES)
    c = information_weights(h, typical, FIELD_NAMES)
    proxy = ProxyPsi.build(gmap, c, INTR, num_samples=0, near=0.1, edge=1.6, generator=None)
    base = pool[3:4]
    xi = torch.zeros(1, 6, dtype=torch.float64, requires_grad=True)
    val = proxy(base @ se3_exp(xi))
    (g,) = torch.autograd.grad(val.sum(), xi)
    eps = 1e-6
    fd = torch.zeros(6, dtype=torch.float64)
    for k in range(6):
        e = torch.zeros(1, 6, dtype=torch.float64)
        e[0, k] = eps
        fd[k] = (proxy(base @ se3_exp(e)) - proxy(base @ se3_exp(-e)))[0] / (2 * eps)
    torch.testing.assert_close(g[0], fd, rtol=1e-5, atol=1e-6 * float(fd.abs().max()))


def test_importance_sampling_is_unbiased_and_seeded(scene) -> None:
    gmap, pool, _, h = scene
    typical = typical_fisher_from_h_acc(h, 3, FIELD_NAMES)
    c = information_weights(h, typical, FIELD_NAMES)
    full = ProxyPsi.build(gmap, c, INTR, num_samples=0, near=0.1, edge=1.6, generator=None)
    vals = []
    for seed in range(20):
        s = ProxyPsi.build(
            gmap,
            c,
            INTR,
            num_samples=60,
            near=0.1,
            edge=1.6,
            generator=torch.Generator().manual_seed(seed),
        )
        vals.append(s(pool[:4]))
    mean = torch.stack(vals).mean(0)
    torch.testing.assert_close(mean, full(pool[:4]), rtol=0.15, atol=0)
    a = ProxyPsi.build(
        gmap,
        c,
        INTR,
        num_samples=60,
        near=0.1,
        edge=1.6,
        generator=torch.Generator().manual_seed(3),
    )
    b = ProxyPsi.build(
        gmap,
        c,
        INTR,
        num_samples=60,
        near=0.1,
        edge=1.6,
        generator=torch.Generator().manual_seed(3),
    )
    assert torch.equal(a.weight, b.weight) and torch.equal(a.means, b.means)


def test_typical_fisher_estimates() -> None:
    n = 100
    lam = 1e-6
    h_view = {"means": torch.full((n, 3), 2.0, dtype=torch.float64)}
    h_view["means"][:10] = 0.0  # unseen Gaussians keep lambda
    h_acc = {"means": lam + 3 * h_view["means"]}  # three views like this one
    m = typical_fisher_from_h_acc(h_acc, 3, ("means",))
    torch.testing.assert_close(m["means"], torch.full((3,), 2.0, dtype=torch.float64))
    m2 = typical_fisher_from_views([h_view], ("means",))
    torch.testing.assert_close(m2["means"], torch.full((3,), 2.0, dtype=torch.float64))
    w = information_weights(h_acc, m, ("means",))
    assert float(w[0]) == pytest.approx(3 * math.log1p(2.0 / lam))
    assert float(w[50]) == pytest.approx(3 * math.log1p(2.0 / (lam + 6.0)))


def test_typical_fisher_and_rates_use_the_given_lambda(scene) -> None:
    """When every Gaussian is seen, the minimum over Gaussians is not lambda: given lambda,
    the fit separates the views' information from the prior exactly."""
    n = 50
    lam = 1e-3
    h_view = {"means": torch.linspace(1.0, 3.0, n, dtype=torch.float64)[:, None].expand(n, 3)}
    h_acc = {"means": lam + 2 * h_view["means"]}  # every Gaussian seen by two views
    m = typical_fisher_from_h_acc(h_acc, 2, ("means",), lam=lam)
    med = float(h_view["means"][:, 0].median())
    torch.testing.assert_close(m["means"], torch.full((3,), med, dtype=torch.float64))
    guessed = typical_fisher_from_h_acc(h_acc, 2, ("means",))  # lambda taken as the minimum
    assert float(guessed["means"][0]) < 0.9 * med
    gmap, _, acq, h = scene
    h_lam = {k: v.clone() for k, v in h.items()}  # built with lambda 1e-6
    fit = observation_rates(gmap, h_lam, acq, INTR, FIELD_NAMES, lam=1e-6, **FIT_KW)
    r = torch.zeros(gmap.num_gaussians, dtype=torch.float64)
    for f in FIELD_NAMES:
        flat = h_lam[f].reshape(gmap.num_gaussians, -1)
        r += ((flat - 1e-6) / flat).clamp(0, 1).sum(1)
    r /= fit.slots
    seen = fit.accumulated >= 0.25 * fit.typical
    torch.testing.assert_close(fit.rate[seen], (r / fit.accumulated)[seen])


def test_exact_psi_renders_on_the_given_background(scene) -> None:
    from agilegs.service.nbv import trace_surrogate
    from agilegs.service.nbv.anchor.exact import exact_psi_fn

    gmap, pool, _, h = scene
    bg = torch.tensor([0.2, 0.9, 0.4], dtype=torch.float64)
    cfg = AnchorConfig(psi="exact", resolution=16)
    fn = exact_psi_fn(gmap, h, INTR, cfg, FIELD_NAMES, background=bg)
    cam = Camera(c2w=pool[3], intrinsics=INTR.scaled(16, 16))
    with torch.no_grad():
        ref = trace_surrogate(fisher_diag(gmap, cam, background=bg), h)
        black = trace_surrogate(fisher_diag(gmap, cam), h)
        got = fn(pool[3:4])[0]
    assert float(got) == pytest.approx(float(ref), rel=1e-9)
    assert abs(float(ref) - float(black)) > 1e-3 * float(black)


def test_exact_psi_ascent_is_monotone() -> None:
    gmap, pool, _, h = tiny_scene(n=120, seed=1)
    aim = gmap.means.median(dim=0).values
    env = PoolEnvelope.from_pool(pool, aim)
    cfg = AnchorConfig(psi="exact", iterations=2, num_starts=1, resolution=24, backtracks=2)
    res = optimize_anchor(
        gmap,
        h,
        pool,
        INTR,
        config=cfg,
        num_acquired=3,
        envelope=env,
        generator=torch.Generator().manual_seed(0),
    )
    trace = res.psi_trace
    assert all(b >= a for a, b in zip(trace, trace[1:]))
    # the reported psi is the exact trace surrogate at the anchor
    from agilegs.service.nbv import trace_surrogate

    small = INTR.scaled(24, 24)
    with torch.no_grad():
        ref = trace_surrogate(fisher_diag(gmap, Camera(c2w=res.c2w, intrinsics=small)), h)
    assert res.psi == pytest.approx(float(ref), rel=1e-6)


def test_bad_anchor_config_raises() -> None:
    for kwargs, word in [
        ({"psi": "bogus"}, "psi"),
        ({"iterations": -1}, "iterations"),
        ({"step_size": 0.0}, "step_size"),
        ({"num_starts": 0}, "num_starts"),
        ({"resolution": 2}, "resolution"),
        ({"occlusion_tests": ((2, 0.02),)}, "occlusion_tests"),
        ({"occlusion_tests": ((0, 0.02),)}, "occlusion_tests"),
        ({"occlusion_tests": ((1, -0.1),)}, "occlusion_tests"),
        ({"occlusion_tests": ()}, "occlusion_tests"),
        ({"occlusion_tests": ((3, "0.1"),)}, "occlusion_tests"),
    ]:
        with pytest.raises(ValueError, match=word):
            AnchorConfig(**kwargs).validate()  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- fitted model
FIT_KW = dict(near=0.1, edge=1.6, num_occluders=0, occ_grid=48, occ_tests=((1, 0.02),))


def _terms(gmap, poses):
    ones = torch.ones(gmap.num_gaussians, dtype=gmap.dtype)
    full = ProxyPsi.build(gmap, ones, INTR, num_samples=0, near=0.1, edge=1.6, generator=None)
    return full(poses, per_sample=True)


def test_observation_rates_follow_the_acquired_views(scene) -> None:
    gmap, _, acq, h = scene
    once = observation_rates(gmap, h, acq[:1], INTR, FIELD_NAMES, **FIT_KW)
    twice = observation_rates(gmap, h, torch.cat([acq[:1], acq[:1]]), INTR, FIELD_NAMES, **FIT_KW)
    terms = _terms(gmap, acq[:1])[0]
    torch.testing.assert_close(once.accumulated, terms)
    torch.testing.assert_close(twice.accumulated, 2 * terms)
    assert once.typical == pytest.approx(float(terms[terms > 1e-6].median()))
    assert once.slots == sum(getattr(gmap, f)[0].numel() for f in FIELD_NAMES)
    seen = terms >= 0.25 * once.typical
    assert seen.sum() > 10
    # the same Hhat spread over twice the observation: half the rate
    torch.testing.assert_close(twice.rate[seen], once.rate[seen] / 2)


def test_observation_rates_of_unconstrained_and_unseen_gaussians(scene) -> None:
    gmap, _, acq, h = scene
    h = {k: v.clone() for k, v in h.items()}
    terms = _terms(gmap, acq).sum(0)
    fit0 = observation_rates(gmap, h, acq, INTR, FIELD_NAMES, **FIT_KW)
    seen = torch.nonzero(terms >= 0.25 * fit0.typical).squeeze(1)
    hidden = int(seen[0])  # seen by the proxy, but Hhat says no view constrains it
    for k in h:
        h[k][hidden] = h[k].reshape(h[k].shape[0], -1).amin(0).reshape(h[k].shape[1:])
    means = gmap.means.detach().clone()
    behind = 1  # moved behind every acquired camera: the proxy never sees it
    means[behind] = acq[0, :3, 3] - 5.0 * acq[0, :3, 2]
    moved = dataclasses.replace(gmap.clone(), means=means)
    fit = observation_rates(moved, h, acq[:1], INTR, FIELD_NAMES, **FIT_KW)
    assert float(fit.rate[hidden]) == 0.0
    assert float(fit.accumulated[behind]) < 1e-9
    assert float(fit.rate[behind]) == pytest.approx(4.0 / fit.typical)


def test_log_form_proxy_and_its_importance_sampling(scene) -> None:
    gmap, pool, acq, h = scene
    fit = observation_rates(gmap, h, acq, INTR, FIELD_NAMES, **FIT_KW)
    c = fit.slots * torch.log1p(fit.rate * fit.typical)
    kw = dict(near=0.1, edge=1.6, rate=fit.rate, slots=fit.slots)
    full = ProxyPsi.build(gmap, c, INTR, num_samples=0, generator=None, **kw)
    want = (fit.slots * torch.log1p(fit.rate * _terms(gmap, pool[:4]))).sum(1)
    torch.testing.assert_close(full(pool[:4]), want)
    vals = [
        ProxyPsi.build(
            gmap, c, INTR, num_samples=60, generator=torch.Generator().manual_seed(s), **kw
        )(pool[:4])
        for s in range(30)
    ]
    torch.testing.assert_close(torch.stack(vals).mean(0), want, rtol=0.15, atol=0)


@pytest.mark.parametrize("model", ["fitted", "directional"])
def test_fitted_model_ranks_the_pool_like_the_exact_eig(model: str) -> None:
    """Views of the side no acquired view saw score high under the proxy and the exact EIG."""
    from agilegs.service.nbv import eig_scores

    gmap, pool, _, _ = tiny_scene(n=300, seed=1)
    acq = pool[[0, 1, 2]]  # neighbours in capture order: one side of the blob
    h = init_information(gmap, 1e-6)
    with torch.no_grad():
        for p in acq:
            h = accumulate_information(h, fisher_diag(gmap, Camera(c2w=p, intrinsics=INTR)))
    phi = eig_scores(gmap, h, pool, INTR)
    gen = torch.Generator().manual_seed(0)
    fitted = optimize_anchor(
        gmap, h, pool, INTR, config=AnchorConfig(iterations=0, model=model, unexplored=False),
        acquired=acq, generator=gen
    )
    assert fitted.diagnostics.model.model == model
    assert fitted.pool_psi is not None

    def ranks(x: torch.Tensor) -> torch.Tensor:
        return x.argsort().argsort().double()

    rho = float(torch.corrcoef(torch.stack([ranks(fitted.pool_psi), ranks(phi)]))[0, 1])
    assert rho > 0.5, rho
    best = int(fitted.pool_psi.argmax())
    assert float((phi < phi[best]).double().mean()) >= 0.75
    typical = optimize_anchor(
        gmap, h, pool, INTR, config=AnchorConfig(iterations=0), generator=gen
    )
    assert typical.diagnostics.model.model == "typical"


def test_occluder_cover_closes_gaps_between_occluder_points() -> None:
    """A sample behind a sparse wall of occluder points leaks through a gap when each occluder
    covers its own cell and is hidden when it covers 3x3 cells; with both tests its visibility
    is their mean; a sample in front of the wall stays visible in every case."""
    dt = torch.float64
    cam = look_at(torch.tensor([0.0, 0.0, -4.0], dtype=dt), torch.zeros(3, dtype=dt))
    # a wall at z = 0 facing the camera, points every other z-buffer cell (gaps between)
    grid = 16
    k = INTR
    z_wall = 4.0
    cells = torch.arange(1, grid, 2, dtype=dt)
    px = (cells + 0.5) * k.width / grid
    u, v = torch.meshgrid(px, px, indexing="xy")
    x = (u.reshape(-1) - k.cx) / k.fx * z_wall
    y = (v.reshape(-1) - k.cy) / k.fy * z_wall
    cam_pts = torch.stack([x, y, torch.full_like(x, z_wall)], dim=1)
    rot, t = cam[:3, :3], cam[:3, 3]
    wall = cam_pts @ rot.T + t
    # samples: one behind the wall in a gap cell, one in front of it
    gap_px = (8 + 0.5) * k.width / grid  # an even cell index: between wall points
    behind_c = torch.tensor(
        [(gap_px - k.cx) / k.fx * 6.0, (gap_px - k.cy) / k.fy * 6.0, 6.0], dtype=dt
    )
    gap2_px = (12 + 0.5) * k.width / grid  # another gap, away from the first
    front_c = torch.tensor(
        [(gap2_px - k.cx) / k.fx * 2.0, (gap2_px - k.cy) / k.fy * 2.0, 2.0], dtype=dt
    )
    samples = torch.stack([behind_c, front_c]) @ rot.T + t
    gmap = GaussianMap.from_points(samples, torch.rand(2, 3, dtype=dt), scale=0.01, opacity=0.9)
    vis = {}
    for tests in (((1, 0.02),), ((3, 0.02),), ((1, 0.02), (3, 0.02))):
        proxy = ProxyPsi.build(
            gmap, torch.ones(2, dtype=dt), INTR, num_samples=0, near=0.1, edge=1.6,
            generator=None, occ_grid=grid, occ_tests=tests, occluders=wall,
        )
        vis[tests] = proxy.visibility(cam.unsqueeze(0))[0].tolist()
    assert vis[((1, 0.02),)] == [1.0, 1.0]  # the hidden sample leaks through the gap
    assert vis[((3, 0.02),)] == [0.0, 1.0]  # covered; the near one is not
    assert vis[((1, 0.02), (3, 0.02))] == [0.5, 1.0]  # two tests: the mean


# ----------------------------------------------------------------------------- transmittance
def _wall(n_side: int = 24, z: float = 0.0, opacity: float = 0.95, scale: float = 0.08):
    """A square wall of Gaussians in the plane z = ``z`` (facing a camera on the -z axis)."""
    u = torch.linspace(-0.6, 0.6, n_side, dtype=torch.float64)
    yy, xx = torch.meshgrid(u, u, indexing="ij")
    pts = torch.stack([xx.flatten(), yy.flatten(), torch.full_like(xx.flatten(), z)], dim=1)
    return GaussianMap.from_points(pts, torch.full_like(pts, 0.5), scale=scale, opacity=opacity)


def test_transmittance_through_a_wall_and_in_front_of_it() -> None:
    from agilegs.service.nbv.anchor.visibility import OpacityMaps

    wall = _wall()
    cam = look_at(torch.tensor([0.0, 0.0, -3.0], dtype=torch.float64),
                  torch.zeros(3, dtype=torch.float64))[None]
    maps = OpacityMaps.build(wall, INTR, torch.zeros(3, dtype=torch.float64), 1.0)
    pts = torch.tensor([[0.0, 0.0, 0.5],    # behind the wall
                        [0.1, -0.1, -0.5],  # in front of it
                        [0.0, 0.0, 0.0]],   # on it: its own slab is not in front of it
                       dtype=torch.float64)
    t = maps.transmittance(cam, pts)[0]
    assert float(t[0]) < 0.05
    assert float(t[1]) > 0.99 and float(t[2]) > 0.9
    # a faint wall hides less; two walls hide more than one
    faint = OpacityMaps.build(_wall(opacity=0.2), INTR, torch.zeros(3, dtype=torch.float64),
                              1.0).transmittance(cam, pts)[0]
    assert float(t[0]) < float(faint[0]) < 1.0
    a, b = _wall(z=-0.2, opacity=0.2), _wall(opacity=0.2)
    double = GaussianMap(**{k: torch.cat([getattr(a, k), getattr(b, k)]) for k in FIELD_NAMES})
    two = OpacityMaps.build(double, INTR, torch.zeros(3, dtype=torch.float64),
                            1.0).transmittance(cam, pts)[0]
    assert float(two[0]) < float(faint[0])


def test_transmittance_is_differentiable_in_the_pose() -> None:
    from agilegs.service.nbv.anchor.visibility import OpacityMaps

    wall = _wall(n_side=12, scale=0.05)
    maps = OpacityMaps.build(wall, INTR, torch.zeros(3, dtype=torch.float64), 1.0)
    cam = look_at(torch.tensor([0.3, 0.2, -3.0], dtype=torch.float64),
                  torch.zeros(3, dtype=torch.float64))[None]
    xi = torch.zeros(1, 6, dtype=torch.float64, requires_grad=True)
    pts = torch.tensor([[0.05, 0.02, 0.4]], dtype=torch.float64)
    t = maps.transmittance(cam @ se3_exp(xi), pts)
    (g,) = torch.autograd.grad(t.sum(), xi)
    assert torch.isfinite(g).all() and float(g.abs().sum()) > 0
