"""`agilegs bench value`: realised gains from cloned trainers, rank correlations, picks."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from agilegs.lab.bench.value import (
    PICKS,
    average_ranks,
    gain_percentile,
    rank_correlation,
)
from agilegs.lab.scenes import bundled_scene
from agilegs.service.cli import main


def test_average_ranks_and_rank_correlation_with_ties() -> None:
    torch.testing.assert_close(average_ranks(torch.tensor([3.0, 1.0, 3.0, 2.0])),
                               torch.tensor([2.5, 0.0, 2.5, 1.0], dtype=torch.float64))
    assert rank_correlation([1, 2, 3, 4], [10, 20, 30, 40]) == pytest.approx(1.0)
    assert rank_correlation([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)
    # a binary membership against a gain: the point-biserial on ranks
    r = rank_correlation([1, 1, 0, 0], [0.9, 0.8, 0.1, 0.2])
    assert r == pytest.approx(math.sqrt(0.8), rel=1e-9)
    assert math.isnan(rank_correlation([1, 1, 1], [1, 2, 3]))  # a constant score
    assert math.isnan(rank_correlation([1, 2], [1, 2]))
    assert gain_percentile([0.1, 0.2, 0.3, 0.4], 0.3) == 75.0


def test_tiny_value_run(tmp_path: Path) -> None:
    out = tmp_path / "value.json"
    plots = tmp_path / "plots"
    assert main(["bench", "value", "--scene", str(bundled_scene("spot")), "--profile", "tiny",
                 "--events", "0,2,9", "--candidates", "5", "--horizon", "4",
                 "--json", str(out), "--plots", str(plots)]) == 0
    res = json.loads(out.read_text())
    events = res["scenes"]["spot_10k"]
    assert [e["event"] for e in events] == [0, 2]  # event 9 is past the schedule
    for e in events:
        n = len(e["sample"])
        assert n >= 5 and len(e["gains"]) == n and len(set(e["sample"])) == n
        assert all(math.isfinite(g) for g in e["gains"])
        for name in ("eig", "trace", "eig_lam1e-06", "eig_geometry", "eig_black_bg", "fisherrf",
                     "cover", "anchor_psi", "shortlist", "agile_plus", "shortlist_paper"):
            assert len(e["scores"][name]) == n, name
        for m in PICKS:
            p = e["picks"][m]
            assert p["pool_index"] in e["sample"]  # every pick's gain is measured
            assert 0.0 < p["percentile"] <= 100.0
            assert p["gain"] == pytest.approx(e["gains"][e["sample"].index(p["pool_index"])])
        # the full-pool EIG picks its maximum; AGILE-GS+ the best of its shortlist by EIG
        eig = dict(zip(e["sample"], e["scores"]["eig"]))
        assert eig[e["picks"]["full_eig"]["pool_index"]] == max(eig.values())
        for name, rho in e["spearman"].items():
            assert -1.0 - 1e-9 <= rho <= 1.0 + 1e-9, name
    summ = res["summary"]
    assert set(summ["per_scene"]) == {"spot_10k"}
    assert set(summ["overall"]["pick_percentile"]) == set(PICKS)
    assert (plots / "value_spot_10k.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_branch_differs_only_by_its_view() -> None:
    from agilegs.config.mapper import MapperConfig
    from agilegs.lab.bench.profiles import PROFILES
    from agilegs.lab.bench.protocol import add_pool_view
    from agilegs.lab.bench.scenes import load_bench_scene
    from agilegs.service.mapper.mapper import Mapper

    prof = PROFILES["tiny"]
    scene = load_bench_scene(bundled_scene("teapot"), prof.scene)
    mapper = Mapper(config=MapperConfig(**{**prof.mapper, "background": scene.background}))
    for i in (0, 5):
        add_pool_view(mapper, scene, i, prof, first=True)
    mapper.step(3)
    a, b, c = mapper.clone(), mapper.clone(), mapper.clone()
    for m in (a, b):
        m.step(4)
    add_pool_view(c, scene, 9, prof)
    c.step(4)
    for k in ("means", "log_scales", "opacity_logits", "sh"):
        assert torch.equal(getattr(a.gmap, k), getattr(b.gmap, k)), k
    assert not torch.equal(a.gmap.means, c.gmap.means) or a.num_gaussians != c.num_gaussians
    assert mapper.num_steps == 3 and a.num_steps == 7  # the original is untouched
