"""``agilegs bench coverage``: sectors, the path, the test views' coverage and the EIG mass of
the picks, on made-up records and on a tiny run."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from agilegs.lab.bench.coverage_report import path_bins, run_coverage, sector_of, view_coverage
from agilegs.lab.bench.eig_mass import eig_mass, per_gaussian_eig
from agilegs.lab.scenes import bundled_scene
from agilegs.service.cli import main
from agilegs.service.nbv import (
    Camera,
    GaussianMap,
    Intrinsics,
    accumulate_information,
    expected_information_gain,
    fisher_diag,
    init_information,
    look_at,
)


def ring_pool(n: int, radius: float = 2.0) -> np.ndarray:
    """Camera-to-world poses of n cameras on a horizontal ring, looking at the origin."""
    out = []
    for k in range(n):
        a = 2 * math.pi * k / n
        eye = torch.tensor([radius * math.cos(a), 0.1 * math.sin(3 * a), radius * math.sin(a)],
                           dtype=torch.float64)
        out.append(look_at(eye, torch.zeros(3, dtype=torch.float64)).numpy())
    return np.stack(out)


def record(pool: np.ndarray, initial: list[int], selected: list[int],
           tests: np.ndarray | None = None, psnr: list[float] | None = None) -> dict:
    rec = {"scene": "ring", "variant": "spread", "seed": 0, "psnr": 20.0,
           "pool_poses": pool.tolist(), "initial": initial, "selected": selected,
           "sequence": initial + selected, "events": []}
    if tests is not None:
        rec["test_poses"] = tests.tolist()
        rec["per_view"] = {"psnr": psnr}
    return rec


def test_sectors_split_a_ring_evenly_and_count_the_picks() -> None:
    pool = ring_pool(16)
    c = pool[:, :3, 3]
    sec = sector_of(c, c, 16)  # sector 0 centred on camera 0: one camera per sector
    assert sorted(sec.tolist()) == list(range(16)) and sec[0] == 0
    sec = sector_of(c, c, 8)
    assert np.bincount(sec, minlength=8).max() <= 3 and sec[0] == 0
    out = run_coverage(record(pool, [0], [1, 2, 3]), 16)
    assert out is not None
    assert out["sectors"]["picks"][1:4] == [1, 1, 1] and out["sectors"]["initial"][0] == 1
    assert out["empty_sectors"] == 13 and out["max_share"] == pytest.approx(1 / 3)
    assert out["tv_sectors"] == pytest.approx(13 / 16)
    assert out["empty_path"] == 13 and out["tv_path"] == pytest.approx(13 / 16)
    spread = run_coverage(record(pool, [], list(range(16))), 16)
    assert spread["empty_sectors"] == 0 and spread["tv_sectors"] == pytest.approx(0.0)
    assert spread["tv_path"] == pytest.approx(0.0) and spread["empty_path"] == 0
    assert path_bins([0, 15, 8], 16, 4).tolist() == [0, 3, 2]


def test_a_test_view_at_an_acquired_view_is_covered() -> None:
    pool = ring_pool(12)
    tests = pool[[0, 6]]
    cov = view_coverage(record(pool, [0, 1], [2], tests, [30.0, 18.0]))
    assert cov is not None
    near, far = cov["views"]
    assert near["distance"] == pytest.approx(0.0, abs=1e-9)
    assert near["angle_deg"] == pytest.approx(0.0, abs=1e-5)
    assert far["distance"] > 1.0 and far["angle_deg"] > 90.0
    assert (near["psnr"], far["psnr"]) == (30.0, 18.0)
    assert cov["psnr_far_half"] == 18.0 and cov["psnr_near_half"] == 30.0
    assert view_coverage(record(pool, [0], [1])) is None  # no test poses recorded


def test_eig_mass_splits_the_views_eig() -> None:
    g = torch.Generator().manual_seed(0)
    pts = 0.3 * torch.randn(150, 3, generator=g, dtype=torch.float64)
    gmap = GaussianMap.from_points(pts, torch.rand(150, 3, generator=g, dtype=torch.float64),
                                   scale=0.05, opacity=0.7)
    intr = Intrinsics.from_fov(55.0, 24, 24)
    pool = torch.from_numpy(ring_pool(10))
    h = init_information(gmap, 1e-3)
    h = accumulate_information(h, fisher_diag(gmap, Camera(c2w=pool[0], intrinsics=intr)))
    hv = fisher_diag(gmap, Camera(c2w=pool[5], intrinsics=intr))
    e = per_gaussian_eig(hv, h)
    assert float(e.sum()) == pytest.approx(float(expected_information_gain(hv, h)), rel=1e-9)
    out = eig_mass(gmap, h, hv, pool[5], pool, intr, 1e-3)
    assert out["phi"] == pytest.approx(float(e.sum()))
    for k in ("near_share", "rare_share", "unseen_share", "pool_seen_weighted"):
        assert 0.0 <= out[k] <= 1.0, k
    assert out["informed"] > 0 and out["depth_ratio"] > 0
    # a view of nothing: no shares
    empty = {k: torch.zeros_like(v) for k, v in hv.items()}
    assert eig_mass(gmap, h, empty, pool[5], pool, intr, 1e-3)["near_share"] is None


def test_bench_coverage_reads_a_tiny_run(tmp_path: Path) -> None:
    out = tmp_path / "bench"
    assert main(["bench", "run", "--scene", str(bundled_scene("spot")), "--methods",
                 "random,spread", "--profile", "tiny", "--seeds", "0", "--out", str(out),
                 "--no-plots", "--eig-mass"]) == 0
    rec = json.loads((out / "runs" / "spot_10k" / "spread" / "seed0.json").read_text())
    assert len(rec["test_poses"]) == len(rec["per_view"]["psnr"])
    assert all(e["eig_mass"]["phi"] > 0 for e in rec["events"])
    assert rec["diagnostics_s"] > 0
    assert main(["bench", "coverage", str(out), "--sectors", "4"]) == 0
    table = (out / "coverage.md").read_text()
    assert "| Spread (farthest point) | 1 |" in table and "## Where the chosen views' EIG lies" in table
    data = json.loads((out / "coverage.json").read_text())
    assert set(data["summary"]) == {"random", "spread"}
    assert data["summary"]["spread"]["eig_near_share"] is not None
    with pytest.raises(SystemExit, match="no run records"):
        main(["bench", "coverage", str(tmp_path)])
