"""`agilegs bench latency` on a small map: every figure it reports is there and sane."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import pytest
import torch

from agilegs.lab.bench.latency import PeakRSS, densified
from agilegs.lab.bench.stages import ANCHOR_STAGES
from agilegs.service.cli import main
from agilegs.service.nbv import GaussianMap


def test_latency_bench_reports_every_method(tmp_path: Path) -> None:
    out = tmp_path / "latency.json"
    rc = main(
        [
            "bench", "latency", "--max-gaussians", "300", "--pool", "10", "--shortlist", "3",
            "--width", "24", "--height", "24", "--events", "2", "--acquired", "2",
            "--methods", "random,agile,agile_plus,full_eig,fisherrf,agile_plus@typical",
            "--json", str(out),
        ]
    )
    assert rc == 0
    res = json.loads(out.read_text())
    methods = res["methods"]
    # in the order asked; the full-pool EIG is the yardstick: its own pick is the top
    assert list(methods) == ["random", "agile", "agile_plus", "full_eig", "fisherrf",
                             "agile_plus@typical"]
    assert methods["full_eig"]["eig_percentile"] == 100.0
    assert len(res["upkeep_ms"]) == 2 and all(u > 0 for u in res["upkeep_ms"])
    assert res["config"]["events"] == 2 and res["config"]["gaussians"] == 300
    for name, m in methods.items():
        assert len(m["latency_ms"]) == 2 and len(m["picks"]) == 2, name
        assert all(0 <= p < 10 for p in m["picks"])
        assert 0.0 <= m["eig_percentile"] <= 100.0
        assert m["median_ms"] > 0 and m["speedup_vs_fisherrf"] > 0
        assert m["speedup_vs_full_eig"] > 0 and m["event_speedup_vs_fisherrf"] > 0
        # per event: the selection plus the upkeep of the method's own information
        upkeep = 0.0 if name in ("random", "fisherrf") else 1.0
        for sel, ev, up in zip(m["latency_ms"], m["event_ms"], res["upkeep_ms"]):
            stages_info = ev - sel - upkeep * up
            assert stages_info >= -1e-6, name
    # FisherRF rebuilds H_train inside its selection: its event holds that, its selection not
    fr = methods["fisherrf"]
    assert fr["stages_ms"]["information"] > 0
    assert fr["event_median_ms"] > fr["median_ms"]
    for name in ("agile", "agile_plus", "agile_plus@typical"):
        m = methods[name]
        assert -1.0 <= m["proxy_spearman"] <= 1.0 and not math.isnan(m["proxy_spearman"])
        assert 0.0 <= m["head_eig_percentile"] <= m["shortlist_best_eig_percentile"] <= 100.0
        stages = m["stages_ms"]
        assert {k for k in stages if "." not in k} == {"information", "anchor", "scoring",
                                                       "leverage", "rerank", "total"}
        # the anchor's stages, apart: within the anchor (medians of two events: means)
        split = [stages[f"anchor.{st}"] for st in ANCHOR_STAGES]
        assert all(v >= 0 for v in split) and 0 < sum(split) <= stages["anchor"] + 1e-6
        assert stages["anchor.ascent.gradients"] + stages["anchor.ascent.values"] <= (
            stages["anchor.ascent"] + 1e-6)
        assert m["value_evaluations"] >= 1 and m["gradient_evaluations"] >= 0
        assert m["psi_evaluations"] == m["value_evaluations"] + m["gradient_evaluations"]
    # AGILE-GS+ reranks its shortlist by the exact EIG: it picks the shortlist's best
    assert methods["agile_plus"]["eig_percentile"] == methods["agile_plus"][
        "shortlist_best_eig_percentile"
    ]
    assert "proxy_spearman" not in methods["random"]
    # the keys the docs' tables and the notebook's scripts read
    ratios = {f"{k}speedup_vs_{r}" for k in ("", "event_", "cpu_") for r in ("full_eig", "fisherrf")}
    plain = {"median_ms", "latency_ms", "event_median_ms", "event_ms", "cpu_median_ms",
             "stages_ms", "other_median_ms", "commit_median_ms", "eig_percentile",
             "eig_percentiles", "picks", "peak_rss_mb"} | ratios
    assert set(methods["random"]) == plain
    assert set(methods["agile_plus"]) == plain | {
        "head_eig_percentile", "shortlist_best_eig_percentile", "psi_evaluations",
        "gradient_evaluations", "value_evaluations", "psi_gain", "proxy_spearman"}
    assert set(res) == {"config", "base_rss_mb", "peak_rss_mb", "upkeep_ms", "methods"}
    assert res["peak_rss_mb"] >= res["base_rss_mb"] > 0
    assert all(m["peak_rss_mb"] >= res["base_rss_mb"] * 0.5 for m in methods.values())


def test_latency_bench_without_the_full_pool_method(tmp_path: Path) -> None:
    out = tmp_path / "latency.json"
    assert main(["bench", "latency", "--max-gaussians", "200", "--pool", "8", "--shortlist",
                 "3", "--width", "16", "--height", "16", "--events", "1", "--acquired", "1",
                 "--methods", "agile_plus,random", "--json", str(out)]) == 0
    methods = json.loads(out.read_text())["methods"]
    assert list(methods) == ["agile_plus", "random"]
    for m in methods.values():  # percentiles against the untimed yardstick, no speedups
        assert 0.0 <= m["eig_percentile"] <= 100.0 and "speedup_vs_full_eig" not in m
    assert methods["agile_plus"]["eig_percentile"] == methods["agile_plus"][
        "shortlist_best_eig_percentile"]


def test_densified_map_splits_every_gaussian() -> None:
    g = torch.Generator().manual_seed(0)
    parent = GaussianMap(
        means=torch.rand(4, 3, generator=g) * 10,
        log_scales=torch.full((4, 3), -1.0),
        quats=torch.randn(4, 4, generator=g),
        opacity_logits=torch.randn(4, generator=g),
        sh=torch.randn(4, 4, 3, generator=g),
    )
    kids = densified(parent, 4 * 27 + 2, seed=1)
    assert len(kids) == 110
    p = torch.arange(110) % 4
    # children sit near their parent (a few of its standard deviations), share its rotation,
    # opacity and colour, and are k^(1/3) times smaller (k = 28 for parents 0, 1; 27 else)
    assert float((kids.means - parent.means[p]).norm(dim=1).max()) < 6 * float(torch.exp(
        torch.tensor(-1.0)))
    assert torch.equal(kids.quats, parent.quats[p]) and torch.equal(kids.sh, parent.sh[p])
    assert torch.equal(kids.opacity_logits, parent.opacity_logits[p])
    k = torch.where(p < 2, 28.0, 27.0)
    torch.testing.assert_close(kids.log_scales, (-1.0 - torch.log(k) / 3)[:, None].expand(-1, 3))
    assert not torch.equal(densified(parent, 110, seed=2).means, kids.means)


def test_peak_rss_sees_a_temporary_allocation() -> None:
    with PeakRSS() as mem:
        before = mem.peak
        buf = torch.ones(64 * 2**20 // 4)  # 64 MiB, touched
        buf.add_(1.0)
        time.sleep(0.2)  # held long enough for the sampler to see it on a busy machine
        del buf
    assert mem.peak - before > 32


def test_a_scene_folder_is_read_and_a_bad_scene_is_one_line(tmp_path: Path) -> None:
    import pytest

    from agilegs.lab.bench.latency import _load_map

    folder = Path(__file__).resolve().parents[3] / "lab/scenes/spot"
    assert len(_load_map(str(folder), 50, 0)) == 50
    with pytest.raises(SystemExit, match=r"^--scene .*nothing\.ply: "):
        _load_map(str(tmp_path / "nothing.ply"), 50, 0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_latency_bench_on_the_gpu_without_the_full_pool_method(tmp_path: Path) -> None:
    # the yardstick is then computed on the GPU: the proxy's ranks are compared there
    out = tmp_path / "latency.json"
    assert main(["bench", "latency", "--device", "cuda", "--max-gaussians", "200", "--pool",
                 "8", "--shortlist", "3", "--width", "16", "--height", "16", "--events", "1",
                 "--acquired", "1", "--methods", "agile,random", "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert -1.0 <= res["methods"]["agile"]["proxy_spearman"] <= 1.0
    assert res["gpu_peak_mb"] >= res["gpu_base_mb"] > 0
