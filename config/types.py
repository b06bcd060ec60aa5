"""The building blocks of the settings: strict constrained scalars, the pydantic config every
settings class shares, and validation of plain data or an instance.

Depends on pydantic only (no torch, no wire, no maths), so that the maths
(``agilegs.service.nbv``), the mapper and the wire contract (``agilegs.schemas``) share one
definition of every setting.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any, TypeVar

from pydantic import BeforeValidator, ConfigDict, Field, Strict, TypeAdapter

__all__ = [
    "INT_MAX",
    "SETTINGS_CONFIG",
    "Bool",
    "Count",
    "Dim",
    "Float",
    "Gain",
    "GridEdge",
    "HalfOpenUnit",
    "Int",
    "Margin",
    "NonNegFloat",
    "NonNegInt",
    "OpenUnitFloat",
    "PosFloat",
    "PosInt",
    "Samples",
    "Scale",
    "Softness",
    "Starts",
    "Steps",
    "SupportSamples",
    "UnitFloat",
    "Width",
    "deep_merge",
    "integral",
    "validate_config",
]


def integral(value: Any) -> Any:
    """An integral float (``2.0``, which JSON Schema counts as an integer) as an int; any
    other value unchanged (a strict int then refuses strings, bools and fractions)."""
    if type(value) is float and value.is_integer() and -(2.0**63) <= value < 2.0**64:
        return int(value)
    return value


SETTINGS_CONFIG = ConfigDict(extra="forbid", revalidate_instances="always")

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


