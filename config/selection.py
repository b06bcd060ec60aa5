"""Settings of the selection methods (paper sections 4-5 and the baselines): what
``agilegs.service.nbv.select`` takes, and what a select request patches on the wire.

The settings are pydantic dataclasses: constructing one validates it (a ``ValueError``, a
pydantic ``ValidationError``, whose errors carry the field path), ``validate_config(cls,
data)`` validates plain data (a decoded JSON or msgpack object) or an instance, and the same
field definitions give the JSON schema that OpenAPI publishes (through
:mod:`agilegs.schemas.config`'s patches).
"""

from __future__ import annotations

import dataclasses
from typing import Annotated, Any, Literal, get_args

from pydantic import AfterValidator, BeforeValidator, Field, Strict, WithJsonSchema
from pydantic.dataclasses import dataclass

from .types import (
    SETTINGS_CONFIG,
    Bool,
    Count,
    Dim,
    Gain,
    GridEdge,
    HalfOpenUnit,
    Margin,
    PosFloat,
    Samples,
    Scale,
    Softness,
    Starts,
    Steps,
    SupportSamples,
    UnitFloat,
    Width,
    deep_merge,
    integral,
    validate_config,
)

__all__ = [
    "COVER_ZBUFFER",
    "FIELD_NAMES",
    "FISHERRF_FIELDS",
    "METHODS",
    "MIXED_ZBUFFER",
    "OBJECTIVES",
    "POINT_ZBUFFER",
    "METHOD_OBJECTIVES",
    "PRESETS",
    "SHORTLISTS",
    "AnchorConfig",
    "FieldName",
    "FisherRFConfig",
    "FisherRFField",
    "Method",
    "Objective",
    "ScoringConfig",
    "SelectConfig",
    "ShortlistStrategy",
    "for_method",
    "objective_of",
    "preset_config",
]

Method = Literal["random", "spread", "fisherrf", "cover", "full_eig", "agile", "agile_plus"]
"""The selection methods (the maths' registry holds one implementation per name): the
baselines Random, spread (farthest-point sampling over the pool: the candidate farthest from
every acquired view, position and rotation; it needs no map), FisherRF and COVER as their
authors' code computes them, ``full_eig`` (the
exact diagonal EIG of every eligible candidate: the ceiling AGILE-GS+ approximates), and
AGILE-GS / AGILE-GS+."""
METHODS: tuple[str, ...] = get_args(Method)
ShortlistStrategy = Literal["leverage", "knearest", "topnorm", "online"]
"""Shortlist strategies of ``agile`` / ``agile_plus``: the paper's ridge leverage and the
ablations."""
SHORTLISTS: tuple[str, ...] = get_args(ShortlistStrategy)
Objective = Literal["eig", "target"]
"""What the exact scoring maximises: the paper's expected information gain, or the worth of a
view on the target views' renders."""
OBJECTIVES: tuple[str, ...] = get_args(Objective)
METHOD_OBJECTIVES: dict[str, Objective] = {"agile": "target", "agile_plus": "target"}
"""The objective a method maximises when ``SelectConfig.objective`` is None, where it is not
the paper's ``eig``."""


def objective_of(method: str, config: SelectConfig) -> Objective:
    """The objective ``method`` maximises under ``config``: ``config.objective``, else the
    method's default (:data:`METHOD_OBJECTIVES`, else ``eig``)."""
    if config.objective is not None:
        return config.objective
    return METHOD_OBJECTIVES.get(method, "eig")


def for_method(config: SelectConfig, method: str) -> SelectConfig:
    """``config`` with its objective set to :func:`objective_of` ``method``."""
    if config.objective is not None:
        return config
    return dataclasses.replace(config, objective=objective_of(method, config))

FieldName = Literal["means", "log_scales", "quats", "opacity_logits", "sh"]
"""The parameter blocks of a Gaussian map."""
FIELD_NAMES: tuple[str, ...] = get_args(FieldName)
FisherRFField = Literal["means", "log_scales", "opacity_logits", "sh"]
"""The parameter blocks FisherRF's Hessian may cover (its code offers no exact rotation term
here: the rasterizer's quaternion gradient is taken w.r.t. the unnormalised quaternion)."""
FISHERRF_FIELDS: tuple[str, ...] = get_args(FisherRFField)



def _odd_covers(tests: tuple[tuple[int, float], ...]) -> tuple[tuple[int, float], ...]:
    for cover, _ in tests:
        if cover % 2 == 0:
            raise ValueError(f"a cover must be odd (got {cover})")
    return tests


