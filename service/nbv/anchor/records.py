"""The anchor's records: what it is found from (:class:`AnchorInputs`, one frozen object a
call) and what it reports besides the anchor (:class:`AnchorDiagnostics`: the proxy's model,
the stages' seconds, the ascent's evaluations, the starts).

The diagnostics are typed fields; where they leave the process (a selection's latency stages
and details, and from there the HTTP response and the benchmark's JSON) they become named
entries in one place, :meth:`agilegs.service.nbv.anchor.ascent.AnchorResult.report`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from agilegs.config.selection import FIELD_NAMES, AnchorConfig
from agilegs.config.types import validate_config

from ..camera import Intrinsics
from ..candidates import pool_radius
from ..gaussians import GaussianMap
from .envelope import PoolEnvelope

__all__ = ["AnchorDiagnostics", "AnchorInputs", "AscentTally", "ModelDiagnostics"]


@dataclass(frozen=True, eq=False)
class AnchorInputs:
    """What the anchor T* = argmax psi(T) is found from (one call's arguments).

    :meth:`checked` validates ``config`` (a ``ValueError`` naming the field); built directly
    it is taken as validated (as a :class:`~agilegs.config.selection.SelectConfig`'s
    ``anchor`` is).

    Attributes:
        gmap: the current map.
        h_acc: accumulated information per field (same shapes as the map's fields).
        candidates: pool poses [D, 4, 4] to draw the starts from.
        intrinsics: the candidates' intrinsics.
        config: anchor settings.
        fields: parameter blocks entering psi.
        num_acquired: number of acquired views (scales the ``"h_acc"`` typical Fisher).
        envelope: where the anchor may go (None: anywhere).
        warm_c2w: the previous anchor [4, 4], an extra start when ``config.warm_start``.
        typical: m_q per field to use as is (overrides ``config.typical_fisher``).
        generator: seeds the importance sampling.
        acquired: poses of the acquired views [A, 4, 4], which the ``"fitted"`` model is
            fitted over (without any, the ``"typical"`` model is used).
        lam: the lambda in ``h_acc`` (None: estimated, see ``fitting.prior_floor``).
        background: the background colour [3] Hhat's Fisher was rendered with (the exact
            psi renders with it too; None: black).
        carried: the parts a previous event kept (its :attr:`AnchorResult.carry
            <agilegs.service.nbv.anchor.ascent.AnchorResult.carry>`, through the warm
            state), reused while ``config.carry_over_tolerance`` allows (:mod:`.carry`).
        rates_carried: the directional model's accumulated terms a previous event kept
            (its :attr:`AnchorResult.rates_carry
            <agilegs.service.nbv.anchor.ascent.AnchorResult.rates_carry>`), extended by the
            new views while ``config.refit_every`` allows
            (:func:`~agilegs.service.nbv.anchor.fitting.directional_rates`).
        targets: views of interest [T, 4, 4] of the ``target`` objective: the proxy's
            samples are weighted by their information at these views (:mod:`.targeted`);
            None: the EIG.
    """

    gmap: GaussianMap
    h_acc: dict[str, Tensor]
    candidates: Tensor
    intrinsics: Intrinsics
    config: AnchorConfig
    fields: tuple[str, ...] = FIELD_NAMES
    num_acquired: int = 1
    envelope: PoolEnvelope | None = None
    warm_c2w: Tensor | None = None
    typical: dict[str, Tensor] | None = None
    generator: torch.Generator | None = None
    acquired: Tensor | None = None
    lam: float | None = None
    background: Tensor | None = None
    carried: Any = None
    rates_carried: Any = None
    targets: Tensor | None = None

    def checked(self) -> AnchorInputs:
        """These inputs with ``config`` validated (a ``ValueError`` naming the field)."""
        return dataclasses.replace(self, config=validate_config(AnchorConfig, self.config))

    @property
    def radius(self) -> float:
        """The pool's radius: the envelope's, else the candidates'."""
        return self.envelope.radius if self.envelope is not None else pool_radius(
            self.candidates)


@dataclass(frozen=True)
class ModelDiagnostics:
    """What the proxy's observation model is (carried with the proxy, :mod:`.carry`).

    Attributes:
        model: ``"typical"``, ``"fitted"`` or ``"directional"``.
        typical_source: the typical model's Fisher: ``"given"`` or ``"h_acc"`` (None for
            the fitted models).
        typical_term: the fitted models' typical proxy term f (None for the typical model).
        unexplored_fraction: the unexplored share of the grid's points, 0 to 1 (None
            without unexplored space).
        unexplored_points: the unexplored points added to the proxy (None without).
    """

    model: str
    typical_source: str | None = None
    typical_term: float | None = None
    unexplored_fraction: float | None = None
    unexplored_points: int | None = None

    def as_dict(self) -> dict[str, Any]:
        """The fields that are set, by name (the form the warm state keeps)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if getattr(self, f.name) is not None}

    @classmethod
    def from_dict(cls, kept: Mapping[str, Any]) -> ModelDiagnostics:
        """The diagnostics :meth:`as_dict` gave (a ``KeyError`` without ``model``)."""
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in kept.items() if k in names and k != "model"},
                   model=kept["model"])


@dataclass
class AscentTally:
    """The ascent's psi evaluations, with and without the gradient, and their seconds (the
    compiled line searches count as values)."""

    gradient_evaluations: int = 0
    value_evaluations: int = 0
    gradient_s: float = 0.0
    value_s: float = 0.0

    def as_split(self) -> dict[str, float]:
        """The tally by name, as :func:`~.ascent.ascend`'s ``split`` receives it."""
        return {"gradient_evaluations": float(self.gradient_evaluations),
                "value_evaluations": float(self.value_evaluations),
                "gradient_s": self.gradient_s, "value_s": self.value_s}


@dataclass
class AnchorDiagnostics:
    """What the anchor's search reports besides the anchor.

    Attributes:
        model: the proxy's model (:class:`ModelDiagnostics`).
        carried: whether the proxy was the previous event's (:mod:`.carry`).
        rates_carried: whether the rates extended the accumulated terms carried from an
            earlier event (``refit_every``).
        timings_s: the seconds of each stage, in order: ``visibility`` (the opacity maps),
            ``rates`` (the model fitted over the acquired views, the importance sample),
            ``unexplored`` (unexplored space), ``starts`` (the pool's psi, the starts),
            ``ascent``.
        ascent: the ascent's evaluations and their seconds (:class:`AscentTally`).
        start_indices: the pool candidates the ascent started from, best first (indices
            into the candidates; the warm start is not one).
        proxy_samples: the proxy's samples (Gaussians and unexplored points).
    """

    model: ModelDiagnostics
    carried: bool
    rates_carried: bool = False
    timings_s: dict[str, float] = field(default_factory=dict)
    ascent: AscentTally = field(default_factory=AscentTally)
    start_indices: list[int] = field(default_factory=list)
    proxy_samples: int = 0
