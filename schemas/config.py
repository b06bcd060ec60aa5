"""Typed settings of the selection methods and of the mapper, and their wire patches.

The settings are pydantic dataclasses: constructing one validates it (a ``ValueError``, a
pydantic ``ValidationError``, whose errors carry the field path), ``TypeAdapter(cls)``
validates plain data (a decoded JSON or msgpack object), and the same field definitions give
the JSON schema that OpenAPI publishes. They hold no tensors, so the client and the maths
share them: ``agilegs.service.nbv`` takes a :class:`SelectConfig`, the mapper a
:class:`MapperConfig`.

On the wire a request carries a *patch*: any subset of the fields, merged over the session's
defaults. :func:`patch_model` turns a settings class into a pydantic model with the same
fields, constraints and defaults; parsing a body with it validates every field given, and it
serialises (and :func:`patch_dict` returns) only the fields that were set.
"""

from __future__ import annotations

import dataclasses
import sys
import typing
from collections.abc import Mapping
from typing import TYPE_CHECKING, Annotated, Any, Literal, TypeAlias, TypeVar, get_args

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    Strict,
    TypeAdapter,
    WithJsonSchema,
    create_model,
    model_serializer,
)
from pydantic.dataclasses import dataclass

from .forms import integral

__all__ = [
    "FIELD_NAMES",
    "FISHERRF_FIELDS",
    "METHODS",
    "PRESETS",
    "SHORTLISTS",
    "AnchorConfig",
    "FieldName",
    "FisherRFConfig",
    "MapperConfig",
    "MapperConfigPatch",
    "Method",
    "ScoringConfig",
    "SelectConfig",
    "SelectConfigPatch",
    "ShortlistStrategy",
    "deep_merge",
    "patch_dict",
    "patch_model",
    "preset_config",
    "validate_config",
]

Method = Literal["random", "fisherrf", "cover", "full_eig", "agile", "agile_plus"]
"""The selection methods (the maths' registry holds one implementation per name): the
baselines Random, FisherRF and COVER as their authors' code computes them, ``full_eig`` (the
exact diagonal EIG of every eligible candidate: the ceiling AGILE-GS+ approximates), and
AGILE-GS / AGILE-GS+."""
METHODS: tuple[str, ...] = get_args(Method)
ShortlistStrategy = Literal["leverage", "knearest", "topnorm", "online"]
"""Shortlist strategies of ``agile`` / ``agile_plus``: the paper's ridge leverage and the
ablations."""
SHORTLISTS: tuple[str, ...] = get_args(ShortlistStrategy)
FieldName = Literal["means", "log_scales", "quats", "opacity_logits", "sh"]
"""The parameter blocks of a Gaussian map."""
FIELD_NAMES: tuple[str, ...] = get_args(FieldName)
FisherRFField = Literal["means", "log_scales", "opacity_logits", "sh"]
"""The parameter blocks FisherRF's Hessian may cover (its code offers no exact rotation term
here: the rasterizer's quaternion gradient is taken w.r.t. the unnormalised quaternion)."""
FISHERRF_FIELDS: tuple[str, ...] = get_args(FisherRFField)

_CONFIG = ConfigDict(extra="forbid", revalidate_instances="always")

# strict scalars: a JSON string is not a number, a number is not a bool
Int = Annotated[int, Strict(), BeforeValidator(integral)]
Float = Annotated[float, Strict(), Field(allow_inf_nan=False)]
Bool = Annotated[bool, Strict()]


INT_MAX = 2**31 - 1
"""Largest value of a count or size setting without a bound of its own."""
PosInt = Annotated[int, Strict(), Field(ge=1, le=INT_MAX), BeforeValidator(integral)]
NonNegInt = Annotated[int, Strict(), Field(ge=0, le=INT_MAX), BeforeValidator(integral)]
PosFloat = Annotated[float, Strict(), Field(gt=0, allow_inf_nan=False)]
NonNegFloat = Annotated[float, Strict(), Field(ge=0, allow_inf_nan=False)]
UnitFloat = Annotated[float, Strict(), Field(ge=0, le=1, allow_inf_nan=False)]
OpenUnitFloat = Annotated[float, Strict(), Field(gt=0, lt=1)]

