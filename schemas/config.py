"""The settings on the wire: a request carries a *patch* of a settings class.

The settings themselves (:class:`SelectConfig`, :class:`MapperConfig` and their parts, the
constrained types, :func:`validate_config`) live in :mod:`agilegs.config`, which the maths
imports too; they are re-exported here. A request carries any subset of a settings class's
fields, merged over the session's defaults. :func:`patch_model` turns a settings class into a
pydantic model with the same fields, constraints and defaults; parsing a body with it
validates every field given, and it serialises (and :func:`patch_dict` returns) only the
fields that were set.
"""

from __future__ import annotations

import dataclasses
import sys
import typing
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, TypeAlias

from pydantic import BaseModel, ConfigDict, Field, create_model, model_serializer

from agilegs.config.mapper import MapperConfig
from agilegs.config.selection import (
    SelectConfig,
)

__all__ = [
    "MapperConfigPatch",
    "SelectConfigPatch",
    "patch_dict",
    "patch_model",
]


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
