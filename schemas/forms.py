"""JSON Schema of request models that come in several forms, and of the rules JSON Schema
cannot state.

A model such as :class:`~agilegs.schemas.geometry.Pose` takes exactly one of several forms
(``matrix``, or ``position`` + ``orientation_xyzw``). Pydantic publishes its fields as a flat
object where any mix is allowed; :func:`one_of` replaces that with a ``oneOf`` of complete,
mutually exclusive branches (each lists every field, the ones its form takes required, the
ones it excludes as ``null``), so that a schema-valid body is one the server accepts.

A rule JSON Schema cannot state (a rotation orthonormal to a tolerance, ``min < max`` on
every axis, a byte length that follows from a shape) stays in the field's description and is
also named in the schema's :data:`RULES_KEY` extension, for tools that generate data.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any

from pydantic import BeforeValidator

from agilegs.config.types import integral

__all__ = ["RULES_KEY", "Form", "WireInt", "integral", "one_of"]

RULES_KEY = "x-agilegs-rules"
"""Schema extension listing the rules a value must meet beyond its JSON Schema (the field's
description says each in words): ``rotation`` (a pose's rotation is proper and orthonormal
within 1e-3), ``unit-quaternion`` (norm within 1e-3 of 1), ``ordered-bounds`` (``min <
max`` on every axis), ``array-size`` (``data`` holds prod(shape) x itemsize bytes),
``image-size`` (an image matches its intrinsics), ``same-length`` (``ids`` has one entry per
pose), ``gaussian-arrays`` (the five arrays describe the same N Gaussians), ``gaussians-file`` (a
readable .ply or .splat file), ``pixels`` (width x height within the server's
max_image_pixels)."""

Schema = dict[str, Any]


WireInt = Annotated[int, BeforeValidator(integral)]
"""An integer on the wire: an int, or a float with an integral value (JSON Schema's
``integer``); strict models refuse strings and bools for it. Give its bounds as the field's
``Field(ge=..., le=...)``; inside another ``Annotated``, put ``BeforeValidator(integral)``
after the constraints instead (pydantic then publishes them as minimum / maximum)."""


@dataclass(frozen=True)
class Form:
    """One form of a model: the fields it requires, those it excludes (absent or null),
    and schemas that replace a field's own in this form (a ``const`` discriminator)."""

    title: str
    required: tuple[str, ...]
    excluded: tuple[str, ...] = ()
    override: Mapping[str, Schema] = field(default_factory=dict)
    description: str | None = None


def _non_null(prop: Schema) -> Schema:
    """``prop`` without its ``null`` alternative (a field that is optional in the model but
    required in a form)."""
    out = {k: v for k, v in prop.items() if k not in ("default",)}
    alts = out.get("anyOf")
    if isinstance(alts, list):
        kept = [a for a in alts if a != {"type": "null"}]
        if len(kept) == 1:
            del out["anyOf"]
            out = {**kept[0], **out}
        else:
            out["anyOf"] = kept
    return out


def one_of(forms: Iterable[Form], rules: Iterable[str] = ()) -> Callable[[Schema], None]:
    """A ``json_schema_extra`` that publishes a model as a ``oneOf`` of its ``forms`` (as
    the one form itself when there is one)."""
    forms = tuple(forms)

    def extra(schema: Schema) -> None:
        props: Schema = schema.pop("properties")
        schema.pop("required", None)
        schema.pop("type", None)
        additional = schema.pop("additionalProperties", False)
        branches = []
        for form in forms:
            bprops: Schema = {}
            for name, prop in props.items():
                if name in form.override:
                    bprops[name] = copy.deepcopy(form.override[name])
                elif name in form.excluded:
                    bprops[name] = {"type": "null"}
                elif name in form.required:
                    bprops[name] = _non_null(prop)
                else:
                    bprops[name] = copy.deepcopy(prop)
            branch: Schema = {"title": form.title, "type": "object", "properties": bprops,
                              "required": list(form.required),
                              "additionalProperties": additional}
            if form.description:
                branch["description"] = form.description
            branches.append(branch)
        if len(branches) == 1:  # one form: the object itself
            schema.update({k: v for k, v in branches[0].items() if k != "title"})
        else:
            schema["oneOf"] = branches
        if rules:
            schema[RULES_KEY] = list(rules)

    return extra
