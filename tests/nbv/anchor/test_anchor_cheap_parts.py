"""Parts of the anchor computed the cheaper way against the way they replaced: the
directional fit's per-slot medians."""

from __future__ import annotations

import pytest
import torch

from agilegs.service.nbv.anchor.fitting import lower_median, slot_medians


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_slot_medians_are_each_column_s_lower_median(dtype: torch.dtype) -> None:
    g = torch.Generator().manual_seed(3)
    x = torch.rand(5001, 9, generator=g, dtype=torch.float64).to(dtype)
    seen = torch.rand(5001, 9, generator=g) > 0.4
    seen[:, 2] = False  # a slot no view saw: 0
    seen[:1, 4] = True
    seen[1:, 4] = False  # one seen row
    x[10, 6] = float("nan")
    seen[10, 6] = True  # a NaN: torch's median
    ref = torch.stack([lower_median(x[:, q][seen[:, q]]) if bool(seen[:, q].any())
                       else torch.zeros((), dtype=dtype) for q in range(9)])
    got = slot_medians(x, seen)
    assert got.dtype == dtype and got.shape == (9,)
    assert torch.equal(got.nan_to_num(-1.0), ref.nan_to_num(-1.0))
    assert float(got[2]) == 0.0 and bool(torch.isnan(got[6]))
