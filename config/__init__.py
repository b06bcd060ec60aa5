"""agilegs.config: the typed settings of the maths and the mapper, and the tolerances of the
geometry conventions.

Neither wire nor maths: it depends on pydantic only, and both the maths
(:mod:`agilegs.service.nbv`, :mod:`agilegs.service.mapper`) and the wire contract
(:mod:`agilegs.schemas`, whose :mod:`agilegs.schemas.config` turns each settings class into the
patch a request carries) import it. :mod:`.selection` holds :class:`SelectConfig` and its
parts, :mod:`.mapper` :class:`MapperConfig`, :mod:`.types` the constrained scalars and
:func:`validate_config`, :mod:`.geometry` the pose tolerances.
"""

from .geometry import MAX_COORD, ORTHONORMAL_ATOL, QUATERNION_NORM_ATOL
from .mapper import MapperConfig
from .selection import (
    COVER_ZBUFFER,
    FIELD_NAMES,
    FISHERRF_FIELDS,
    METHODS,
    MIXED_ZBUFFER,
    POINT_ZBUFFER,
    PRESETS,
    SHORTLISTS,
    AnchorConfig,
    FieldName,
    FisherRFConfig,
    FisherRFField,
    Method,
    ScoringConfig,
    SelectConfig,
    ShortlistStrategy,
    preset_config,
)
from .types import deep_merge, integral, validate_config

__all__ = [
    "COVER_ZBUFFER",
    "FIELD_NAMES",
    "FISHERRF_FIELDS",
    "MAX_COORD",
    "METHODS",
    "MIXED_ZBUFFER",
    "ORTHONORMAL_ATOL",
    "POINT_ZBUFFER",
    "PRESETS",
    "QUATERNION_NORM_ATOL",
    "SHORTLISTS",
    "AnchorConfig",
    "FieldName",
    "FisherRFConfig",
    "FisherRFField",
    "MapperConfig",
    "Method",
    "ScoringConfig",
    "SelectConfig",
    "ShortlistStrategy",
    "deep_merge",
    "integral",
    "preset_config",
    "validate_config",
]
