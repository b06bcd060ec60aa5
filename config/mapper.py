"""Training settings of the mapper (:mod:`agilegs.service.mapper`), shared with the wire
(a session's ``MapperOptions.config`` patches them)."""

from __future__ import annotations

import dataclasses
from typing import Annotated, Any, Literal

from pydantic import BeforeValidator, Field, Strict
from pydantic.dataclasses import dataclass

from .types import (
    SETTINGS_CONFIG,
    Bool,
    Int,
    NonNegFloat,
    NonNegInt,
    OpenUnitFloat,
    PosFloat,
    PosInt,
    UnitFloat,
    integral,
)

__all__ = ["MapperConfig"]


@dataclass(config=SETTINGS_CONFIG)
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
    rasterizer: Literal["auto", "builtin", "gsplat"] = Field(
        default="auto", description="what renders the training views: builtin (this project's "
        "rasterizer, CPU and CUDA), gsplat (CUDA, float32; pip install 'agilegs[cuda]') or auto "
        "(gsplat where the map is a float32 map on CUDA and gsplat loads, else builtin)")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)