def _unique(values: tuple[str, ...] | None) -> tuple[str, ...] | None:
    if values is not None and len(set(values)) != len(values):
        raise ValueError("must not repeat a parameter block")
    return values


Blocks = Annotated[tuple[FieldName, ...],
                   Field(min_length=1, json_schema_extra={"uniqueItems": True}),
                   AfterValidator(_unique)]
"""A non-empty set of parameter blocks (no repeats)."""

OcclusionTests = Annotated[
    tuple[tuple[Annotated[int, Strict(), Field(ge=1, le=63), BeforeValidator(integral),
                          WithJsonSchema({"type": "integer", "minimum": 1, "maximum": 63,
                                          "not": {"multipleOf": 2}})],
                Annotated[float, Strict(), Field(ge=0, le=10, allow_inf_nan=False)]], ...],
    Field(min_length=1, max_length=8),
    AfterValidator(_odd_covers),
]
"""Z-buffer visibility tests, each (cover in cells, odd; relative depth tolerance)."""

COVER_ZBUFFER: tuple[tuple[int, float], ...] = ((3, 0.10),)
"""Each occluder covers 3x3 z-buffer cells, 10% depth tolerance (the proxy's default)."""
POINT_ZBUFFER: tuple[tuple[int, float], ...] = ((1, 0.02),)
"""Each occluder on its own z-buffer cell, 2% depth tolerance."""
MIXED_ZBUFFER: tuple[tuple[int, float], ...] = POINT_ZBUFFER + COVER_ZBUFFER
"""The mean of the point and the 3x3 tests."""


