"""Spread: farthest-point sampling over the pool, against a brute-force reference; without a
map; in embodied mode."""

from __future__ import annotations

import math

import pytest
import torch

from agilegs.config.selection import ScoringConfig, SelectConfig
from agilegs.service.nbv import GaussianMap, Intrinsics, init_information, look_at, select
from agilegs.service.nbv.candidates import capture_pool, pool_radius, scene_center_radius
from agilegs.service.nbv.spread import farthest_point_order, nearest_distances

INTR = Intrinsics.from_fov(55.0, 32, 32)


def world(d: int = 30, seed: int = 0, dtype: torch.dtype = torch.float64):
    g = torch.Generator().manual_seed(seed)
    pts = 0.3 * torch.randn(120, 3, generator=g, dtype=dtype)
    gmap = GaussianMap.from_points(pts, torch.rand(120, 3, generator=g, dtype=dtype),
                                   scale=0.05, opacity=0.7)
    poses = capture_pool([0.0, 0.0, 0.0], 2.0, d, seed=seed).to(torch.float64)
    u, _, vh = torch.linalg.svd(poses[:, :3, :3])  # orthonormal to float64's precision
    poses[:, :3, :3] = u @ vh
    return gmap, poses.to(dtype)


def brute_distance(a: torch.Tensor, b: torch.Tensor, w: float) -> float:
    """||c_a - c_b|| + w * the rotation angle between a and b, in plain floats."""
    pa, pb = a[:3, 3].tolist(), b[:3, 3].tolist()
    trans = math.sqrt(sum((x - y) ** 2 for x, y in zip(pa, pb)))
    ra, rb = a[:3, :3].tolist(), b[:3, :3].tolist()
    tr = sum(ra[k][i] * rb[k][i] for i in range(3) for k in range(3))  # trace(Ra^T Rb)
    return trans + w * math.acos(max(-1.0, min(1.0, (tr - 1.0) / 2.0)))


def brute_pick(pool: torch.Tensor, eligible: list[int], acquired: torch.Tensor, w: float) -> int:
    best, best_d = None, -math.inf
    for i in eligible:
        d = min(brute_distance(pool[i], a, w) for a in acquired)
        if d > best_d + 1e-12:  # strictly farther: ties keep the lower index
            best, best_d = i, d
    assert best is not None
    return best


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_spread_picks_what_the_brute_force_max_min_picks(seed: int) -> None:
    gmap, poses = world(seed=seed)
    acquired, pool = poses[[0, 7, 19]], poses[[i for i in range(30) if i not in (0, 7, 19)]]
    h = init_information(gmap, 1e-3)
    aim, _ = scene_center_radius(gmap.means)
    w = pool_radius(pool, aim)  # the default rotation weight: the pool's radius
    sel = select("spread", gmap, h, pool, INTR, acquired=acquired)
    assert sel.index == brute_pick(pool, list(range(len(pool))), acquired, w)
    for i, s in sel.scores.items():
        assert s == pytest.approx(min(brute_distance(pool[i], a, w) for a in acquired), rel=1e-6)
    # an explicit rotation weight is the one used
    for rw in (1e-6, 5.0):
        cfg = SelectConfig(scoring=ScoringConfig(rot_weight=rw))
        sel = select("spread", gmap, h, pool, INTR, acquired=acquired, config=cfg)
        assert sel.index == brute_pick(pool, list(range(len(pool))), acquired, rw)


def test_successive_picks_are_the_farthest_point_order() -> None:
    gmap, poses = world(d=25)
    h = init_information(gmap, 1e-3)
    acquired = poses[[3]]
    remaining = [i for i in range(25) if i != 3]
    w = 1.7
    cfg = SelectConfig(scoring=ScoringConfig(rot_weight=w))
    chosen = []
    for _ in range(6):
        sel = select("spread", gmap, h, poses[remaining], INTR, acquired=acquired, config=cfg)
        pick = remaining.pop(sel.index)
        chosen.append(pick)
        acquired = torch.cat([acquired, poses[[pick]]])
    order = farthest_point_order(poses[[i for i in range(25) if i != 3]], poses[[3]], w, 6)
    others = [i for i in range(25) if i != 3]
    assert [others[i] for i in order] == chosen


def test_ties_go_to_the_lowest_index_and_no_reference_picks_the_first() -> None:
    gmap, poses = world(d=8)
    h = init_information(gmap, 1e-3)
    # no acquired view: every candidate is at +inf
    sel = select("spread", gmap, h, poses, INTR)
    assert sel.index == 0
    assert all(math.isinf(s) for s in sel.scores.values())
    # two copies of the farthest candidate: the lower index wins
    z = torch.zeros(3, dtype=torch.float64)
    here = look_at(torch.tensor([2.0, 0.0, 0.0], dtype=torch.float64), z)
    side = look_at(torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64), z)
    back = look_at(torch.tensor([-2.0, 0.0, 0.0], dtype=torch.float64), z)
    pool = torch.stack([side, back, back, side])
    sel = select("spread", gmap, h, pool, INTR, acquired=here[None])
    assert sel.index == 1 and sel.scores[1] == sel.scores[2] > sel.scores[0]
    assert farthest_point_order(pool, None, 1.0, 3)[0] == 0
    assert nearest_distances(pool, None, 1.0).isinf().all()
    assert farthest_point_order(pool, None, 1.0, 0) == []
    assert sorted(farthest_point_order(pool, None, 1.0, 100)) == [0, 1, 2, 3]