# the bounds of the selection settings that set its cost (time, memory): every request that
# keeps within them is answered
Steps = Annotated[int, Strict(), Field(ge=0, le=100), BeforeValidator(integral)]
"""Ascent steps or step halvings: at most 100."""
Starts = Annotated[int, Strict(), Field(ge=1, le=64), BeforeValidator(integral)]
Count = Annotated[int, Strict(), Field(ge=0, le=10_000_000), BeforeValidator(integral)]
"""A number of Gaussians or samples (0 where the field says so): at most 10^7."""
GridEdge = Annotated[int, Strict(), Field(ge=1, le=1024), BeforeValidator(integral)]
"""The edge of a z-buffer or support grid, in cells: at most 1024."""
Width = Annotated[int, Strict(), Field(ge=4, le=4096), BeforeValidator(integral)]
"""A render width in pixels, 4 to 4096 (and its square within the server's max_image_pixels)."""
Dim = Annotated[int, Strict(), Field(ge=1, le=4096), BeforeValidator(integral)]
Samples = Annotated[int, Strict(), Field(ge=0, le=64), BeforeValidator(integral)]
SupportSamples = Annotated[int, Strict(), Field(ge=1, le=65_536), BeforeValidator(integral)]
Scale = Annotated[float, Strict(), Field(ge=1e-12, le=1e6, allow_inf_nan=False)]
"""A positive length, weight or tolerance: 1e-12 to 1e6."""
Softness = Annotated[float, Strict(), Field(ge=1e-6, le=10, allow_inf_nan=False)]
Margin = Annotated[float, Strict(), Field(ge=0, le=0.9, allow_inf_nan=False)]
HalfOpenUnit = Annotated[float, Strict(), Field(ge=0, lt=1, allow_inf_nan=False)]
Gain = Annotated[float, Strict(), Field(ge=-1e6, le=1e6, allow_inf_nan=False)]


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


# ============================================================================ selection
@dataclass(config=_CONFIG)
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
    num_gaussians: Count = Field(default=2000,
        description="Gaussians importance-sampled for the proxy (0: all)")
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


@dataclass(config=_CONFIG)
class ScoringConfig:
    """Candidate scoring against the anchor (paper section 4.2) and the shortlist maths."""

    grid: GridEdge = Field(default=64,
        description="edge of the point z-buffer grid giving the support samples")
    ray_samples: Samples = Field(default=1,
        description="extra support samples along the anchor ray per surface sample")
    ray_min_fraction: HalfOpenUnit = Field(
        default=0.5, description="ray samples lie in [this, 1) x the surface depth")
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


@dataclass(config=_CONFIG)
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


@dataclass(config=_CONFIG)
class SelectConfig:
    """Settings of ``agilegs.service.nbv.select``; every field settable per call."""

    shortlist_size: Annotated[int, Strict(), Field(ge=1, le=1024),
                              BeforeValidator(integral)] = Field(default=10,
        description="N, the shortlist budget of agile / agile_plus")
    shortlist: ShortlistStrategy = Field(
        default="leverage", description="shortlist strategy: the paper's 'leverage', or the "
        "ablations 'knearest', 'topnorm', 'online'")
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
    },
}
"""Named SelectConfig patches. ``paper``: AGILE-GS as the paper states it: one anchor, which
ascends the trace surrogate of the exact Fisher rendered at T (through the rasterizer; its
starts are the pool's best under the isotropic fitted proxy), and the leverage greedy starts
from lambda_G I."""


