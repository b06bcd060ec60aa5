"""Benchmark variants: a selection method with some settings changed, named once for every
benchmark (``bench run``, ``bench latency``, ``bench proxy``).

A variant key is ``<method>`` or ``<method>@<option>[+<option>...]``, for example
``agile@knearest``, ``agile_plus@n20``, ``agile_plus@exact``, ``agile_plus@typical+cold`` or
``full_eig@target`` (the target objective instead of the EIG).
The options (:data:`OPTIONS`) change the :class:`~agilegs.config.selection.SelectConfig` the
method selects with; ``n<N>`` sets the shortlist size N.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

from agilegs.config.selection import (
    COVER_ZBUFFER,
    MIXED_ZBUFFER,
    POINT_ZBUFFER,
    PRESETS,
    SHORTLISTS,
    SelectConfig,
)
from agilegs.config.types import deep_merge, validate_config
from agilegs.service.nbv.methods.base import method_names

__all__ = [
    "DISPLAY",
    "OPTIONS",
    "SHORTLIST_DISPLAY",
    "Variant",
    "build_variants",
    "display_name",
    "parse_variant",
]

Group = Literal["main", "shortlist", "budget", "variant"]

DISPLAY = {
    "random": "Random",
    "spread": "Spread (farthest point)",
    "fisherrf": "FisherRF",
    "cover": "COVER",
    "full_eig": "Full-pool EIG (ceiling)",
    "agile": "AGILE-GS",
    "agile_plus": "AGILE-GS+",
    "agile@paper": "AGILE-GS (paper)",
    "agile_plus@paper": "AGILE-GS+ (paper)",
    "agile@single": "AGILE-GS (one anchor)",
    "agile_plus@single": "AGILE-GS+ (one anchor)",
    "full_eig@target": "Full-pool target objective",
    "agile_plus@target": "AGILE-GS+ (target objective)",
    "agile@target": "AGILE-GS (target objective)",
}
SHORTLIST_DISPLAY = {
    "leverage": "Ridge leverage",
    "knearest": "K-nearest views",
    "topnorm": "Top independent norm",
    "online": "Online row sampling",
}


def _anchor(**changes: Any) -> Callable[[SelectConfig], SelectConfig]:
    return lambda c: dataclasses.replace(c, anchor=dataclasses.replace(c.anchor, **changes))


def _scoring(**changes: Any) -> Callable[[SelectConfig], SelectConfig]:
    return lambda c: dataclasses.replace(c, scoring=dataclasses.replace(c.scoring, **changes))


def _shortlist(name: str) -> Callable[[SelectConfig], SelectConfig]:
    return lambda c: dataclasses.replace(c, shortlist=name)  # type: ignore[arg-type]


def _preset(name: str) -> Callable[[SelectConfig], SelectConfig]:
    def apply(c: SelectConfig) -> SelectConfig:
        return validate_config(SelectConfig, deep_merge(dataclasses.asdict(c), PRESETS[name]))
    return apply


OPTIONS: dict[str, tuple[str, Callable[[SelectConfig], SelectConfig]]] = {
    **{s: (f"the {SHORTLIST_DISPLAY[s].lower()} shortlist", _shortlist(s))
       for s in SHORTLISTS if s != "leverage"},
    "paper": ("the paper's AGILE-GS: the anchor ascends the exact trace surrogate through the "
              "rasterizer, the leverage greedy starts from lambda_G I (SelectConfig preset "
              "'paper')", _preset("paper")),
    "exact": ("the anchor ascends the exact trace surrogate (one start, 3 steps)",
              _anchor(psi="exact", num_starts=1, iterations=3, warm_start=True)),
    "all_gaussians": ("the proxy sums over every Gaussian (no importance sampling)",
                      _anchor(num_gaussians=0)),
    "no_ascent": ("the best pool start under the proxy, no gradient steps",
                  _anchor(iterations=0)),
    "cold": ("no warm start from the previous anchor", _anchor(warm_start=False)),
    "typical": ("the proxy's typical model (one Fisher value per parameter slot)",
                _anchor(model="typical")),
    "start_view": ("the typical model with its value from one Fisher pass",
                   _anchor(model="typical", typical_fisher="start_view")),
    "point_zbuffer": ("z-buffer visibility: each occluder on its own cell, 2% depth tolerance",
                      _anchor(visibility="zbuffer", occluders=2000, occlusion_tests=POINT_ZBUFFER)),
    "cover_zbuffer": ("z-buffer visibility: each occluder covers 3x3 cells, 10% tolerance",
                      _anchor(visibility="zbuffer", occluders=2000, occlusion_tests=COVER_ZBUFFER)),
    "mixed_zbuffer": ("z-buffer visibility: the mean of the point and the 3x3 tests",
                      _anchor(visibility="zbuffer", occluders=2000, occlusion_tests=MIXED_ZBUFFER)),
    "directional": ("the proxy's directional model: per parameter slot, with a mean's world "
                    "axes and a scale's local axes seen across the rays",
                    _anchor(model="directional")),
    "isotropic": ("the proxy's fitted model without directions: one rate per Gaussian",
                  _anchor(model="fitted")),
    "unexplored": ("the proxy also counts the unexplored part of the map's extent as "
                   "never-observed Gaussians", _anchor(unexplored=True)),
    "radial_unexplored": ("the unexplored space expects the density the views found at each "
                          "distance from the map's centre (8 radial shells)",
                          _anchor(unexplored_shells=8)),
    "enclosed_unexplored": ("the unexplored space leaves out the inside of the map's "
                            "surfaces (what its Gaussians enclose on all six axis directions)",
                            _anchor(unexplored_inside=False)),
    "no_unexplored": ("the proxy counts only the map's Gaussians", _anchor(unexplored=False)),
    "carry_over": ("the anchor's pose-independent parts (the proxy) reused from the last event "
                   "while the map's and Hhat's per-field sums are within 20% of theirs at the "
                   "build", _anchor(carry_over_tolerance=0.2)),
    "full_starts": ("the anchor's starts ranked by the full proxy psi over the whole pool "
                    "(no coarse pass)", _anchor(start_samples=0)),
    "full_fit": ("the proxy's visibility and rates over every Gaussian of the map (no fixed-"
                 "size sample)", _anchor(fit_gaussians=0)),
    "refit": ("the directional model's terms recomputed over every acquired view at every "
              "event (none carried over)", _anchor(refit_every=1)),
    "modes": ("three anchors from distinct modes of psi (starts spread alike), the shortlist "
              "drawn across their support samples", _anchor(anchors=3)),
    "one_anchor": ("one anchor, the shortlist drawn around it", _anchor(anchors=1)),
    "single": ("one anchor of the isotropic fitted proxy over the map's Gaussians only",
               _anchor(model="fitted", unexplored=False, anchors=1)),
    "quarter_unseen": ("the fitted model counts unseen Gaussians as seen by a quarter of a "
                       "typical view", _anchor(unseen="quarter_view")),
    "unconditioned": ("the leverage greedy starts from lambda_G I (not the acquired rows)",
                      _scoring(condition_on_acquired=False)),
    "no_probes": ("AGILE-GS+ reranks the model's shortlist alone (no uniform probes)",
                  lambda c: dataclasses.replace(c, probes=0)),
    "probes3": ("AGILE-GS+ gives at least 3 of the N reranked slots to uniform probes",
                lambda c: dataclasses.replace(c, probes=3)),
    "eig": ("the paper's objective: the expected information gain sum log(1 + H_v / Hhat) "
            "in the rerank and the anchor, whatever the method's default",
            lambda c: dataclasses.replace(c, objective="eig")),
    "target": ("the target objective: the fall of the pool's predicted render variance; "
               "full_eig scores and AGILE-GS+ reranks by it (T from 8 farthest-point pool "
               "views at half the width and height), and the anchor of AGILE-GS and AGILE-GS+ "
               "weights its samples by their information at 32 farthest-point pool views",
               lambda c: dataclasses.replace(c, objective="target")),
    "target_full": ("the target objective with T at the candidates' resolution and the "
                    "anchor's samples weighted at every pool view",
                    lambda c: dataclasses.replace(
                        c, objective="target", target_scale=1.0,
                        anchor=dataclasses.replace(c.anchor, target_poses=0))),
    "target16": ("the target objective with T from 16 farthest-point pool views",
                 lambda c: dataclasses.replace(c, objective="target", target_views=16)),
    "target4": ("the target objective with T from 4 farthest-point pool views",
                lambda c: dataclasses.replace(c, objective="target", target_views=4)),
    "spread_probes": ("AGILE-GS+ draws its probes in their farthest-point order from the "
                      "acquired views (the first is spread's pick) instead of uniformly",
                      lambda c: dataclasses.replace(c, probe_draw="spread")),
    "spread50": ("full_eig scores only the candidates at least half as far from the acquired "
                 "views as the farthest one (spread broken by the objective)",
                 lambda c: dataclasses.replace(c, spread_filter=0.5)),
    "spread75": ("full_eig scores only the candidates at least 75% as far from the acquired "
                 "views as the farthest one",
                 lambda c: dataclasses.replace(c, spread_filter=0.75)),
}
"""Variant options: name -> (what it changes, the change)."""

_BUDGET = re.compile(r"^n(\d+)$")


@dataclass(frozen=True)
class Variant:
    """A method with its settings; ``key`` names its runs.

    Attributes:
        key: the variant key (``agile_plus@n20``).
        method: the selection method.
        shortlist: the shortlist strategy.
        shortlist_size: N.
        options: the options after ``@``, budget excluded.
        group: which table it belongs to: the main comparison, the shortlist or budget
            ablation, or another variant.
    """

    key: str
    method: str
    shortlist: str = "leverage"
    shortlist_size: int = 10
    options: tuple[str, ...] = ()
    group: Group = "main"

    def config(self, base: SelectConfig | None = None) -> SelectConfig:
        """``base`` (default settings when None) with this variant's changes."""
        cfg = dataclasses.replace(base or SelectConfig(), shortlist=self.shortlist,  # type: ignore[arg-type]
                                  shortlist_size=self.shortlist_size)
        for name in self.options:
            cfg = OPTIONS[name][1](cfg)
        return cfg


