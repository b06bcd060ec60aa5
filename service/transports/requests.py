"""The gateway's validation step: a request's model from its decoded data or its HTTP query
parameters, with a 422 that names every bad field (:meth:`Gateway.handle
<agilegs.service.transports.gateway.Gateway.handle>`, step 4)."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ValidationError

from agilegs.schemas import OPERATIONS
from agilegs.schemas.errors import ErrorCode
from agilegs.schemas.requests import check_request_id

from ..errors import ServiceError, invalid, not_found, validation_error

__all__ = ["QueryParams", "parse_request", "parse_request_id"]


class QueryParams(dict[str, str]):
    """A request's fields as they came in HTTP query parameters (strings)."""


def parse_request(op: str, payload: Any) -> BaseModel | None:
    """The request model of operation ``op`` from decoded data, or from
    :class:`QueryParams` (None for bodiless ones); a 422 naming every bad field."""
    spec = OPERATIONS.get(op)
    if spec is None:
        raise not_found("op", f"unknown operation {op!r}")
    if spec.request is None:
        return None
    if payload is None:
        raise invalid("body", "body: a request body is required")
    try:
        if isinstance(payload, QueryParams):
            return spec.request.model_validate_strings(dict(payload))
        return spec.request.model_validate(payload)
    except ValidationError as exc:
        raise validation_error(exc, "query" if isinstance(payload, QueryParams) else "body"
                               ) from None


def parse_request_id(text: str | None, field: str) -> str | None:
    """A write's request id (:mod:`agilegs.schemas.requests`) from ``text`` (None: none
    given); 400 naming ``field`` when it is not one."""
    if text is None:
        return None
    try:
        return check_request_id(text)
    except ValueError as exc:
        raise ServiceError(400, ErrorCode.BAD_REQUEST, f"{field}: {exc}", field) from None
