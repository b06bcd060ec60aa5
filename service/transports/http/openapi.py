"""The OpenAPI description of the HTTP API: bodies in JSON and msgpack, the error bodies of
every operation, and the request models (bodies are decoded by the gateway, not FastAPI)."""

from __future__ import annotations

import math
from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from agilegs.schemas import OPERATIONS, ErrorBody, Operation, codec
from agilegs.schemas.codec import GAUSSIAN_FILE_TYPES
from agilegs.schemas.forms import RULES_KEY
from agilegs.schemas.keys import INSTANCE_ID_PATTERN
from agilegs.schemas.requests import REQUEST_ID_HEADER, REQUEST_ID_PATTERN

from ...settings import Settings

__all__ = ["DESCRIPTION", "apply_limits", "build_openapi", "links", "route_openapi"]


_HEADERS: dict[int, dict[str, Any]] = {
    401: {"WWW-Authenticate": {"description": "Bearer", "schema": {"type": "string"}}},
    415: {"Accept": {"description": "the media types the operation reads",
                     "schema": {"type": "string"}}},
}


_FILES = {"ply": "the Inria 3DGS layout: x y z nx ny nz f_dc_* f_rest_* opacity scale_* rot_*, "
               "float32, the raw parameters", "splat": "antimatter15's 32-byte records, "
               "quantised: colour, opacity and rotation to 8 bits, no SH beyond the DC"}


def _error_responses(op: Operation) -> dict[int | str, dict[str, Any]]:
    codes = [400, 401, 406, 422, 500, 503]
    if op.request is not None and not op.query:
        codes += [413, 415]
    if op.scope == "session":
        codes += [404, 409, 429, 502, 504]
    elif op.name == "create_session":
        codes += [404, 409, 429, 502, 504]  # 404: no instance answers as ?instance=
    if op.http_method != "GET":
        codes.append(507)  # the state folder is full
    out: dict[int | str, dict[str, Any]] = {}
    for c in sorted(set(codes)):
        out[c] = {
            "model": ErrorBody,
            "description": "error (see the error codes)",
            "content": {codec.MSGPACK: {"schema": {"$ref": "#/components/schemas/ErrorBody"}}},
        }
        if c in _HEADERS:
            out[c]["headers"] = _HEADERS[c]
    return out


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
        content["application/octet-stream"] = {"schema": {
            "type": "string", "format": "binary", RULES_KEY: ["gaussians-file"],
            "description": "a .ply (Inria 3DGS) or .splat (antimatter15) file"}}
        extra["parameters"] = [{
            "name": "format", "in": "query", "required": False,
            "description": "format of an application/octet-stream body (default: sniffed)",
            "schema": {"type": "string", "enum": ["ply", "splat"]},
        }]
    if op.name == "create_session":
        extra["parameters"] = [{
            "name": "instance", "in": "query", "required": False,
            "description": "create it on this instance (default: the instance with the fewest "
                           "sessions, ties by smallest id; see "
                           "agilegs.service.transports.zenoh.cluster)",
            "schema": {"type": "string", "pattern": INSTANCE_ID_PATTERN},
        }]
    return extra


def route_openapi(op: Operation) -> dict[str, Any]:
    """The ``add_api_route`` keywords that describe ``op``'s bodies and answers."""
    content: dict[str, Any] = {codec.MSGPACK: {
        "schema": {"$ref": f"#/components/schemas/{op.response.__name__}"}}}
    if op.name == "get_gaussians":
        for fmt, media in GAUSSIAN_FILE_TYPES.items():
            content[media] = {"schema": {"type": "string", "format": "binary", "description": (
                f"the map as a .{fmt} file ({_FILES[fmt]}), answered when Accept prefers "
                f"{media} to JSON and msgpack (406 names the types it answers)")}}
    if op.event_stream:
        content["text/event-stream"] = {"schema": {
            "type": "string", "description": "server-sent events (Accept: text/event-stream): "
            "feed, decision (id <epoch>:<seq>, data a DecisionEvent), missed, closed, error"}}
    extra = _request_body(op)
    if op.http_method != "GET":
        extra = extra or {}
        extra["parameters"] = [*extra.get("parameters", []), {
            "name": REQUEST_ID_HEADER, "in": "header", "required": False,
            "description": "this write's request id: sent again (a retry after a lost answer, "
                           "or after the session moved), it is answered from the session's "
                           "record and applies nothing (agilegs.schemas.requests)",
            "schema": {"type": "string", "pattern": REQUEST_ID_PATTERN},
        }]
    return {
        "responses": {200: {"content": content, "links": links(op)}, **_error_responses(op)},
        "openapi_extra": extra,
    }


# ---------------------------------------------------------------------------- links
#: request bodies that a response's ids fill in: (source, target) -> requestBody
#: (a pool may be empty, so its answers lead to no candidate id)
_BODY_LINKS: dict[tuple[str, str], dict[str, Any]] = {
    ("select", "commit"): {"candidate_id": "$response.body#/chosen/id"},
    ("select", "add_observations"): {
        "observations": [{"candidate_id": "$response.body#/chosen/id"}]},
    ("commit", "add_observations"): {"observations": [{"view_id": "$response.body#/id"}]},
}