def parse_variant(key: str, shortlist_size: int = 10, group: Group | None = None) -> Variant:
    """The variant named ``key`` (``shortlist_size``: N unless ``n<N>`` sets it); ValueError
    naming the unknown method or option."""
    method, _, rest = key.partition("@")
    if method not in method_names():
        raise ValueError(f"unknown method {method!r} in {key!r} (known: "
                         f"{', '.join(method_names())})")
    shortlist, size, options = "leverage", shortlist_size, []
    for opt in (o for o in rest.split("+") if o) if rest else ():
        budget = _BUDGET.match(opt)
        if budget:
            size = int(budget.group(1))
            if size < 1:
                raise ValueError(f"{key!r}: a shortlist budget must be >= 1")
        elif opt in SHORTLISTS:
            shortlist = opt
        elif opt in OPTIONS:
            options.append(opt)
        else:
            raise ValueError(f"unknown option {opt!r} in {key!r} (known: n<N>, "
                             f"{', '.join(OPTIONS)})")
    if group is None:
        group = "main" if not rest else "variant"
    return Variant(key, method, shortlist, size, tuple(options), group)


def build_variants(
    methods: Sequence[str],
    shortlist_size: int,
    strategies: Sequence[str] = (),
    budgets: Sequence[int] = (),
    shortlist_method: str = "agile",
) -> list[Variant]:
    """The runs' variants: the methods (any variant key), then the shortlist and budget
    ablations (deduplicated).

    Args:
        methods: method names or variant keys: the main comparison (its tables and paired
            differences).
        shortlist_size: the profile's N.
        strategies: shortlist strategies of the ablation, run with ``shortlist_method``.
        budgets: shortlist sizes N of the AGILE-GS+ budget ablation.
        shortlist_method: "agile" (the paper's table) or "agile_plus". With "agile" the
            "topnorm" strategy picks exactly what "leverage" picks: the first greedy
            ridge-leverage pick (S_0 = lambda_G I) is the row of largest norm.

    Raises:
        ValueError: an unknown method, option or strategy, or a budget < 1.
    """
    if shortlist_method not in ("agile", "agile_plus"):
        raise ValueError(f"--shortlist-method must be agile or agile_plus, got "
                         f"{shortlist_method!r}")
    out: dict[str, Variant] = {}
    for m in methods:
        try:
            out.setdefault(m, parse_variant(m, shortlist_size, "main"))
        except ValueError as exc:
            raise ValueError(f"--methods: {exc}") from None
    for s in strategies:
        if s not in SHORTLISTS:
            raise ValueError(f"--shortlist-strategies: unknown strategy {s!r} (known: "
                             f"{', '.join(SHORTLISTS)})")
        key = shortlist_method if s == "leverage" else f"{shortlist_method}@{s}"
        out.setdefault(key, parse_variant(key, shortlist_size, "shortlist"))
    for n in budgets:
        if int(n) < 1:
            raise ValueError(f"--budgets: a shortlist budget must be >= 1, got {n}")
        key = "agile_plus" if int(n) == shortlist_size else f"agile_plus@n{int(n)}"
        out.setdefault(key, parse_variant(key, shortlist_size, "budget"))
    return list(out.values())


def display_name(key: str) -> str:
    """Human name of a variant key (``agile_plus@n5`` -> ``AGILE-GS+ (N=5)``)."""
    if key in DISPLAY:
        return DISPLAY[key]
    base, _, extra = key.partition("@")
    name = DISPLAY.get(base, base)
    parts = []
    for opt in extra.split("+"):
        budget = _BUDGET.match(opt)
        if budget:
            return f"{name} (N={budget.group(1)})" if len(extra.split("+")) == 1 else (
                f"{name} [{extra}]")
        parts.append(SHORTLIST_DISPLAY.get(opt, opt))
    return f"{name} [{', '.join(parts)}]"
