"""The warm-up calls the kernels every method and the mapper use, on a synthetic scene."""

from __future__ import annotations

from agilegs.service.nbv.warmup import warm_up


def test_warm_up_runs_each_method_and_a_training_step() -> None:
    got = warm_up(["random", "agile_plus"], gaussians=60)
    assert set(got) == {"select:random", "select:agile_plus", "train", "total"}
    assert all(v >= 0 for v in got.values()) and got["total"] >= got["select:agile_plus"]
