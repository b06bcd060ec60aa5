"""Random: a seeded uniform choice among the eligible candidates."""

from __future__ import annotations

import torch

from .base import MethodResult, SelectionContext, register


class RandomMethod:
    name = "random"
    uses_information = False

    def __call__(self, ctx: SelectionContext) -> MethodResult:
        pick = int(torch.randint(len(ctx.eligible), (1,), generator=ctx.generator(1)))
        return MethodResult(index=ctx.eligible[pick])


register(RandomMethod())
