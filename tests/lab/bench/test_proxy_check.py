"""`agilegs bench proxy`: the anchor configurations scored against the exact EIG."""

from __future__ import annotations

import json
import math
from pathlib import Path

from agilegs.lab.bench.latency import spearman
from agilegs.lab.bench.options import DEFAULT_CONFIGS
from agilegs.lab.bench.proxy_check import METRICS, percentile
from agilegs.lab.scenes import bundled_scene
from agilegs.service.cli import main


def test_spearman_and_percentile() -> None:
    import torch

    a = torch.tensor([1.0, 2.0, 3.0, 4.0])
    assert spearman(a, a * 10) == 1.0 and spearman(a, -a) == -1.0
    assert percentile(a, 3) == 100.0 and percentile(a, 0) == 25.0


def test_proxy_check_on_a_tiny_run(tmp_path: Path) -> None:
    out = tmp_path / "proxy.json"
    rc = main(["bench", "proxy", "--scene", str(bundled_scene("spot")), "--profile", "tiny",
               "--json", str(out)])
    assert rc == 0
    res = json.loads(out.read_text())
    (events,) = res["scenes"].values()
    assert len(events) == res["events"] == 3  # the tiny profile's selections
    for ev in events:
        assert set(ev) == set(DEFAULT_CONFIGS)
        for figs in ev.values():
            assert -1.0 <= figs["spearman"] <= 1.0
            for m in ("agile_pct", "plus_pct"):
                assert 0.0 <= figs[m] <= 100.0
            assert figs["agile_pct"] <= figs["plus_pct"]  # the pick is on the shortlist
            assert 0.0 <= figs["agile_sep_deg"] <= 180.0
    for name, means in res["means"].items():
        assert set(means) == set(METRICS) and not math.isnan(means["spearman"]), name
