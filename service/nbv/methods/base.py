"""The interface every selection method implements, and the registry of methods by name.

A method is a callable object with a ``name`` that takes a :class:`SelectionContext` (the
map, Hhat, the pool, the eligible candidates, the settings and the previous warm state, all
validated by :func:`agilegs.service.nbv.select`) and returns a :class:`MethodResult`. It is
registered with :func:`register` when its module is imported; :func:`get_method` looks it up.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Protocol

import torch
from torch import Tensor

from agilegs.config.selection import SelectConfig

from ..camera import Intrinsics
from ..gaussians import GaussianMap

__all__ = [
    "STAGES",
    "MethodResult",
    "SelectionContext",
    "SelectionMethod",
    "get_method",
    "method_names",
    "register",
]

STAGES: tuple[str, ...] = ("information", "anchor", "scoring", "leverage", "rerank", "total")
"""The latency stages of a selection (milliseconds; a method fills the ones it has):
``information`` is information a method rebuilds for itself (FisherRF's H_train)."""


def seeded_generator(seed: int, event: int, salt: int) -> torch.Generator:
    """The generator of one random choice: a function of the seed, the event and the use."""
    return torch.Generator().manual_seed(
        (int(seed) * 1_000_003 + int(event) * 7919 + salt) % (2**63 - 1)
    )


@dataclass
class SelectionContext:
    """Everything a method selects from (validated, in the map's dtype).

    Attributes:
        gmap: the current map.
        h_acc: accumulated information Hhat per field, including lambda.
        pool: the candidates, camera-to-world [D, 4, 4].
        intrinsics: shared by every candidate.
        config: the settings.
        fields: the parameter blocks entering phi and psi.
        eligible: indices of the candidates that may be chosen (ascending).
        acquired: the acquired poses [A, 4, 4], or None.
        state: the previous selection's warm state ({} for a cold start).
        event: the event counter (from ``state``), which seeds this event's random choices.
        aim: the map's robust centre [3].
        radius: the pool's median camera distance from ``aim``.
        rot_weight: world units per radian of the SE(3) distance.
        background: background colour [3] of the Fisher renders, or None (black).
        lam: the lambda included in ``h_acc``, or None (unknown: estimated where needed).
        targets: the target views [T, 4, 4] of the ``target`` objective, or None (the pool).
    """

    gmap: GaussianMap
    h_acc: Mapping[str, Tensor]
    pool: Tensor
    intrinsics: Intrinsics
    config: SelectConfig
    fields: tuple[str, ...]
    eligible: list[int]
    acquired: Tensor | None
    state: dict[str, Any]
    event: int
    aim: Tensor
    radius: float
    rot_weight: float
    background: Tensor | None
    lam: float | None = None
    targets: Tensor | None = None

    @property
    def eligible_index(self) -> Tensor:
        """``eligible`` as a LongTensor [E]."""
        return torch.as_tensor(self.eligible, dtype=torch.long)

    @property
    def eligible_poses(self) -> Tensor:
        """The eligible candidates' poses [E, 4, 4]."""
        return self.pool[self.eligible_index]

    def generator(self, salt: int) -> torch.Generator:
        """This event's generator for the random choice numbered ``salt``."""
        return seeded_generator(self.config.seed, self.event, salt)


@dataclass
class MethodResult:
    """What a method returns (indices are into the pool, not into ``eligible``).

    Attributes:
        index: the chosen candidate.
        shortlist: the ordered shortlist ([] without one).
        scores: per-candidate scores the method computed.
        anchor_c2w: the anchor pose [4, 4], or None.
        psi_trace: psi along the anchor's ascent ([] without one).
        latency_ms: milliseconds per stage of :data:`STAGES` (the total is added by select).
        state: entries of the warm state for the next selection.
        details: diagnostics.
        chosen_information: the diagonal Fisher of the chosen view per block of
            ``context.fields``, rendered on ``context.background``, where the method
            computed it while scoring (else None).
    """

    index: int
    shortlist: list[int] = field(default_factory=list)
    scores: dict[int, float] = field(default_factory=dict)
    anchor_c2w: Tensor | None = None
    psi_trace: list[float] = field(default_factory=list)
    latency_ms: dict[str, float] = field(default_factory=dict)
    state: dict[str, Any] = field(default_factory=dict)
    details: dict[str, Any] = field(default_factory=dict)
    chosen_information: dict[str, Tensor] | None = None


class SelectionMethod(Protocol):
    """A selection method: ``method(context) -> MethodResult``."""

    name: str
    uses_information: bool
    """Whether it reads Hhat (the benchmark gives the others lambda I only)."""
    # A method may also say ``uses_map = False`` (read with ``getattr``, default True): it
    # reads none of the map's Gaussians, so it selects on a map with none (spread).

    def __call__(self, ctx: SelectionContext) -> MethodResult: ...


_REGISTRY: dict[str, SelectionMethod] = {}


def register(method: SelectionMethod) -> SelectionMethod:
    """Add ``method`` to the registry under ``method.name`` (once)."""
    if method.name in _REGISTRY:
        raise ValueError(f"a selection method named {method.name!r} is registered already")
    _REGISTRY[method.name] = method
    return method


def get_method(name: str) -> SelectionMethod:
    """The registered method ``name``; ValueError naming the known ones otherwise."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"method must be one of {method_names()}, got {name!r}") from None


def method_names() -> tuple[str, ...]:
    """The registered methods' names, in registration order."""
    return tuple(_REGISTRY)


@contextmanager
def timed(latency: dict[str, float], stage: str) -> Iterator[None]:
    """Add the block's wall time to ``latency[stage]`` (ms)."""
    t0 = time.perf_counter()
    try:
        yield
    finally:
        latency[stage] = latency.get(stage, 0.0) + (time.perf_counter() - t0) * 1e3
