"""What a selection hands on to the acquisition: the chosen view's Fisher, kept from scoring,
equals a fresh pass; Hhat of a set of views."""

from __future__ import annotations

import pytest
import torch

from agilegs.config.selection import FIELD_NAMES, SelectConfig
from agilegs.service.nbv import (
    Camera,
    GaussianMap,
    Intrinsics,
    accumulate_information,
    eig_scores,
    fisher_diag,
    information_of_views,
    init_information,
    select,
    view_information,
)
from agilegs.service.nbv.candidates import capture_pool
from agilegs.service.nbv.methods.common import argmax_first, eig_scores_keeping_best

INTR = Intrinsics.from_fov(55.0, 24, 24)


def world(dtype: torch.dtype = torch.float32, n: int = 120, d: int = 10):
    g = torch.Generator().manual_seed(3)
    pts = 0.3 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    gmap = GaussianMap.from_points(pts, torch.rand(n, 3, generator=g, dtype=torch.float64),
                                   scale=0.06, opacity=0.6).to(dtype=dtype)
    poses = capture_pool([0.0, 0.0, 0.0], 2.0, d + 2, seed=1).to(dtype)
    acq, pool = poses[:2], poses[2:]
    h = init_information(gmap, 1e-6)
    with torch.no_grad():
        for p in acq:
            h = accumulate_information(h, fisher_diag(gmap, Camera(c2w=p, intrinsics=INTR)))
    return gmap, h, pool, acq


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_scores_equal_eig_scores_and_the_kept_fisher_is_the_argmax_s(dtype) -> None:
    gmap, h, pool, _ = world(dtype)
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=dtype)
    phi, kept = eig_scores_keeping_best(gmap, h, pool, INTR, fields=FIELD_NAMES, background=bg)
    ref = eig_scores(gmap, h, pool, INTR, background=bg)
    assert torch.equal(phi, ref)  # the same arithmetic, bit for bit
    best = argmax_first(phi)
    assert kept is not None
    with torch.no_grad():
        fresh = fisher_diag(gmap, Camera(c2w=pool[best], intrinsics=INTR), background=bg)
    for k in FIELD_NAMES:
        assert torch.equal(kept[k], fresh[k]), k
    # the blocks asked for only, and nothing for no pose
    _, some = eig_scores_keeping_best(gmap, h, pool[:3], INTR, fields=("sh",))
    assert some is not None and set(some) == {"sh"}
    assert eig_scores_keeping_best(gmap, h, pool[:0], INTR, fields=FIELD_NAMES)[1] is None


def test_ties_and_nan_keep_the_view_argmax_first_picks() -> None:
    gmap, h, pool, _ = world()
    same = pool[[4, 4, 2]]  # a tie between the first two: the first is kept
    phi, kept = eig_scores_keeping_best(gmap, h, same, INTR, fields=FIELD_NAMES)
    assert phi[0] == phi[1] and argmax_first(phi) in (0, 2)
    with torch.no_grad():
        fresh = fisher_diag(gmap, Camera(c2w=same[argmax_first(phi)], intrinsics=INTR))
    assert kept is not None and torch.equal(kept["means"], fresh["means"])


@pytest.mark.parametrize("method", ["full_eig", "agile_plus"])
def test_methods_that_score_by_eig_hand_on_the_chosen_view_s_fisher(method) -> None:
    gmap, h, pool, acq = world()
    sel = select(method, gmap, h, pool, INTR, acquired=acq, lam=1e-6,
                 config=SelectConfig(shortlist_size=4))
    assert sel.chosen_information is not None
    fresh = view_information(gmap, pool[sel.index], INTR)
    for k in FIELD_NAMES:
        assert torch.equal(sel.chosen_information[k], fresh[k]), k


@pytest.mark.parametrize("method", ["random", "agile", "cover", "fisherrf"])
def test_methods_that_do_not_score_by_eig_hand_on_nothing(method) -> None:
    gmap, h, pool, acq = world()
    sel = select(method, gmap, h, pool, INTR, acquired=acq, config=SelectConfig(shortlist_size=4))
    assert sel.chosen_information is None


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_information_of_views_is_lambda_plus_every_view_s_fisher(dtype) -> None:
    gmap, _, pool, _ = world(dtype)
    bg = torch.tensor([1.0, 1.0, 1.0], dtype=dtype)
    got = information_of_views(gmap, pool[:3], INTR, 1e-3, bg)
    with torch.no_grad():
        views = [fisher_diag(gmap, Camera(c2w=p, intrinsics=INTR), background=bg)
                 for p in pool[:3]]
    for k in FIELD_NAMES:
        want = 1e-3 + views[0][k] + views[1][k] + views[2][k]
        torch.testing.assert_close(got[k], want.to(dtype), rtol=1e-6 if dtype == torch.float32
                                   else 1e-12, atol=0)
    assert information_of_views(gmap, [], INTR, 1e-3)["means"].eq(1e-3).all()
    empty = gmap.subset(torch.zeros(0, dtype=torch.long))
    assert view_information(empty, pool[0], INTR)["means"].shape == (0, 3)
