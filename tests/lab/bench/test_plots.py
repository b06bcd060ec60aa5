"""The trajectory plot says what its marks are (a legend and the order's colour bar)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import pytest

from agilegs.lab.bench import plots


def test_the_trajectory_plot_has_a_legend(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                          ) -> None:
    import torch

    from agilegs.service.nbv.candidates import capture_pool

    class Scene:
        pool_poses = capture_pool(torch.zeros(3), 2.0, 12, seed=0)

    run = {"initial": [0, 1], "trajectory": [[0.0, 0.0, 2.0], [2.0, 0.0, 0.0],
                                             [0.0, -1.0, -2.0]]}
    results = {"variants": [{"key": "random"}, {"key": "agile_plus"}],
               "summary": {"random": {}, "agile_plus": {}},
               "scenes": {"s": {"runs": {"random": {"0": run}, "agile_plus": {"0": run}}}}}
    figs: list[Any] = []
    monkeypatch.setattr(plots.plt, "close", figs.append)
    out = plots.plot_trajectories(results, "s", Scene(), tmp_path / "t.png")  # type: ignore[arg-type]
    assert out is not None and out.read_bytes()[:4] == b"\x89PNG"
    (fig,) = figs
    (legend,) = fig.legends
    assert [t.get_text() for t in legend.get_texts()] == [
        "candidate pool", "initial views", "path", "views chosen"]
    assert any(a.get_label() == "<colorbar>" for a in fig.axes)
    plt.close(fig)
