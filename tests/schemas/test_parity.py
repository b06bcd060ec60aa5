"""The wire contract and the code behind it name the same things."""

from __future__ import annotations

import dataclasses
from typing import get_args

from agilegs.schemas import OPERATIONS, keys
from agilegs.schemas import config as cfg
from agilegs.schemas import models as m
from agilegs.service.nbv.gaussians import GaussianMap
from agilegs.service.nbv.methods import get_method, method_names
from agilegs.service.nbv.selectors import METHODS, SHORTLISTS
from agilegs.service.sessions.registry import HANDLERS


def test_methods_shortlists_and_blocks_match_the_maths() -> None:
    assert get_args(m.Method) == method_names() == METHODS == cfg.METHODS
    assert get_args(m.ShortlistStrategy) == SHORTLISTS == cfg.SHORTLISTS
    assert get_args(cfg.FieldName) == m.FIELD_NAMES
    fields = {f.name for f in dataclasses.fields(GaussianMap)}
    assert set(m.FIELD_NAMES) == fields
    for name in method_names():
        assert get_method(name).name == name


def test_every_operation_has_a_handler_and_a_zenoh_key() -> None:
    assert set(HANDLERS) == set(OPERATIONS)
    assert set(keys.SERVICE_OPS) | set(keys.SESSION_OPS) == set(OPERATIONS)
    for op in OPERATIONS.values():
        assert (op.name in keys.SERVICE_OPS) == (op.scope == "service")


def test_config_patches_mirror_the_settings() -> None:
    for cls in (cfg.SelectConfig, cfg.AnchorConfig, cfg.ScoringConfig, cfg.MapperConfig):
        patch = cfg.patch_model(cls)
        assert set(patch.model_fields) == {f.name for f in dataclasses.fields(cls)}
        default = cls()
        # an empty patch is the defaults; every field given round-trips
        assert cfg.validate_config(cls, cfg.patch_dict(patch())) == default
        full = patch.model_validate(dataclasses.asdict(default))
        assert cfg.validate_config(cls, cfg.patch_dict(full)) == default