def preset_config(name: str, **overrides: Any) -> SelectConfig:
    """The SelectConfig of preset ``name`` (:data:`PRESETS`), ``overrides`` merged over it
    (nested settings as mappings)."""
    if name not in PRESETS:
        raise ValueError(f"preset must be one of {sorted(PRESETS)}, got {name!r}")
    return validate_config(SelectConfig, deep_merge(PRESETS[name], overrides))


# ============================================================================ the mapper
@dataclass(config=_CONFIG)
class MapperConfig:
    """Training settings of the mapper (3DGS defaults unless said otherwise)."""

    lr_means: PosFloat = Field(default=1.6e-4,
        description="initial learning rate of the means, times the scene extent")
    lr_means_final: PosFloat = Field(default=1.6e-6,
        description="final learning rate of the means, times the scene extent")
    lr_means_steps: PosInt = Field(default=30_000,
        description="steps of the exponential decay from lr_means to lr_means_final")
    lr_log_scales: PosFloat = Field(default=5e-3, description="learning rate of the log-scales")
    lr_quats: PosFloat = Field(default=1e-3, description="learning rate of the quaternions")
    lr_opacity: PosFloat = Field(default=5e-2, description="learning rate of the opacity logits")
    lr_sh_dc: PosFloat = Field(default=2.5e-3,
        description="learning rate of the SH DC coefficients")
    lr_sh_rest: PosFloat = Field(default=2.5e-3 / 20,
        description="learning rate of the higher SH bands")
    adam_eps: PosFloat = Field(default=1e-15, description="Adam epsilon")
    lambda_dssim: UnitFloat = Field(default=0.2,
        description="weight of D-SSIM in (1 - l) L1 + l (1 - SSIM)")
    lambda_depth: NonNegFloat = Field(
        default=0.1, description="weight of the depth L1 for views with depth (0: off)")
    scene_extent: PosFloat | None = Field(
        default=None, description="scene radius scaling lr_means, percent_dense and "
        "max_world_scale (None: estimated from the cameras or the Gaussians)")
    sh_degree: Annotated[int, Strict(), Field(ge=0, le=3), BeforeValidator(integral)] = Field(
        default=3, description="SH degree of Gaussians created from points or depth")
    sh_degree_interval: PosInt | None = Field(
        default=1000, description="the active SH degree grows by one every this many steps "
        "(None: every band from the start)")
    densify: Bool = Field(default=True, description="enable densification and pruning")
    densify_from: NonNegInt = Field(default=100, description="first step at which to densify")
    densify_every: PosInt = Field(default=100, description="densify every this many steps")
    densify_until: PosInt | None = Field(
        default=15_000, description="last step at which to densify or reset opacity (None: "
        "forever)")
    densify_grad_threshold: NonNegFloat = Field(
        default=2e-4, description="mean NDC-space gradient norm that triggers densification")
    percent_dense: PosFloat = Field(default=0.01,
        description="clone when the largest scale <= this x extent, else split")
    split_samples: Annotated[int, Strict(), Field(ge=2, le=16), BeforeValidator(integral)] = Field(
        default=2, description="children of a split Gaussian")
    split_scale_divisor: PosFloat = Field(default=1.6,
        description="children's scales are the parent's divided by this")
    prune_opacity: NonNegFloat = Field(
        default=0.005, description="prune Gaussians with opacity below this")
    prune_large_from: NonNegInt | None = Field(
        default=3000, description="after this step also prune Gaussians larger than "
        "max_screen_radius pixels or max_world_scale x extent (None: never)")
    max_screen_radius: PosFloat = Field(default=20.0,
        description="screen-radius threshold of the large-Gaussian pruning")
    max_world_scale: PosFloat = Field(default=0.1,
        description="world-scale threshold (x extent) of that pruning")
    opacity_reset_every: PosInt | None = Field(
        default=3000, description="reset opacities every this many steps (None: never)")
    opacity_reset_value: OpenUnitFloat = Field(
        default=0.01, description="opacities are clamped to at most this at a reset")
    max_gaussians: PosInt | None = Field(
        default=1_000_000, description="cap on the number of Gaussians (None: no cap)")
    background: tuple[UnitFloat, UnitFloat, UnitFloat] = Field(
        default=(0.0, 0.0, 0.0), description="RGB composited behind the Gaussians in training "
        "renders")
    init_opacity: OpenUnitFloat = Field(
        default=0.1, description="opacity of Gaussians created from points or depth")
    init_stride: PosInt = Field(default=4,
        description="pixel stride of the back-projection grid of depth maps")
    init_max_points: PosInt | None = Field(
        default=50_000, description="at most this many points per back-projection (None: all)")
    extend_from_depth: Bool = Field(
        default=True, description="a view with depth adds Gaussians where the rendered alpha "
        "is below extend_alpha_threshold")
    extend_alpha_threshold: UnitFloat = Field(default=0.5,
        description="alpha under which a pixel counts as uncovered")
    seed: Int = Field(default=0, description="seed of the view sampler, the split sampler and "
                      "point subsampling")
    tile_size: PosInt = Field(default=8, description="rasterizer tile edge in pixels")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


