"""The target objective: a view's worth on the target views' renders, against a brute-force
reference (per-pixel Jacobians, float64), its use by full_eig and agile_plus, and the paper's
EIG left the default."""

from __future__ import annotations

import math

import pytest
import torch

from agilegs.config.selection import (
    METHOD_OBJECTIVES,
    AnchorConfig,
    SelectConfig,
    for_method,
    objective_of,
    preset_config,
)
from agilegs.service.nbv import (
    Camera,
    GaussianMap,
    Intrinsics,
    accumulate_information,
    eig_scores,
    fisher_diag,
    init_information,
    select,
)
from agilegs.service.nbv.candidates import capture_pool
from agilegs.service.nbv.targets import (
    target_gain,
    target_gain_bruteforce,
    target_information,
    target_intrinsics,
    target_scores_keeping_best,
    target_subsample,
)

INTR = Intrinsics.from_fov(55.0, 10, 8)


def tiny(n: int = 12, seed: int = 0):
    """A few float64 Gaussians, a pool, Hhat from two views (lambda 1e-3)."""
    g = torch.Generator().manual_seed(seed)
    pts = 0.25 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    cols = torch.rand(n, 3, generator=g, dtype=torch.float64)
    gmap = GaussianMap.from_points(pts, cols, scale=0.12, opacity=0.6)
    pool = capture_pool([0.0, 0.0, 0.0], 1.6, 10, seed=seed, dtype=torch.float64)
    h = init_information(gmap, 1e-3)
    for p in pool[[0, 5]]:
        h = accumulate_information(h, fisher_diag(gmap, Camera(c2w=p, intrinsics=INTR)))
    return gmap, pool, h


def test_target_gain_matches_the_per_pixel_brute_force() -> None:
    gmap, pool, h = tiny()
    targets, view = pool[[2, 7]], pool[4]
    fields = tuple(k for k, _ in gmap.items())
    t_info = target_information(gmap, targets, INTR, fields=fields)
    h_v = fisher_diag(gmap, Camera(c2w=view, intrinsics=INTR))
    fast = target_gain(h_v, h, t_info)
    slow = target_gain_bruteforce(gmap, h, view, targets, INTR)
    assert fast > 0
    assert fast == pytest.approx(slow, rel=1e-6)
    # with a background too
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    t_bg = target_information(gmap, targets[:1], INTR, fields=fields, background=bg)
    h_bg = fisher_diag(gmap, Camera(c2w=view, intrinsics=INTR), background=bg)
    assert target_gain(h_bg, h, t_bg) == pytest.approx(
        target_gain_bruteforce(gmap, h, view, targets[:1], INTR, background=bg), rel=1e-6)


def test_a_view_is_worth_nothing_where_no_target_looks() -> None:
    gmap, pool, h = tiny()
    fields = tuple(k for k, _ in gmap.items())
    t_info = {f: torch.zeros_like(getattr(gmap, f)) for f in fields}
    h_v = fisher_diag(gmap, Camera(c2w=pool[3], intrinsics=INTR))
    assert target_gain(h_v, h, t_info) == 0.0
    # and a target's own view, acquired, removes its variance more than a far view does
    t_own = target_information(gmap, pool[[3]], INTR, fields=fields)
    own = target_gain(h_v, h, t_own)
    far = target_gain(fisher_diag(gmap, Camera(c2w=pool[8], intrinsics=INTR)), h, t_own)
    assert own > far >= 0


def test_scores_keep_the_winners_fisher() -> None:
    gmap, pool, h = tiny()
    fields = tuple(k for k, _ in gmap.items())
    t_info = target_information(gmap, pool[[1, 6]], INTR, fields=fields)
    scores, best = target_scores_keeping_best(gmap, h, pool[[2, 3, 4]], INTR, t_info,
                                              fields=fields)
    i = int(torch.argmax(scores))
    assert best is not None
    ref = fisher_diag(gmap, Camera(c2w=pool[[2, 3, 4]][i], intrinsics=INTR))
    for f in fields:
        torch.testing.assert_close(best[f], ref[f])
    for k, pose in enumerate(pool[[2, 3, 4]]):
        hv = fisher_diag(gmap, Camera(c2w=pose, intrinsics=INTR))
        assert float(scores[k]) == pytest.approx(target_gain(hv, h, t_info), rel=1e-12)


