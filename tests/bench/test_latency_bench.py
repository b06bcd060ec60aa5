"""`agilegs bench latency` on a small map: every figure it reports is there and sane."""

from __future__ import annotations

import json
import math
from pathlib import Path

from agilegs.service.cli import main


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
        assert set(m["stages_ms"]) == {"information", "anchor", "scoring", "leverage", "rerank",
                                       "total"}
    # AGILE-GS+ reranks its shortlist by the exact EIG: it picks the shortlist's best
    assert methods["agile_plus"]["eig_percentile"] == methods["agile_plus"][
        "shortlist_best_eig_percentile"
    ]
    assert "proxy_spearman" not in methods["random"]


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
