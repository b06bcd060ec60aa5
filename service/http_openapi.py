"""The OpenAPI description of the HTTP API: bodies in JSON and msgpack, the error bodies of
every operation, and the request models (bodies are decoded by the gateway, not FastAPI)."""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from agilegs.schemas import codec
from agilegs.schemas.errors import ErrorBody
from agilegs.schemas.keys import INSTANCE_ID_PATTERN
from agilegs.schemas.ops import OPERATIONS, Operation

__all__ = ["DESCRIPTION", "build_openapi", "route_openapi"]


def _error_responses(op: Operation) -> dict[int | str, dict[str, Any]]:
    codes = [400, 401, 406, 422, 500]
    if op.request is not None and not op.query:
        codes += [413, 415]
    if op.scope == "session":
        codes += [404, 409, 429]
    elif op.name == "create_session":
        codes += [404, 409, 429]  # 404: no instance answers as ?instance=
    if op.http_method != "GET":
        codes.append(507)  # the state folder is full
    return {
        c: {
            "model": ErrorBody,
            "description": "error (see the error codes)",
            "content": {codec.MSGPACK: {"schema": {"$ref": "#/components/schemas/ErrorBody"}}},
        }
        for c in sorted(set(codes))
    }


def _query_parameters(op: Operation) -> dict[str, Any]:
    """The request model's fields as query parameters (an operation with ``query``)."""
    assert op.request is not None
    js = op.request.model_json_schema(mode="validation")
    required = set(js.get("required", []))
    return {"parameters": [
        {"name": name, "in": "query", "required": name in required,
         "description": prop.get("description", ""),
         "schema": {k: v for k, v in prop.items() if k not in ("title", "description")}}
        for name, prop in js["properties"].items()
    ]}


def _request_body(op: Operation) -> dict[str, Any] | None:
    if op.request is None:
        return None
    if op.query:
        return _query_parameters(op)
    ref = {"$ref": f"#/components/schemas/{op.request.__name__}"}
    content: dict[str, Any] = {codec.JSON: {"schema": ref}, codec.MSGPACK: {"schema": ref}}
    extra: dict[str, Any] = {"requestBody": {"required": True, "content": content}}
    if op.name == "set_gaussians":
        # a raw .ply / .splat upload: the file as the body, its format in the query
        content["application/octet-stream"] = {"schema": {"type": "string", "format": "binary"}}
        extra["parameters"] = [{
            "name": "format", "in": "query", "required": False,
            "description": "format of an application/octet-stream body (default: sniffed)",
            "schema": {"type": "string", "enum": ["ply", "splat"]},
        }]
    if op.name == "create_session":
        extra["parameters"] = [{
            "name": "instance", "in": "query", "required": False,
            "description": "create it on this instance (default: the instance with the fewest "
                           "sessions, ties by smallest id; see agilegs.service.cluster)",
            "schema": {"type": "string", "pattern": INSTANCE_ID_PATTERN},
        }]
    return extra


def route_openapi(op: Operation) -> dict[str, Any]:
    """The ``add_api_route`` keywords that describe ``op``'s bodies and answers."""
    content: dict[str, Any] = {codec.MSGPACK: {
        "schema": {"$ref": f"#/components/schemas/{op.response.__name__}"}}}
    if op.event_stream:
        content["text/event-stream"] = {"schema": {
            "type": "string", "description": "server-sent events (Accept: text/event-stream): "
            "feed, decision (id <epoch>:<seq>, data a DecisionEvent), missed, closed, error"}}
    return {
        "responses": {200: {"content": content}, **_error_responses(op)},
        "openapi_extra": _request_body(op),
    }


def build_openapi(app: FastAPI, *, bearer: bool) -> dict[str, Any]:
    """FastAPI's schema plus the request models; cached on the app."""
    if app.openapi_schema:
        return app.openapi_schema
    schema = get_openapi(title=app.title, version=app.version, summary=app.summary,
                         description=app.description, routes=app.routes)
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    for op in OPERATIONS.values():
        if op.request is None or op.query:
            continue
        js = op.request.model_json_schema(ref_template="#/components/schemas/{model}",
                                          mode="validation")
        for name, sub in js.pop("$defs", {}).items():
            components.setdefault(name, sub)
        components[op.request.__name__] = js
    if bearer:
        schema["components"]["securitySchemes"] = {"bearer": {"type": "http", "scheme": "bearer"}}
        schema["security"] = [{"bearer": []}]
    app.openapi_schema = schema
    return schema


DESCRIPTION = """
Next-best-view selection for active 3D Gaussian Splatting (AGILE-GS), per map session.

* Bodies are JSON (`application/json`) or msgpack (`application/msgpack`), chosen by
  `Content-Type`; responses follow `Accept`. Bytes travel raw in msgpack and base64 in JSON.
* Poses are camera-to-world with OpenCV axes (x right, y down, z forward): a 4x4 row-major
  `matrix`, or `position` + `orientation_xyzw` (unit quaternion, ROS order x, y, z, w). The
  rotation must be orthonormal (max |RᵀR − I| ≤ 1e-3, det > 0).
* Every error is `{"error": {"status", "code", "message", "field", "errors"}}` with a 4xx
  status naming the offending field; a refused request changes nothing.
* With `AGILEGS_TOKEN` set, every request needs `Authorization: Bearer <token>`.
* The same operations are served over Zenoh under `agilegs/<session>/<op>`.
* With several instances joined over Zenoh, any instance serves every session: an operation
  on a session another instance owns is forwarded to it (its answer is returned as is; 404
  `session_unavailable` when no instance answers for the session); `POST /v1/sessions` places
  a new session on the instance with the fewest sessions (or `?instance=<id>`), and
  `GET /v1/sessions` lists every instance's sessions.
"""