def test_the_subsample_spreads_over_the_targets() -> None:
    pool = capture_pool([0.0, 0.0, 0.0], 1.6, 30, seed=1, dtype=torch.float64)
    picks = target_subsample(pool, 1.6, 6)
    assert picks[0] == 0 and len(set(picks)) == 6
    assert target_subsample(pool, 1.6, 100) == target_subsample(pool, 1.6, 30)


def _full_target_scores(gmap, h, cands, targets, fields=None, scale=None):
    """The target scores with T on the targets' images of ``scale`` (the default's if None)."""
    fields = fields or tuple(k for k, _ in gmap.items())
    scale = SelectConfig().target_scale if scale is None else scale
    t_info = target_information(gmap, targets, target_intrinsics(INTR, scale), fields=fields)
    return [target_gain(fisher_diag(gmap, Camera(c2w=p, intrinsics=INTR)), h, t_info)
            for p in cands]


def test_full_eig_with_the_target_objective() -> None:
    gmap, pool, h = tiny()
    cands = pool[[1, 2, 3, 4, 6, 7, 8, 9]]
    default = select("full_eig", gmap, h, cands, INTR)
    assert objective_of("full_eig", SelectConfig()) == "eig"
    phi = eig_scores(gmap, h, cands, INTR)
    assert default.index == int(torch.argmax(phi))
    # the targets given: T from config.target_views of them, spread
    targets = pool[[0, 5]]
    cfg = SelectConfig(objective="target", target_views=2)
    sel = select("full_eig", gmap, h, cands, INTR, config=cfg, targets=targets)
    want = _full_target_scores(gmap, h, cands, targets)
    assert sel.index == max(range(len(want)), key=lambda i: (want[i], -i))
    for i, s in sel.scores.items():
        assert s == pytest.approx(want[i], rel=1e-9)
    assert sel.latency_ms["scoring.targets"] > 0
    assert sel.chosen_information is not None
    # T at the candidates' own resolution: target_scale 1
    full = select("full_eig", gmap, h, cands, INTR, targets=targets,
                  config=SelectConfig(objective="target", target_views=2, target_scale=1.0))
    want_full = _full_target_scores(gmap, h, cands, targets, scale=1.0)
    assert want_full != want
    for i, s in full.scores.items():
        assert s == pytest.approx(want_full[i], rel=1e-9)
    # no targets: the pool's farthest-point subsample
    cfg = SelectConfig(objective="target", target_views=3)
    sel = select("full_eig", gmap, h, cands, INTR, config=cfg)
    from agilegs.service.nbv.candidates import pool_radius, scene_center_radius
    w = pool_radius(cands, scene_center_radius(gmap.means)[0])
    sub = cands[target_subsample(cands, w, 3)]
    want = _full_target_scores(gmap, h, cands, sub)
    assert sel.index == max(range(len(want)), key=lambda i: (want[i], -i))


def test_agile_plus_reranks_by_the_objective() -> None:
    gmap, pool, h = tiny()
    cands = pool[[1, 2, 3, 4, 6, 7, 8, 9]]
    targets = pool[[0, 5]]
    cfg = SelectConfig(objective="target", target_views=2, shortlist_size=4)
    sel = select("agile_plus", gmap, h, cands, INTR, config=cfg, targets=targets,
                 acquired=pool[[0, 5]], lam=1e-3)
    want = _full_target_scores(gmap, h, cands[sel.shortlist], targets)
    best = max(range(len(want)), key=lambda i: (want[i], -i))
    assert sel.index == sel.shortlist[best]
    assert sel.latency_ms["rerank.targets"] > 0
    for v, s in sel.scores.items():
        assert s == pytest.approx(want[sel.shortlist.index(v)], rel=1e-9)


