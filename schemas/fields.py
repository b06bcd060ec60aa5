"""Field types and helpers the wire models share: ids, the wire's own size caps, strictness."""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BeforeValidator, ConfigDict, Field, StringConstraints
from pydantic.json_schema import JsonDict

from agilegs.config.types import integral

__all__ = [
    "MAX_OBSERVATIONS_WIRE",
    "MAX_POOL_WIRE",
    "SESSION_ID_PATTERN",
    "STRICT",
    "UNIQUE",
    "EmbodiedK",
    "Id",
    "Seed",
    "SessionId",
    "ShortlistSize",
    "StepsPerView",
    "narrowed",
    "unique",
]


SESSION_ID_PATTERN = r"^[A-Za-z0-9_-]{1,64}$"
SessionId = Annotated[str, StringConstraints(pattern=SESSION_ID_PATTERN)]
"""A session id: 1 to 64 characters from ``[A-Za-z0-9_-]`` (safe in URLs and Zenoh keys)."""

Id = Annotated[int, Field(ge=0, le=2**53), BeforeValidator(integral)]
MAX_POOL_WIRE = 100_000  # the schema's own cap; the server's pool_size setting is lower
MAX_OBSERVATIONS_WIRE = 256


UNIQUE: JsonDict = {"uniqueItems": True}
STRICT = ConfigDict(extra="forbid", strict=True)


ShortlistSize = Annotated[int, Field(ge=1, le=1024), BeforeValidator(integral)]
EmbodiedK = Annotated[int, Field(ge=1, le=100_000), BeforeValidator(integral)]
Seed = Annotated[int, Field(ge=0, le=2**63 - 1), BeforeValidator(integral)]
StepsPerView = Annotated[int, Field(ge=0, le=1_000_000), BeforeValidator(integral)]


def unique(values: list[Any] | None, what: str) -> None:
    """ValueError naming the first repeated entry of ``values`` (called ``what``)."""
    if values is not None and len(set(values)) != len(values):
        seen: set[Any] = set()
        for i, v in enumerate(values):
            if v in seen:
                raise ValueError(f"{what} must be unique ({what}[{i}] = {v!r} repeats)")
            seen.add(v)


def narrowed(extra: dict[str, Any]) -> Any:
    """A field ``json_schema_extra`` that narrows the referenced model of the field (or of its
    items) with ``extra`` (``allOf`` the reference, plus ``extra``)."""

    def narrow(js: dict[str, Any]) -> None:
        for holder in ([js.get("items", {})] + list(js.get("items", {}).get("anyOf", []))
                       + list(js.get("anyOf", []))):
            if "$ref" in holder:
                ref = holder.pop("$ref")
                holder.update({"allOf": [{"$ref": ref}], **extra})

    return narrow