# ============================================================================ validation
C = TypeVar("C")
_ADAPTERS: dict[type, TypeAdapter[Any]] = {}


def _adapter(cls: type[C]) -> TypeAdapter[C]:
    if cls not in _ADAPTERS:
        _ADAPTERS[cls] = TypeAdapter(cls)
    return _ADAPTERS[cls]


def validate_config(cls: type[C], data: Any) -> C:
    """``cls`` from plain data (a mapping) or an instance, validated; pydantic's
    ``ValidationError`` (a ``ValueError``) names every bad field by its path."""
    return _adapter(cls).validate_python(data)


def deep_merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` updated by ``over``, nested mappings merged key by key."""
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = value
    return out


# ============================================================================ patches
class _Patch(BaseModel):
    """A subset of a settings class's fields; dumps only the fields that were set."""

    model_config = ConfigDict(extra="forbid")

    @model_serializer(mode="wrap")
    def _only_set(self, handler: Any) -> Any:
        data = handler(self)
        return {k: v for k, v in data.items() if k in self.model_fields_set}


_PATCHES: dict[type, type[_Patch]] = {}


def patch_model(cls: type) -> type[_Patch]:
    """The wire patch of settings class ``cls``: a model with the same fields, types,
    constraints and defaults (nested settings become nested patches); any subset may be
    given, and only what was given is serialised."""
    if cls in _PATCHES:
        return _PATCHES[cls]
    hints = typing.get_type_hints(cls, vars(sys.modules[cls.__module__]), include_extras=True)
    fields: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        info = f.default if isinstance(f.default, type(Field())) else None
        description = getattr(info, "description", None)
        if dataclasses.is_dataclass(hint):
            sub = patch_model(hint)  # type: ignore[arg-type]
            fields[f.name] = (sub, Field(default_factory=sub, description=description))
            continue
        default = info.get_default(call_default_factory=True) if info is not None else f.default
        fields[f.name] = (hint, Field(default=default, description=description))
    model = create_model(
        f"{cls.__name__}Patch", __base__=_Patch, __doc__=f"Any subset of {cls.__name__}'s "
        f"fields, merged over the session's settings. {cls.__doc__ or ''}".strip(),
        __module__=__name__, **fields,
    )
    _PATCHES[cls] = model
    return model


def patch_dict(patch: BaseModel | Mapping[str, Any] | None) -> dict[str, Any]:
    """The fields set in ``patch`` as plain data (nested patches too); {} for None."""
    if patch is None:
        return {}
    if isinstance(patch, BaseModel):
        return dict(patch.model_dump(mode="python"))
    return dict(patch)


if TYPE_CHECKING:  # generated classes: type checkers see the base
    SelectConfigPatch: TypeAlias = _Patch
    MapperConfigPatch: TypeAlias = _Patch
else:
    SelectConfigPatch = patch_model(SelectConfig)
    MapperConfigPatch = patch_model(MapperConfig)