@dataclass(config=SETTINGS_CONFIG)
class AnchorConfig:
    """Settings of the anchor ascent (paper section 4.1); each field documents its default."""

    psi: Literal["proxy", "exact"] = Field(
        default="proxy",
        description="the function the anchor ascends: 'proxy' (rasterization-free model of "
        "the view's information, fitted to Hhat) or 'exact' (the trace surrogate through the "
        "exact Fisher of a render at T)")
    model: Literal["fitted", "directional", "typical"] = Field(
        default="directional",
        description="the proxy's observation model: 'fitted' (a Gaussian's gain from a view "
        "is log(1 + a_i w_i(T)), a_i fitted to Hhat over the acquired views), 'directional' "
        "(per parameter slot, log(1 + a_iq w_i(T) f_q(T)) with f_q the slot's direction "
        "factor: a mean's world axis or a scale's local axis is seen across the view's rays, "
        "not along them; a_iq fitted to Hhat over the acquired views) or 'typical' (one "
        "typical Fisher value per parameter slot); without acquired views the typical model "
        "is used")
    unseen: Literal["quarter_view", "prior"] = Field(
        default="prior",
        description="the fitted model's Gaussians no acquired view saw: 'quarter_view' (as "
        "if a quarter of a typical view had seen them) or 'prior' (the seen Gaussians' "
        "median information per unit of footprint against their own Hhat, as the exact EIG)")
    unexplored: Bool = Field(
        default=True,
        description="the fitted and directional models also count the unexplored part of "
        "the map's extent (grid points no acquired view saw in front of the map's surfaces) "
        "as never-observed Gaussians, at the map's density")
    unexplored_cells: Annotated[int, Strict(), Field(ge=2, le=64),
                                BeforeValidator(integral)] = Field(
        default=16, description="grid points per axis of the unexplored space")
    unexplored_shells: Annotated[int, Strict(), Field(ge=1, le=64),
                                 BeforeValidator(integral)] = Field(
        default=1,
        description="radial shells of the unexplored space's expected density: an unexplored "
        "grid point holds as many Gaussians as the observed grid points at its distance from "
        "the map's centre do (1: the map's mean density everywhere)")
    unexplored_inside: Bool = Field(
        default=True,
        description="also count as unexplored the grid points the map's Gaussians enclose on "
        "all six axis directions (the inside of its surfaces, which no view sees)")
    anchors: Annotated[int, Strict(), Field(ge=1, le=8), BeforeValidator(integral)] = Field(
        default=3,
        description="anchors kept from distinct modes of psi (the ascents' end points, best "
        "first, each at least mode_separation from the better ones); with more than one, the "
        "starts are spread the same way and the shortlist is drawn across every anchor's "
        "support samples")
    mode_separation: Softness = Field(
        default=0.5,
        description="least SE(3) distance between two modes, in pool radii (a radian of "
        "rotation counts as one radius)")
    iterations: Steps = Field(default=3, description="most accepted ascent steps per start")
    step_size: Softness = Field(default=0.15,
        description="initial step length in the twist metric (0.15: ~9 degrees or 0.15 pool "
        "radii)")
    backtracks: Steps = Field(default=4,
        description="halvings of the step tried before a start stops")
    min_rel_gain: Gain = Field(
        default=1e-3, description="a start stops when an accepted step gains less than this "
        "fraction of psi")
    num_starts: Starts = Field(default=3,
        description="pool candidates used as starts, the best under the proxy")
    warm_start: Bool = Field(default=True,
                             description="also start from the previous anchor (warm state)")
    refit_every: Annotated[int, Strict(), Field(ge=1, le=1000),
                           BeforeValidator(integral)] = Field(
        default=4,
        description="the directional model's terms accumulated over the acquired views are "
        "kept in the warm state and extended by the new views' terms; they are recomputed "
        "over every acquired view every this many events, and whenever the map's Gaussian "
        "count changes or the acquired views are not the kept ones followed by new ones "
        "(1: every event)")
    start_samples: Count = Field(default=256,
        description="the pool is first ranked by a coarse psi over this many of the proxy's "
        "samples (drawn in proportion to their share of psi, reweighted: an unbiased "
        "estimate), and the full psi is evaluated only on the start_refined best under it "
        "(0: the full psi over the whole pool)")
    start_refined: Annotated[int, Strict(), Field(ge=1, le=100_000),
                             BeforeValidator(integral)] = Field(
        default=24,
        description="pool candidates, the best under the coarse psi, whose full psi is "
        "evaluated and among which the starts are chosen (with start_samples > 0)")
    num_gaussians: Count = Field(default=2000,
        description="Gaussians importance-sampled for the proxy (0: all)")
    target_poses: Count = Field(default=32,
        description="objective 'target': the proxy's samples are weighted by their "
        "information at this many of the targets, a farthest-point subsample of them (one "
        "proxy evaluation each, once per selection; 0: every target)")
    fit_gaussians: Count = Field(default=16384,
        description="the fitted and directional models read a seeded uniform sample of this "
        "many of the map's Gaussians, each standing for N / fit_gaussians of them: the "
        "visibility's occluders and the rates are drawn and fitted over it, and the proxy's "
        "importance sample drawn from it, so that their cost does not grow with the map "
        "(0: every Gaussian)")
    resolution: Width | None = Field(
        default=None,
        description="anchor image width in pixels (None: the proxy uses the candidates' "
        "intrinsics, the exact psi 64 pixels)")
    typical_fisher: Literal["h_acc", "start_view"] = Field(
        default="h_acc",
        description="the typical model's Fisher value per slot: from Hhat ('h_acc') or from "
        "one Fisher pass at the best start ('start_view', cached in the warm state)")
    envelope: Bool = Field(default=True,
                           description="keep the anchor inside the pool's envelope")
    envelope_margin: Margin = Field(
        default=0.05, description="relative margin on the envelope's radius range and, in "
        "radians, on its elevation range")
    visibility: Literal["transmittance", "zbuffer"] = Field(
        default="transmittance",
        description="the proxy's visibility of a Gaussian: 'transmittance' (the "
        "transmittance in front of it through the map, as the renderer "
        "composites, from per-pose deep opacity maps) or 'zbuffer' (the point z-buffer tests "
        "of occlusion_tests)")
    transmittance_cells: Annotated[int, Strict(), Field(ge=2, le=64),
                                   BeforeValidator(integral)] = Field(
        default=16, description="screen cells per image side of the deep opacity maps")
    transmittance_bins: Annotated[int, Strict(), Field(ge=1, le=128),
                                  BeforeValidator(integral)] = Field(
        default=32, description="depth slices of the deep opacity maps over the map's extent")
    occluders: Count = Field(default=2000,
        description="Gaussians forming the visibility: 'transmittance' draws this many in "
        "proportion to their optical mass (reweighted; 0: all), 'zbuffer' a seeded subset of "
        "opaque ones (0: no occlusion test)")
    occlusion_grid: GridEdge = Field(default=48,
        description="visibility 'zbuffer': edge of the proxy's z-buffer in cells")
    occlusion_tests: OcclusionTests = Field(
        default=COVER_ZBUFFER,
        description="visibility 'zbuffer': the tests, each [cover, tolerance]: every occluder "
        "covers cover x cover cells (odd) and a sample passes when its depth is within "
        "tolerance (relative) of the buffer; visibility is the fraction of tests passed")
    near_fraction: Softness = Field(
        default=0.05, description="the proxy's soft near plane, as a fraction of the pool "
        "radius")
    edge_softness: Softness = Field(
        default=0.05, description="width of the proxy's sigmoid image-bound test, as a "
        "fraction of the image width")
    carry_over_tolerance: UnitFloat = Field(
        default=0.0,
        description="reuse the previous event's pose-independent parts of the anchor (the "
        "proxy: its sample, rates, opacity maps and unexplored points; kept in the warm "
        "state) while the map's per-field sums of |parameter|, Hhat's per-field sums and "
        "the pool's radius are within this fraction of their values when the parts were "
        "built, with the same settings (0: rebuilt every event)")