def test_the_anchor_weighs_its_samples_by_the_targets() -> None:
    gmap, pool, h = tiny()
    cands = pool[[1, 2, 3, 4, 6, 7, 8, 9]]
    base = dict(acquired=pool[[0, 5]], lam=1e-3)
    eig = select("agile", gmap, h, cands, INTR, config=SelectConfig(objective="eig"), **base)
    assert "anchor.targets" not in eig.latency_ms
    for targets in (pool[[0]], pool[[5]], None):  # the request's, else the pool's
        cfg = SelectConfig(objective="target")
        sel = select("agile", gmap, h, cands, INTR, config=cfg, targets=targets, **base)
        assert sel.latency_ms["anchor.targets"] >= 0 and 0 <= sel.index < len(cands)
        assert sel.anchor_c2w is not None
    # targets on opposite sides move the anchor
    a = select("agile", gmap, h, cands, INTR, config=SelectConfig(objective="target"),
               targets=pool[[0]], **base).anchor_c2w
    b = select("agile", gmap, h, cands, INTR, config=SelectConfig(objective="target"),
               targets=pool[[5]], **base).anchor_c2w
    assert a is not None and b is not None and not torch.allclose(a, b)


def test_the_anchor_weighs_at_a_farthest_point_subsample_of_the_targets() -> None:
    from agilegs.service.nbv.candidates import pool_radius, scene_center_radius

    gmap, pool, h = tiny()
    cands = pool[[1, 2, 3, 4, 6, 7, 8, 9]]
    base = dict(acquired=pool[[0, 5]], lam=1e-3)

    def anchor(targets, poses):
        cfg = SelectConfig(objective="target", anchor=AnchorConfig(target_poses=poses))
        sel = select("agile", gmap, h, cands, INTR, config=cfg, targets=targets, **base)
        assert sel.latency_ms["anchor.targets"] >= 0
        return sel.anchor_c2w

    w = pool_radius(cands, scene_center_radius(gmap.means)[0])
    sub = pool[target_subsample(pool, w, 3)]
    assert torch.equal(anchor(pool, 3), anchor(sub, 0))  # 3 of the 10, farthest-point
    assert torch.equal(anchor(pool, 10), anchor(pool, 0))  # as many as there are: all
    assert torch.equal(anchor(None, 3), anchor(cands[target_subsample(cands, w, 3)], 0))


def test_target_images_keep_the_field_of_view() -> None:
    big = Intrinsics.from_fov(60.0, 640, 480)
    half = target_intrinsics(big, 0.5)
    assert (half.width, half.height) == (320, 240)
    assert half.fx / half.width == pytest.approx(big.fx / big.width)
    assert target_intrinsics(big, 1.0) is big
    tiny_img = target_intrinsics(INTR, 0.01)
    assert (tiny_img.width, tiny_img.height) == (1, 1)


def test_an_unset_objective_is_the_methods_own(monkeypatch: pytest.MonkeyPatch) -> None:
    assert SelectConfig().objective is None
    assert preset_config("paper").objective == "eig"  # the paper's, whatever the defaults
    for method in ("full_eig", "agile", "agile_plus", "random"):
        assert objective_of(method, SelectConfig()) == METHOD_OBJECTIVES.get(method, "eig")
        assert objective_of(method, SelectConfig(objective="target")) == "target"
        assert objective_of(method, SelectConfig(objective="eig")) == "eig"
    monkeypatch.setitem(METHOD_OBJECTIVES, "agile_plus", "target")
    assert for_method(SelectConfig(), "agile_plus").objective == "target"
    assert for_method(SelectConfig(), "full_eig").objective == "eig"
    # the selection maximises the resolved objective: the same as naming it
    gmap, pool, h = tiny()
    cands = pool[[1, 2, 3, 4, 6, 7, 8, 9]]
    base = dict(acquired=pool[[0, 5]], lam=1e-3)
    unset = select("agile_plus", gmap, h, cands, INTR, config=SelectConfig(shortlist_size=4),
                   **base)
    named = select("agile_plus", gmap, h, cands, INTR, **base,
                   config=SelectConfig(shortlist_size=4, objective="target"))
    assert unset.index == named.index and unset.scores == named.scores
    assert unset.latency_ms["rerank.targets"] > 0


def test_targets_are_checked() -> None:
    gmap, pool, h = tiny()
    cfg = SelectConfig(objective="target")
    bad = pool[[0]].clone()
    bad[0, 0, 0] = math.nan
    for targets in (bad, pool[:0], pool[0]):
        with pytest.raises(ValueError, match="targets"):
            select("full_eig", gmap, h, pool, INTR, config=cfg, targets=targets)