def test_spread_needs_no_map_and_no_information() -> None:
    _, poses = world(d=12)
    empty = GaussianMap.from_points(torch.zeros(0, 3, dtype=torch.float64),
                                    torch.zeros(0, 3, dtype=torch.float64))
    h = init_information(empty, 1e-3)
    acquired = poses[[2, 9]]
    sel = select("spread", empty, h, poses, INTR, acquired=acquired)
    w = pool_radius(poses, poses[:, :3, 3].mean(0))
    assert sel.index == brute_pick(poses, list(range(12)), acquired, w)
    with pytest.raises(ValueError, match="no Gaussians"):
        select("full_eig", empty, h, poses, INTR, acquired=acquired)


def test_embodied_spread_stays_among_the_k_nearest() -> None:
    gmap, poses = world(d=30)
    h = init_information(gmap, 1e-3)
    acquired = poses[[0, 15]]
    pool = poses[1:]
    for metric in ("position", "se3"):
        cfg = SelectConfig(embodied_k=4, embodied_metric=metric,  # type: ignore[arg-type]
                           scoring=ScoringConfig(rot_weight=2.0))
        sel = select("spread", gmap, h, pool, INTR, acquired=acquired, current_pose=poses[15],
                     config=cfg)
        assert len(sel.eligible) == 4 and sel.index in sel.eligible
        assert sel.index == brute_pick(pool, sel.eligible, acquired, 2.0)
        assert set(sel.scores) == set(sel.eligible)


def test_spread_works_in_float32() -> None:
    gmap, poses = world(dtype=torch.float32)
    h = init_information(gmap, 1e-3)
    sel = select("spread", gmap, h, poses[1:], INTR, acquired=poses[:1])
    assert 0 <= sel.index < 29
    assert sel.scores[sel.index] == max(sel.scores.values())


def test_full_eig_broken_by_spread_scores_only_the_far_candidates() -> None:
    from agilegs.service.nbv import Camera, accumulate_information, eig_scores, fisher_diag

    gmap, poses = world(d=20)
    intr = Intrinsics.from_fov(55.0, 16, 16)
    acquired, pool = poses[[0, 10]], poses[[i for i in range(20) if i not in (0, 10)]]
    h = init_information(gmap, 1e-3)
    for p in acquired:
        h = accumulate_information(h, fisher_diag(gmap, Camera(c2w=p, intrinsics=intr)))
    cfg = SelectConfig(spread_filter=0.5, scoring=ScoringConfig(rot_weight=2.0))
    sel = select("full_eig", gmap, h, pool, intr, acquired=acquired, config=cfg)
    dist = [min(brute_distance(p, a, 2.0) for a in acquired) for p in pool]
    kept = [i for i, d in enumerate(dist) if d >= 0.5 * max(dist) - 1e-9]
    assert sorted(sel.scores) == kept and sel.details["spread_kept"] == len(kept)
    phi = eig_scores(gmap, h, pool[kept], intr)
    assert sel.index == kept[int(torch.argmax(phi))]
    assert 0 <= sel.latency_ms["scoring.spread"] <= sel.latency_ms["scoring"]
    # at 1, spread's own pick; at 0, every candidate
    one = select("full_eig", gmap, h, pool, intr, acquired=acquired,
                 config=SelectConfig(spread_filter=1.0, scoring=ScoringConfig(rot_weight=2.0)))
    assert one.index == brute_pick(pool, list(range(len(pool))), acquired, 2.0)
    assert len(select("full_eig", gmap, h, pool, intr, acquired=acquired).scores) == len(pool)


def test_agile_plus_draws_its_probe_where_spread_would_pick() -> None:
    from agilegs.service.nbv import Camera, accumulate_information, fisher_diag

    gmap, poses = world(d=20)
    intr = Intrinsics.from_fov(55.0, 16, 16)
    acquired, pool = poses[[0, 10]], poses[[i for i in range(20) if i not in (0, 10)]]
    h = init_information(gmap, 1e-3)
    for p in acquired:
        h = accumulate_information(h, fisher_diag(gmap, Camera(c2w=p, intrinsics=intr)))
    cfg = SelectConfig(shortlist_size=4, probes=1, probe_draw="spread",
                       scoring=ScoringConfig(rot_weight=2.0))
    sel = select("agile_plus", gmap, h, pool, intr, acquired=acquired, config=cfg, lam=1e-3)
    model, probe = sel.shortlist[:-1], sel.shortlist[-1]
    rest = [i for i in range(len(pool)) if i not in model]
    assert probe == brute_pick(pool, rest, acquired, 2.0)
    assert sel.details["probes"] == 1 and sel.index in sel.shortlist
