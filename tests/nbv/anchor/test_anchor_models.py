"""The proxy's directional model and its unexplored space, against the exact Fisher and by
construction."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from agilegs.config.selection import FIELD_NAMES, AnchorConfig
from agilegs.service.nbv import (
    Camera,
    GaussianMap,
    Intrinsics,
    accumulate_information,
    fisher_diag,
    init_information,
    look_at,
)
from agilegs.service.nbv.anchor.ascent import optimize_anchor
from agilegs.service.nbv.anchor.fitting import directional_rates, slot_kinds
from agilegs.service.nbv.anchor.proxy import DIRECTION_KINDS, ProxyPsi, direction_factors
from agilegs.service.nbv.anchor.unexplored import unexplored_space
from agilegs.service.nbv.anchor.visibility import OpacityMaps
from agilegs.service.nbv.candidates import capture_pool, scene_center_radius

INTR = Intrinsics.from_fov(55.0, 32, 32)
F64 = torch.float64


def _pose(eye: list[float]) -> torch.Tensor:
    return look_at(torch.tensor(eye, dtype=F64), torch.zeros(3, dtype=F64))


def test_direction_factors_vanish_along_the_ray() -> None:
    # a camera on the z axis looking at the origin: the ray is world z
    pts = torch.zeros(1, 3, dtype=F64)
    centres = torch.tensor([[0.0, 0.0, -2.0]], dtype=F64)
    theta = 0.3
    rot = torch.tensor([[math.cos(theta), 0.0, math.sin(theta)], [0.0, 1.0, 0.0],
                        [-math.sin(theta), 0.0, math.cos(theta)]], dtype=F64)
    f = direction_factors(pts, centres, rot.unsqueeze(0))[0, 0]
    assert len(DIRECTION_KINDS) == f.numel() == 7
    assert f[0] == 1.0
    torch.testing.assert_close(f[1:4], torch.tensor([1.0, 1.0, 0.0], dtype=F64))
    # local axes: the columns of rot; their z components are -sin, 0, cos
    torch.testing.assert_close(
        f[4:], 1.0 - torch.tensor([-math.sin(theta), 0.0, math.cos(theta)], dtype=F64) ** 2)
    # without axes the local factors are 1
    assert bool((direction_factors(pts, centres, None)[0, 0, 4:] == 1).all())


def test_exact_fisher_of_a_mean_is_small_along_the_ray() -> None:
    # the assumption behind the directional model, checked on the exact Fisher: a camera
    # on the z axis learns little about the means' z and much about x and y
    g = torch.Generator().manual_seed(0)
    pts = 0.05 * torch.randn(40, 3, generator=g, dtype=F64)
    gmap = GaussianMap.from_points(pts, torch.rand(40, 3, generator=g, dtype=F64), scale=0.03,
                                   opacity=0.6)
    h = fisher_diag(gmap, Camera(c2w=_pose([0.0, 0.0, -2.0]), intrinsics=INTR))["means"]
    seen = h.sum(1) > 0
    assert int(seen.sum()) >= 20
    total = h[seen].sum(0)
    assert float(total[2]) < 0.05 * float(total[:2].min())


def _blob(n: int = 200, seed: int = 0) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    pts = 0.3 * torch.randn(n, 3, generator=g, dtype=F64)
    cols = torch.rand(n, 3, generator=g, dtype=F64)
    return GaussianMap.from_points(pts, cols, scale=0.05, opacity=0.7)


def _h_acc(gmap: GaussianMap, poses: torch.Tensor, lam: float) -> dict[str, torch.Tensor]:
    h = init_information(gmap, lam)
    with torch.no_grad():
        for p in poses:
            h = accumulate_information(h, fisher_diag(gmap, Camera(c2w=p, intrinsics=INTR)))
    return h


def _seer(gmap: GaussianMap) -> ProxyPsi:
    centre, r98 = scene_center_radius(gmap.means)
    grid = OpacityMaps.build(gmap, INTR, centre, r98)
    return ProxyPsi.build(gmap, torch.ones(gmap.num_gaussians, dtype=F64), INTR, num_samples=0,
                          near=0.05, edge=1.6, generator=None, grid=grid)


def test_directional_rates_reproduce_h_acc_where_seen() -> None:
    # by construction: for every slot the acquired views saw, rate * W = (Hhat - lambda) / Hhat
    gmap = _blob()
    lam = 1e-3
    acq = torch.stack([_pose([0.0, 0.0, -2.0]), _pose([0.0, 0.0, 2.0])])
    h = _h_acc(gmap, acq, lam)
    seer = _seer(gmap)
    fit = directional_rates(gmap, h, acq, INTR, FIELD_NAMES, near=seer.near, edge=seer.edge,
                            grid=seer.grid, lam=lam)
    kinds = slot_kinds(h, FIELD_NAMES)
    assert fit.rate.shape == (gmap.num_gaussians, kinds.numel())
    assert kinds[:3].tolist() == [1, 2, 3] and kinds[3:6].tolist() == [4, 5, 6]
    assert bool((kinds[6:] == 0).all())
    flat = torch.cat([h[f].reshape(gmap.num_gaussians, -1) for f in FIELD_NAMES], dim=1)
    w = fit.accumulated[:, kinds]
    floor = 0.25 * fit.typical * torch.tensor([1.0] + [2.0 / 3.0] * 6, dtype=F64)[kinds]
    seen = w >= floor
    assert bool(seen.any())
    torch.testing.assert_close((fit.rate * w)[seen], ((flat - lam) / flat)[seen])
    # both views look along world z: the means' z slots were seen less than x and y
    assert float(fit.accumulated[:, 3].sum()) < 0.2 * float(fit.accumulated[:, 1].sum())
    # a never-seen slot's rate: the seen slots' median information per unit of term, over
    # lambda (the quaternions of these isotropic Gaussians carry no information: 0)
    g = (flat - lam) / w.clamp_min(1e-30)
    for q in (0, 2, 3, 10):
        torch.testing.assert_close(fit.prior_rate[q], g[seen[:, q], q].median() / lam)
    assert bool((fit.prior_rate[:6] > 0).all()) and bool((fit.prior_rate[6:10] == 0).all())
    # slots no acquired view saw take that median as their information per unit of term
    unseen = ~seen[:, 2]
    if bool(unseen.any()):
        torch.testing.assert_close(fit.rate[unseen, 2] * flat[unseen, 2],
                                   g[seen[:, 2], 2].median().expand(int(unseen.sum())))


def test_the_directional_anchor_looks_across_the_acquired_views() -> None:
    # views along z leave the means' z unconstrained: the directional model rates a view
    # along x above one along z (the isotropic fitted model cannot tell them apart by
    # direction)
    gmap = _blob()
    lam = 1e-3
    acq = torch.stack([_pose([0.0, 0.0, -2.0]), _pose([0.0, 0.0, 2.0])])
    h = _h_acc(gmap, acq, lam)
    pool = torch.stack([_pose([0.0, 0.0, -2.05]), _pose([2.0, 0.0, 0.0])])
    cfg = AnchorConfig(model="directional", iterations=0, num_starts=2, num_gaussians=0,
                       envelope=False)
    res = optimize_anchor(gmap, h, pool, INTR, config=cfg, acquired=acq, lam=lam,
                          generator=torch.Generator().manual_seed(0))
    assert res.pool_psi is not None
    assert float(res.pool_psi[1]) > 1.2 * float(res.pool_psi[0])
    assert res.diagnostics.model.model == "directional"


def _half_shell(n: int = 400) -> GaussianMap:
    # Gaussians on the z < 0 half of a sphere: the other half is unexplored
    g = torch.Generator().manual_seed(1)
    d = torch.randn(n, 3, generator=g, dtype=F64)
    d = d / d.norm(dim=1, keepdim=True)
    d[:, 2] = -d[:, 2].abs()
    return GaussianMap.from_points(0.4 * d, torch.rand(n, 3, generator=g, dtype=F64),
                                   scale=0.04, opacity=0.9)


def test_unexplored_space_is_behind_what_was_seen() -> None:
    gmap = _half_shell()
    acq = torch.stack([_pose([0.0, 0.0, -2.0])])
    space = unexplored_space(gmap, acq, _seer(gmap), cells=12)
    assert 0.05 < space.unexplored_fraction < 0.95
    assert space.means.shape[0] > 0 and bool((space.weight > 0).all())
    assert space.density > 0
    # the camera is at z = -2: what it did not see lies behind the shell, not in front
    centre, _ = scene_center_radius(gmap.means)
    z = space.means[:, 2] - centre[2]
    assert float(z.mean()) > 0.1 and float((space.weight * z).sum() / space.weight.sum()) > 0.1
    # with a second view from behind, less is unexplored
    both = torch.stack([_pose([0.0, 0.0, -2.0]), _pose([0.0, 0.0, 2.0])])
    assert unexplored_space(gmap, both, _seer(gmap), cells=12).unexplored_fraction < (
        space.unexplored_fraction)


def test_shell_densities_by_hand() -> None:
    from agilegs.service.nbv.anchor.unexplored import radial_shells, shell_densities

    pts = torch.tensor([[0.0, 0, 0], [0.5, 0, 0], [0, 0.9, 0], [1.0, 1.0, 1.0], [0, 0, 1.2]],
                       dtype=F64)
    shell = radial_shells(pts, torch.zeros(3, dtype=F64), 1.0, 4)  # width sqrt(3) / 4
    assert shell.tolist() == [0, 1, 2, 3, 2]
    seen = torch.tensor([True, True, False, True, True])
    per_cell = torch.tensor([4.0, 2.0, 7.0, 0.0, 6.0], dtype=F64)
    # shell 2 holds one observed point (6 Gaussians) and one unobserved (not counted)
    assert shell_densities(shell, seen, per_cell, 4).tolist() == [4.0, 2.0, 6.0, 0.0]
    # a shell no point of which was observed expects nothing
    assert shell_densities(shell, torch.tensor([False, True, True, True, False]), per_cell,
                           4).tolist() == [0.0, 2.0, 7.0, 0.0]
    # one shell: the mean over every observed point
    one = radial_shells(pts, torch.zeros(3, dtype=F64), 1.0, 1)
    assert shell_densities(one, seen, per_cell, 1).tolist() == [3.0]


def test_unexplored_space_beyond_the_map_is_worth_nothing() -> None:
    """The grid's corners lie beyond every Gaussian: at their distance the observed cells are
    empty, so they hold no weight (with one shell they take the map's mean density)."""
    gmap = _half_shell()
    acq = torch.stack([_pose([0.0, 0.0, -2.0])])
    centre, r98 = scene_center_radius(gmap.means)
    far = float((gmap.means - centre).norm(dim=1).max())
    radial = unexplored_space(gmap, acq, _seer(gmap), cells=12, shells=8)
    flat = unexplored_space(gmap, acq, _seer(gmap), cells=12, shells=1)
    # a shell's width: the grid's corner distance over 8
    width = r98 * 1.1 * 3**0.5 / 8
    assert float((radial.means - centre).norm(dim=1).max()) <= far + width + 1e-9
    assert float((flat.means - centre).norm(dim=1).max()) > far + width
    assert flat.shell_density.shape == (1,) and radial.shell_density.shape == (8,)
    assert float(radial.shell_density[-1]) == 0.0


def test_enclosed_cells_are_the_inside_of_a_closed_surface() -> None:
    from agilegs.service.nbv.anchor.unexplored import enclosed

    box = torch.zeros(6, 6, 6, dtype=torch.bool)
    box[1, 1:5, 1:5] = box[4, 1:5, 1:5] = True
    box[1:5, 1, 1:5] = box[1:5, 4, 1:5] = True
    box[1:5, 1:5, 1] = box[1:5, 1:5, 4] = True
    inner = enclosed(box)
    assert int(inner.sum()) == 8 and bool(inner[2:4, 2:4, 2:4].all())
    open_box = box.clone()
    open_box[4, 1:5, 1:5] = False  # one face missing: open along +x
    assert not bool(enclosed(open_box).any())


def test_the_inside_of_a_closed_map_is_not_unexplored() -> None:
    """A whole elongated ellipsoid seen from one side: its far half is unexplored, and so is
    its inside, at distances from the centre where the surface lies elsewhere; the inside is
    enclosed by the Gaussians and dropped without ``count_inside`` (with radial shells, so
    that the inside is at a distance where the views found matter)."""
    g = torch.Generator().manual_seed(2)
    d = torch.randn(4000, 3, generator=g, dtype=F64)
    d = d / d.norm(dim=1, keepdim=True)
    axes = torch.tensor([0.8, 0.25, 0.25], dtype=F64)
    gmap = GaussianMap.from_points(d * axes, torch.rand(4000, 3, generator=g, dtype=F64),
                                   scale=0.04, opacity=0.9)
    acq = torch.stack([_pose([0.0, 0.0, -2.0])])
    centre, _ = scene_center_radius(gmap.means)
    dropped = unexplored_space(gmap, acq, _seer(gmap), cells=12, shells=8,
                               count_inside=False)
    kept = unexplored_space(gmap, acq, _seer(gmap), cells=12, shells=8, count_inside=True)

    def deep(space) -> Tensor:  # noqa: ANN001
        return (((space.means - centre) / axes).norm(dim=1) < 0.6)

    assert bool(deep(kept).any())  # the inside is unexplored at a distance with matter...
    assert not bool(deep(dropped).any())  # ...but enclosed by the map
    assert 0 < dropped.means.shape[0] < kept.means.shape[0]


def test_the_unexplored_term_draws_the_anchor_to_the_unseen_side() -> None:
    gmap = _half_shell()
    lam = 1e-3
    acq = torch.stack([_pose([0.0, -0.3, -2.0]), _pose([0.3, 0.0, -2.0])])
    h = _h_acc(gmap, acq, lam)
    pool = capture_pool([0.0, 0.0, 0.0], 2.0, 24, seed=0, dtype=F64)
    behind = pool[:, 2, 3] > 1.0
    assert bool(behind.any())
    gains = {}
    for flag in (False, True):
        cfg = AnchorConfig(model="directional", unexplored=flag, unexplored_cells=12,
                           iterations=0, num_gaussians=0, envelope=False)
        res = optimize_anchor(gmap, h, pool, INTR, config=cfg, acquired=acq, lam=lam,
                              generator=torch.Generator().manual_seed(0))
        assert res.pool_psi is not None
        gains[flag] = float(res.pool_psi[behind].mean() / res.pool_psi[~behind].mean())
        assert (res.diagnostics.model.unexplored_points is not None) == flag
    assert gains[True] > gains[False]


def test_distinct_best_keeps_the_best_and_spreads_the_rest() -> None:
    from agilegs.service.nbv.anchor.ascent import distinct_best
    from agilegs.service.nbv.se3 import pose_distance

    pool = capture_pool([0.0, 0.0, 0.0], 2.0, 24, seed=3, dtype=F64)
    g = torch.Generator().manual_seed(0)
    scores = torch.rand(24, generator=g, dtype=F64)
    radius = 2.0
    picked = distinct_best(pool, scores, 4, 0.8 * radius, radius).tolist()
    assert picked[0] == int(scores.argmax())
    assert 2 <= len(picked) <= 4
    for a in range(len(picked)):
        for b in range(a):
            assert float(pose_distance(pool[picked[a]], pool[picked[b]], radius)) >= 0.8 * radius
    # each pick is the best of those far enough from the picks before it
    for k in range(1, len(picked)):
        far = [i for i in range(24) if all(
            float(pose_distance(pool[i], pool[j], radius)) >= 0.8 * radius for j in picked[:k])]
        assert picked[k] == max(far, key=lambda i: float(scores[i]))
    # no separation: the plain top-k
    assert distinct_best(pool, scores, 3, 0.0, radius).tolist() == (
        torch.topk(scores, 3).indices.tolist())


def test_several_anchors_come_from_distinct_modes_and_span_the_shortlist() -> None:
    from agilegs.config.selection import SelectConfig
    from agilegs.service.nbv import select
    from agilegs.service.nbv.se3 import pose_distance

    gmap = _blob(300)
    lam = 1e-3
    pool = capture_pool([0.0, 0.0, 0.0], 2.0, 30, seed=0, dtype=F64)
    acq = pool[[0, 10]]
    cands = pool[[i for i in range(30) if i not in (0, 10)]]
    h = _h_acc(gmap, acq, lam)
    one = SelectConfig(anchor=AnchorConfig(anchors=1, num_starts=4))
    three = SelectConfig(anchor=AnchorConfig(anchors=3, num_starts=4))
    res = optimize_anchor(gmap, h, cands, INTR, config=three.anchor, acquired=acq, lam=lam,
                          generator=torch.Generator().manual_seed(0))
    assert res.modes is not None and 2 <= res.modes.shape[0] <= 3
    torch.testing.assert_close(res.modes[0], res.c2w)
    assert res.mode_psi == sorted(res.mode_psi, reverse=True)
    assert res.mode_psi[0] == res.psi
    radius = float((cands[:, :3, 3]).norm(dim=1).median())
    for a in range(1, res.modes.shape[0]):
        d = pose_distance(res.modes[:a], res.modes[a].expand(a, 4, 4), radius)
        assert float(d.min()) >= 0.5 * radius * (1 - 1e-6)
    s1 = select("agile", gmap, h, cands, INTR, config=one, acquired=acq, lam=lam)
    s3 = select("agile", gmap, h, cands, INTR, config=three, acquired=acq, lam=lam)
    assert s3.details["anchor_modes"] >= 2 and "anchor_modes" not in s1.details
    # the coverage matrix spans every anchor's support samples
    assert s3.details["support_samples"] > s1.details["support_samples"]
    assert len(s3.shortlist) == len(s1.shortlist) == 10
