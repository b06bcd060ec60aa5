"""The wire contract and the code behind it name the same things."""

from __future__ import annotations

import dataclasses
from typing import get_args

from agilegs.config.mapper import MapperConfig
from agilegs.config.selection import (
    FIELD_NAMES,
    SHORTLISTS,
    AnchorConfig,
    FieldName,
    Method,
    ScoringConfig,
    SelectConfig,
    ShortlistStrategy,
)
from agilegs.config.types import validate_config
from agilegs.schemas import OPERATIONS, keys
from agilegs.schemas import config as cfg
from agilegs.service.nbv import METHODS, GaussianMap
from agilegs.service.nbv.methods.base import get_method, method_names
from agilegs.service.sessions.registry import HANDLERS


def test_methods_shortlists_and_blocks_match_the_maths() -> None:
    assert get_args(Method) == method_names() == METHODS
    assert get_args(ShortlistStrategy) == SHORTLISTS
    assert get_args(FieldName) == FIELD_NAMES
    fields = {f.name for f in dataclasses.fields(GaussianMap)}
    assert set(FIELD_NAMES) == fields
    for name in method_names():
        assert get_method(name).name == name


def test_every_operation_has_a_handler_and_a_zenoh_key() -> None:
    assert set(HANDLERS) == set(OPERATIONS)
    assert set(keys.SERVICE_OPS) | set(keys.SESSION_OPS) == set(OPERATIONS)
    for op in OPERATIONS.values():
        assert (op.name in keys.SERVICE_OPS) == (op.scope == "service")


def test_config_patches_mirror_the_settings() -> None:
    for cls in (SelectConfig, AnchorConfig, ScoringConfig, MapperConfig):
        patch = cfg.patch_model(cls)
        assert set(patch.model_fields) == {f.name for f in dataclasses.fields(cls)}
        default = cls()
        # an empty patch is the defaults; every field given round-trips
        assert validate_config(cls, cfg.patch_dict(patch())) == default
        full = patch.model_validate(dataclasses.asdict(default))
        assert validate_config(cls, cfg.patch_dict(full)) == default