@dataclass(config=SETTINGS_CONFIG)
class ScoringConfig:
    """Candidate scoring against the anchor (paper section 4.2) and the shortlist maths."""

    grid: GridEdge = Field(default=64,
        description="edge of the point z-buffer grid giving the support samples")
    ray_samples: Samples = Field(default=1,
        description="extra support samples along the anchor ray per surface sample")
    ray_min_fraction: HalfOpenUnit = Field(
        default=0.5, description="ray samples lie in [this, 1) x the surface depth")
    support_gaussians: Count = Field(default=65536,
        description="the support samples' surface points are the nearest means per grid "
        "cell among a seeded uniform sample of this many of the map's Gaussians, so that "
        "their cost does not grow with the map (0: every Gaussian)")
    max_samples: SupportSamples = Field(default=2048,
        description="K, at most this many support samples (a seeded subset beyond)")
    min_opacity: UnitFloat = Field(default=0.05,
                               description="Gaussians below this opacity are no support samples")
    jl_dim: Dim = Field(default=64, description="d, the Johnson-Lindenstrauss dimension")
    sigma_p: Scale | None = Field(
        default=None, description="positional tolerance of rho in world units (None: 0.5 x "
        "the pool's median camera distance from its centre)")
    gamma: Scale = Field(default=1.0, description="sharpness of the row weight rho^gamma")
    eps: Scale = Field(default=1e-3,
        description="the inverse-range regulariser, relative to the pool radius")
    ridge: Scale = Field(default=1e-2,
        description="lambda_G relative to the largest ||b_v||^2 (unit-free)")
    ridge_absolute: Bool = Field(default=False,
                                 description="take ridge as the absolute lambda_G")
    online_oversample: Softness = Field(default=1.0,
        description="oversampling of the 'online' shortlist")
    rot_weight: Scale | None = Field(
        default=None, description="world units per radian in the SE(3) distance of knearest "
        "and embodied mode (None: the pool's median camera distance from its centre)")
    near: Scale = Field(default=0.01, description="near plane of the frustum tests, world units")
    condition_on_acquired: Bool = Field(
        default=True, description="the leverage greedy starts from the acquired views' rows "
        "(S_0 = lambda_G I + B_acq^T B_acq); False: from lambda_G I (the paper)")


@dataclass(config=SETTINGS_CONFIG)
class FisherRFConfig:
    """FisherRF's settings, as its public code's defaults (JiangWenPL/FisherRF,
    ``active_train.py``)."""

    reg_lambda: PosFloat = Field(
        default=1e-6, description="lambda of the acquisition score sum H_v / (H_train + "
        "lambda) (--reg_lambda)")
    fields: Annotated[tuple[FisherRFField, ...],
                      Field(min_length=1, json_schema_extra={"uniqueItems": True}),
                      AfterValidator(_unique)] = Field(
        default=("means", "log_scales", "opacity_logits", "sh"),
        description="parameter blocks of the Hessian (the default leaves rotation out, as "
        "--filter_out_grad rotation)")


