"""``bench render --device cuda``'s parts that run anywhere: the sizes and one row of timings
(on the CPU, without gsplat)."""

from __future__ import annotations

import argparse

import pytest
import torch

from agilegs.lab.bench import render_bench
from agilegs.lab.bench.render_gpu import _time_gpu, parse_size


def test_sizes_are_square_or_width_by_height() -> None:
    assert parse_size("512") == (512, 512)
    assert parse_size("1024x768") == (1024, 768)
    with pytest.raises(ValueError):
        parse_size("0x5")
    with pytest.raises(ValueError):
        parse_size("wide")


def test_one_row_times_every_kind_that_can_run_and_reports_the_mapper_rasterizer() -> None:
    row = _time_gpu(None, 400, 40, 30, 1, "cpu", anchor_samples=100, anchor_pool=6)
    assert set(row["ms"]) == {"fwd", "fwd_bwd", "fisher", "moments", "fisher_torch",
                              "mapper_step", "anchor_pool", "anchor_grad", "anchor_pool_torch",
                              "anchor_grad_torch"}
    assert all(v > 0 for v in row["ms"].values())
    # off CUDA the default Fisher is the compiled CPU kernels', against the torch reference
    assert row["fisher_path"] == "torch" and row["fisher_agree"] < 1e-4
    assert row["gsplat"] is False and row["mapper_rasterizer"] == "builtin"
    assert (row["width"], row["height"]) == (40, 30)
    # the anchor's proxy: the compiled CPU kernel against the torch reference
    assert row["anchor_path"] == "numba" and row["anchor_agree"] < 1e-4
    assert row["anchor_pool"] == 6 and 0 < row["anchor_samples"] <= 100
    assert row["anchor_slots"] > 20


def test_the_gpu_path_refuses_a_machine_without_cuda() -> None:
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    p = argparse.ArgumentParser()
    render_bench.add_arguments(p)
    args = p.parse_args(["--device", "cuda", "--sizes", "64"])
    with pytest.raises(SystemExit, match="CUDA is not available"):
        render_bench.run(args)