def links(op: Operation) -> dict[str, Any]:
    """The OpenAPI links of ``op``'s 200 answer: a created session's id (``id`` of
    ``create_session``'s answer) and a session operation's own ``session`` lead to every
    session operation; the candidate ids of a pool, the chosen candidate of a selection and
    the id of a committed view fill the bodies that take them."""
    if op.name == "create_session":
        session = "$response.body#/id"
    elif op.scope == "session" and op.name != "delete_session":
        session = "$request.path.session"
    else:
        return {}
    out: dict[str, Any] = {}
    for target in OPERATIONS.values():
        if target.scope != "session":
            continue
        link: dict[str, Any] = {"operationId": target.name, "parameters": {"session": session}}
        body = _BODY_LINKS.get((op.name, target.name))
        if body is not None:  # the whole body: merged into another, it could clash
            link["requestBody"] = body
            link["x-schemathesis"] = {"merge_body": False}
        out[target.name] = link
    return out


# ---------------------------------------------------------------------------- limits
def _limit(components: dict[str, Any], model: str, field: str, key: str, value: int) -> None:
    """Tighten ``key`` (maximum / maxItems) of ``model.field`` to ``value`` (if lower)."""
    schema = components.get(model)
    if schema is None:
        return
    for branch in [schema, *schema.get("oneOf", [])]:
        prop = branch.get("properties", {}).get(field)
        if prop is None:
            continue
        for target in [prop, *prop.get("anyOf", [])]:
            if target.get("type") in ("integer", "array"):
                target[key] = min(value, target.get(key, value))
        default = prop.get("default")
        if key == "maximum" and isinstance(default, int) and default > value:
            prop["default"] = value  # the server lowers the default to its limit too


def apply_limits(components: dict[str, Any], settings: Settings) -> None:
    """Publish the server's limits as schema bounds: the pool size, the shortlist size, the
    Gaussians created at the start, and image sides (width x height must also stay within
    ``max_image_pixels``, which JSON Schema cannot state: see the ``pixels`` rule)."""
    _limit(components, "PoolIn", "poses", "maxItems", settings.max_pool_size)
    _limit(components, "PoolIn", "ids", "maxItems", settings.max_pool_size)
    for model in ("SelectRequest", "SelectDefaults"):  # (a config patch's is overridden by these)
        _limit(components, model, "shortlist_size", "maximum", settings.max_shortlist)
    _limit(components, "SessionCreate", "init_gaussians", "maximum", settings.max_gaussians)
    for side in ("width", "height"):
        _limit(components, "Intrinsics", side, "maximum", settings.max_image_pixels)
    width = math.isqrt(settings.max_image_pixels)  # a render's width, squared, within the limit
    _limit(components, "AnchorConfigPatch", "resolution", "maximum", width)
    _limit(components, "SelectConfigPatch", "cover_resolution", "maximum", width)


def build_openapi(app: FastAPI, settings: Settings) -> dict[str, Any]:
    """FastAPI's schema plus the request models and the server's limits; cached on the app."""
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
            # the validation schema: it also describes what the answers hold (a settings
            # patch, which serialises through a function, has none of its own)
            components[name] = sub
        components[op.request.__name__] = js
    apply_limits(components, settings)
    if settings.token_value() is not None:
        schema["components"]["securitySchemes"] = {"bearer": {"type": "http", "scheme": "bearer"}}
        schema["security"] = [{"bearer": []}]
    app.openapi_schema = schema
    return schema


DESCRIPTION = """
Next-best-view selection for active 3D Gaussian Splatting (AGILE-GS), per map session.

* Bodies are JSON (`application/json`) or msgpack (`application/msgpack`), chosen by
  `Content-Type`; responses follow `Accept`. Bytes travel raw in msgpack and base64 in JSON.
  `get_gaussians` also answers the map as a file: `Accept: application/x-ply` (Inria 3DGS
  `.ply`) or `application/x-splat` (antimatter15 `.splat`).
* Poses are camera-to-world with OpenCV axes (x right, y down, z forward): a 4x4 row-major
  `matrix`, or `position` + `orientation_xyzw` (unit quaternion, ROS order x, y, z, w). The
  rotation must be orthonormal (max |RᵀR − I| ≤ 1e-3, det > 0).
* Every error is `{"error": {"status", "code", "message", "field", "errors", "supported"}}`
  with a 4xx status naming the offending field; a refused request changes nothing.
* This schema states every rule the server enforces: a schema-valid request is accepted, or
  refused only for the session's state (404, 409, 429). Rules JSON Schema cannot state (a
  rotation orthonormal within 1e-3, min < max, byte lengths that follow from shapes) are in
  the field descriptions and named in the `x-agilegs-rules` extension. Links chain the ids
  that `create_session`, the pool operations, `select` and `commit` return.
* With `AGILEGS_TOKEN` set, every request needs `Authorization: Bearer <token>`.
* The same operations are served over Zenoh under `agilegs/<session>/<op>`.
* With several instances joined over Zenoh, any instance serves every session: an operation
  on a session another instance owns is forwarded to it (its answer is returned as is; 404
  `session_unavailable` when no instance answers for the session); `POST /v1/sessions` places
  a new session on the instance with the fewest sessions (or `?instance=<id>`), and
  `GET /v1/sessions` lists every instance's sessions.
"""
