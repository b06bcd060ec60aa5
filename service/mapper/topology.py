"""How the Gaussians after a topology change (densify, prune, extension, a replaced map)
relate to those before, and carrying per-Gaussian state across such a change."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import torch
from torch import Tensor

__all__ = ["TopologyChange", "remap_per_gaussian"]


@dataclass
class TopologyChange:
    """How the Gaussians after a change relate to those before.

    Attributes:
        src: LongTensor [N_new]: new Gaussian j is a copy of old Gaussian ``src[j]`` (kept,
            cloned, or a split child, which differs in position and scale), or brand new when
            ``src[j] == -1`` (from depth or points, or a replaced map).
        kept: BoolTensor [N_old]: old Gaussians that survive as themselves (not pruned, not
            replaced by split children); ``kept.sum()`` of the new ones have ``identity``.
        identity: BoolTensor [N_new]: new Gaussians that are an old Gaussian kept as itself
            (their Adam moments were carried; the others start from zero).
        num_old: N_old.
        num_new: N_new.
        reason: "densify" (clone/split then prune), "extend" (Gaussians added from a depth
            map), "init" (map initialised or replaced), or "replace" (``replace_gmap``).
        counts: e.g. {"cloned": ., "split": ., "pruned": ., "added": .}.
    """

    src: Tensor
    kept: Tensor
    identity: Tensor
    num_old: int
    num_new: int
    reason: str
    counts: dict[str, int] = field(default_factory=dict)


def remap_per_gaussian(
    values: Mapping[str, Tensor],
    src: Tensor,
    fill: float | Tensor | Mapping[str, float | Tensor] = 0.0,
) -> dict[str, Tensor]:
    """Carry per-Gaussian tensors across a topology change.

    Args:
        values: tensors whose first dimension is N_old (e.g. Ĥ per field: [N_old, ...]).
        src: LongTensor [N_new] from :class:`TopologyChange` (-1 for brand-new Gaussians).
        fill: value for brand-new Gaussians: a scalar, a tensor broadcastable to one row
            ``[...]``, or a mapping from key to either (keys it lacks are filled with 0).

    Returns:
        New dict with tensors [N_new, ...]: row j is ``values[k][src[j]]`` (so clones and split
        children copy their source) or ``fill`` where ``src[j] == -1``.
    """
    if src.ndim != 1 or src.dtype not in (torch.int64, torch.int32):
        raise ValueError(
            f"src must be an integer tensor [N_new], got {src.dtype} {list(src.shape)}"
        )
    out: dict[str, Tensor] = {}
    for k, v in values.items():
        n_old = v.shape[0] if v.ndim else 0
        if v.ndim == 0:
            raise ValueError(f"values[{k!r}] must have a Gaussian dimension first, got a scalar")
        s = src.to(v.device).long()
        if s.numel() and (int(s.max()) >= n_old or int(s.min()) < -1):
            raise ValueError(
                f"src indexes outside values[{k!r}] (N_old = {n_old}, src range "
                f"[{int(s.min())}, {int(s.max())}])"
            )
        f = fill.get(k, 0.0) if isinstance(fill, Mapping) else fill
        new = s < 0
        rows = v[s.clamp_min(0)] if n_old else v.new_zeros((s.numel(), *v.shape[1:]))
        if bool(new.any()):
            fv = torch.as_tensor(f, dtype=v.dtype, device=v.device)
            rows = rows.clone()
            rows[new] = fv.expand(int(new.sum()), *v.shape[1:]).to(v.dtype)
        out[k] = rows
    return out


# ----------------------------------------------------------------------------- geometry helpers
