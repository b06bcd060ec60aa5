"""Small helpers the selection methods share."""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["argmax_first"]


def argmax_first(values: Tensor) -> int:
    """Index of the largest value, the lowest index on ties (NaN never wins)."""
    v = torch.nan_to_num(values.to(torch.float64), nan=-math.inf)
    return int(torch.argmax(v))