@dataclass(config=SETTINGS_CONFIG)
class SelectConfig:
    """Settings of ``agilegs.service.nbv.select``; every field settable per call."""

    shortlist_size: Annotated[int, Strict(), Field(ge=1, le=1024),
                              BeforeValidator(integral)] = Field(default=10,
        description="N, the shortlist budget of agile / agile_plus")
    shortlist: ShortlistStrategy = Field(
        default="leverage", description="shortlist strategy: the paper's 'leverage', or the "
        "ablations 'knearest', 'topnorm', 'online'")
    probes: Annotated[int, Strict(), Field(ge=0, le=512), BeforeValidator(integral)] = Field(
        default=1,
        description="agile_plus: the least number of the N reranked slots given to probes, "
        "candidates drawn uniformly from the eligible ones outside the model's shortlist. Their "
        "exact EIG beside the model's tells whether the model still predicts it: an event "
        "where a probe beats every model candidate doubles the probes of the next event (at "
        "most half of N), one where the model wins halves them (at least this number); 0: "
        "none, every slot the model's (the paper)")
    probe_draw: Literal["uniform", "spread"] = Field(
        default="uniform",
        description="how agile_plus draws its probes among the eligible candidates outside "
        "the model's shortlist: 'uniform' (seeded by the event) or 'spread' (their "
        "farthest-point order from the acquired views: the first probe is spread's pick there)")
    embodied_k: Annotated[int, Strict(), Field(ge=1, le=100_000),
                          BeforeValidator(integral)] | None = Field(
        default=None, description="only the K candidates nearest the current view are "
        "eligible (None: all; the paper's embodied protocol uses 5)")
    embodied_metric: Literal["position", "se3"] = Field(
        default="position", description="the distance of embodied mode: 'position' (camera "
        "centres, as COVER's protocol picks its K nearest frames) or 'se3' (position and "
        "rotation, scoring.rot_weight world units per radian)")
    seed: Annotated[int, Strict(), Field(ge=0, le=2**63 - 1), BeforeValidator(integral)] = Field(
        default=0, description="seeds every random choice")
    fields: Blocks | None = Field(
        default=None, description="parameter blocks entering phi and psi (None: all five)")
    objective: Objective | None = Field(
        default=None,
        description="what full_eig, agile_plus's rerank and the anchor of agile and agile_plus "
        "maximise: 'eig' (the paper's expected information gain sum log(1 + H_v / Hhat) over "
        "every parameter) or 'target' (the fall of the target views' predicted render "
        "variance, sum T H_v / (Hhat (Hhat + H_v)) with T the targets' summed Fisher: the "
        "request's target poses, else the pool); None: the method's default (docs/maths.md)")
    spread_filter: UnitFloat = Field(
        default=0.0,
        description="full_eig scores only the eligible candidates whose distance to the "
        "nearest acquired view (spread's SE(3) distance) is at least this fraction of the "
        "farthest candidate's: spread broken by the objective (0: every eligible candidate, "
        "1: spread's own pick)")
    target_views: Annotated[int, Strict(), Field(ge=1, le=256),
                            BeforeValidator(integral)] = Field(
        default=8,
        description="objective 'target': the targets' Fisher T is summed over this many of "
        "them, a farthest-point subsample (one Fisher pass each, once per selection)")
    target_scale: Annotated[float, Strict(), Field(gt=0, le=1, allow_inf_nan=False)] = Field(
        default=0.5,
        description="objective 'target': the targets' Fisher T is computed on images this "
        "fraction of the candidates' width and height (same field of view); T's scale does "
        "not change which view is best, its shape over the parameters does, and a quarter "
        "of the pixels costs about a quarter of the time")
    anchor: AnchorConfig = Field(default_factory=AnchorConfig)
    scoring: ScoringConfig = Field(default_factory=ScoringConfig)
    cover_bins: Dim = Field(default=128, description="COVER's direction bins per Gaussian")
    cover_resolution: Width | None = Field(
        default=None, description="COVER's render width in pixels (None: the candidates')")
    cover_radius_clip: Annotated[float, Strict(), Field(ge=0, le=1e6, allow_inf_nan=False)] = Field(
        default=3.0, description="COVER fills no bin for a Gaussian whose projected radius "
        "in an acquired view is at most this many pixels on both axes (its code's gsplat "
        "projection, radius_clip=3.0)")
    fisherrf: FisherRFConfig = Field(default_factory=FisherRFConfig)
    fisher_background: tuple[UnitFloat, UnitFloat, UnitFloat] | None = Field(
        default=None, description="background colour of the Fisher renders (None: black); "
        "give the background the map is trained with")

    def validate(self) -> None:
        """Validate the settings as they are now (after attribute assignments too)."""
        validate_config(SelectConfig, self)


PRESETS: dict[str, dict[str, Any]] = {
    "paper": {
        "anchor": {"psi": "exact", "anchors": 1, "model": "fitted", "unexplored": False},
        "scoring": {"condition_on_acquired": False},
        "probes": 0,
        "objective": "eig",
    },
}
"""Named SelectConfig patches. ``paper``: AGILE-GS as the paper states it: one anchor, which
ascends the trace surrogate of the exact Fisher rendered at T (through the rasterizer; its
starts are the pool's best under the isotropic fitted proxy), the leverage greedy starts
from lambda_G I, and AGILE-GS+ reranks the model's shortlist alone (no probes)."""


def preset_config(name: str, **overrides: Any) -> SelectConfig:
    """The SelectConfig of preset ``name`` (:data:`PRESETS`), ``overrides`` merged over it
    (nested settings as mappings)."""
    if name not in PRESETS:
        raise ValueError(f"preset must be one of {sorted(PRESETS)}, got {name!r}")
    return validate_config(SelectConfig, deep_merge(PRESETS[name], overrides))
