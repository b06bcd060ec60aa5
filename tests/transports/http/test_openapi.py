"""The served OpenAPI schema says what the server accepts: a body is schema-valid exactly when
the request model accepts it, but for the rules JSON Schema cannot state (named in the
``x-agilegs-rules`` extension), which the model refuses naming the field; the server's limits
are in the schema; links chain created ids to the operations that use them."""

from __future__ import annotations

import base64
import copy
import json
from typing import Any

import jsonschema_rs
import numpy as np
import pytest
from conftest import InProcess, ring_poses
from pydantic import BaseModel, ValidationError

from agilegs import schemas as m
from agilegs.schemas import OPERATIONS
from agilegs.schemas.forms import RULES_KEY

EYE = np.eye(4).tolist()
SKEW = [[1.0, 0.02, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0, 0, 0, 1]]
INTR = {"fx": 10.0, "fy": 10.0, "cx": 4.0, "cy": 4.0, "width": 8, "height": 8}
BOUNDS = {"min": [-1.0, -1.0, -1.0], "max": [1.0, 1.0, 1.0]}
QUAT = {"position": [0.0, 0.0, 0.0], "orientation_xyzw": [0.0, 0.0, 0.0, 1.0]}
DEPTH = {"dtype": "float32", "shape": [8, 8], "data": base64.b64encode(bytes(256)).decode()}

# (model, body, schema-valid, model-accepts, the rule the model adds where they differ)
CASES: list[tuple[type[BaseModel], dict[str, Any], bool, bool, str | None]] = [
    (m.CommitRequest, {}, False, False, None),
    (m.CommitRequest, {"candidate_id": 1}, True, True, None),
    (m.CommitRequest, {"candidate_id": 2.0}, True, True, None),
    (m.CommitRequest, {"candidate_id": "1"}, False, False, None),
    (m.CommitRequest, {"candidate_id": True}, False, False, None),
    (m.CommitRequest, {"candidate_id": 1, "pose": {"matrix": EYE}}, False, False, None),
    (m.CommitRequest, {"candidate_id": None, "pose": {"matrix": EYE}}, True, True, None),
    (m.CommitRequest, {"pose": {}}, False, False, None),
    (m.CommitRequest, {"pose": {"matrix": EYE, "position": [0, 0, 0]}}, False, False, None),
    (m.CommitRequest, {"pose": QUAT}, True, True, None),
    (m.CommitRequest, {"pose": {"matrix": None, **QUAT}}, True, True, None),
    (m.CommitRequest, {"pose": {"position": [0, 0, 0]}}, False, False, None),
    (m.CommitRequest, {"pose": {**QUAT, "orientation_xyzw": [0, 0, 0, 2]}}, False, False, None),
    (m.CommitRequest, {"pose": {**QUAT, "orientation_xyzw": [0, 0, 0.3, 1]}}, True, False,
     "unit-quaternion"),
    (m.CommitRequest, {"pose": {"matrix": SKEW}}, True, False, "rotation"),
    (m.CommitRequest, {"pose": {"matrix": [[1.5, 0, 0, 0]] + EYE[1:]}}, False, False, None),
    (m.CommitRequest, {"pose": {"matrix": EYE[:3] + [[0, 0, 0.1, 1]]}}, False, False, None),
    (m.CommitRequest, {"pose": {"matrix": [[1, 0, 0, 2e6]] + EYE[1:]}}, False, False, None),
    (m.CommitRequest, {"pose": {"matrix": [["1", 0, 0, 0]] + EYE[1:]}}, False, False, None),
    (m.CommitRequest, {"pose": {"matrix": [[True, 0, 0, 0]] + EYE[1:]}}, False, False, None),
    (m.CommitRequest, {"pose": {"matrix": [[1, 0, 0, 0]] + EYE[1:]}}, True, True, None),
    (m.CommitRequest, {"candidate_id": 1, "keep_in_pool": "yes"}, False, False, None),
    (m.ObservationsIn, {"observations": [{}]}, False, False, None),
    (m.ObservationsIn, {"observations": [{"view_id": 1}]}, True, True, None),
    (m.ObservationsIn, {"observations": [{"view_id": 1, "candidate_id": 2}]}, False, False, None),
    (m.ObservationsIn, {"observations": [{"candidate_id": 2, "pose": QUAT}]}, True, True, None),
    (m.ObservationsIn, {"observations": [{"pose": QUAT, "depth": DEPTH}]}, True, True, None),
    (m.ObservationsIn, {"observations": [{"pose": QUAT, "depth": {**DEPTH, "dtype": "float64"}}]},
     False, False, None),
    (m.ObservationsIn, {"observations": [{"pose": QUAT, "depth": {**DEPTH, "shape": [8, 8, 1]}}]},
     False, False, None),
    (m.ObservationsIn, {"observations": [{"pose": QUAT, "depth": {**DEPTH, "shape": [8, 9]}}]},
     True, False, "array-size"),
    (m.ObservationsIn, {"observations": [{"view_id": 0, "image": {"encoding": "png",
                                                                  "data": "AAAA"}}]},
     True, True, None),
    (m.ObservationsIn, {"observations": [{"view_id": 0, "image": {
        "encoding": "png", "data": "AAAA", "dtype": "uint8"}}]}, False, False, None),
    (m.ObservationsIn, {"observations": [{"view_id": 0, "image": {
        "encoding": "raw", "data": "AAAA"}}]}, False, False, None),
    (m.ObservationsIn, {"observations": [{"view_id": 0, "image": {
        "encoding": "raw", "data": "AAAA", "dtype": "uint8", "shape": [1, 1, 3]}}]},
     True, True, None),
    (m.ObservationsIn, {"observations": [{"view_id": 0, "image": {
        "encoding": "raw", "data": "AAAA", "dtype": "uint8", "shape": [1, 1, 4]}}]},
     False, False, None),
    (m.ObservationsIn, {"observations": [{"view_id": 0, "image": {
        "encoding": "png", "data": "not base64!"}}]}, False, False, None),
    (m.PoolIn, {"poses": [{"matrix": EYE}], "ids": [3]}, True, True, None),
    (m.PoolIn, {"poses": [{"matrix": EYE}] * 2, "ids": [3, 3]}, False, False, None),
    (m.PoolIn, {"poses": [{"matrix": EYE}] * 2, "ids": [3]}, True, False, "same-length"),
    (m.PoolIn, {"poses": [{"matrix": EYE}, QUAT]}, True, True, None),
    (m.SelectRequest, {}, True, True, None),
    (m.SelectRequest, {"current_id": 1, "current_pose": QUAT}, False, False, None),
    (m.SelectRequest, {"current_id": 1, "current_pose": None}, True, True, None),
    (m.SelectRequest, {"fields": ["means", "means"]}, False, False, None),
    (m.SelectRequest, {"config": {"fields": ["sh", "sh"]}}, False, False, None),
    (m.SelectRequest, {"config": {"anchor": {"iterations": 101}}}, False, False, None),
    (m.SelectRequest, {"config": {"shortlist_size": 1024}}, True, True, None),
    (m.SelectRequest, {"config": {"shortlist_size": 1025}}, False, False, None),
    (m.SelectRequest, {"config": {"anchor": {"iterations": 100}}}, True, True, None),
    (m.SelectRequest, {"config": {"anchor": {"occlusion_tests": [[2, 0.1]]}}}, False, False,
     None),
    (m.SelectRequest, {"config": {"anchor": {"occlusion_tests": [[5, 0.1]]}}}, True, True, None),
    (m.SelectRequest, {"config": {"scoring": {"grid": 4096}}}, False, False, None),
    (m.SelectRequest, {"config": {"nonsense": 1}}, False, False, None),
    (m.SelectRequest, {"method": "nonsense"}, False, False, None),
    (m.SelectRequest, {"commit": 1}, False, False, None),
    (m.SelectRequest, {"targets": [{"matrix": EYE}], "config": {"objective": "target"}}, True,
     True, None),
    (m.SelectRequest, {"targets": []}, False, False, None),
    (m.SelectRequest, {"config": {"objective": "best"}}, False, False, None),
    (m.SessionCreate, {"intrinsics": INTR}, False, False, None),
    (m.SessionCreate, {"intrinsics": INTR, "bounds": None}, False, False, None),
    (m.SessionCreate, {"intrinsics": INTR, "frames": []}, False, False, None),
    (m.SessionCreate, {"intrinsics": INTR, "bounds": BOUNDS}, True, True, None),
    (m.SessionCreate, {"intrinsics": INTR, "frames": [{"pose": QUAT}]}, True, True, None),
    (m.SessionCreate, {"intrinsics": INTR, "frames": [{"pose": QUAT, "view_id": 1}]}, False,
     False, None),
    (m.SessionCreate, {"intrinsics": INTR, "bounds": {"min": [0, 0, 0], "max": [1, 0, 1]}},
     True, False, "ordered-bounds"),
    (m.SessionCreate, {"intrinsics": {**INTR, "width": 0}, "bounds": BOUNDS}, False, False,
     None),
    (m.SessionCreate, {"intrinsics": INTR, "bounds": BOUNDS, "gaussians": {"format": "arrays",
                                                                           "data": "AAAA"}},
     False, False, None),
    (m.SessionCreate, {"intrinsics": INTR, "bounds": BOUNDS, "defaults": {"seed": -1}}, False,
     False, None),
]


@pytest.fixture(scope="module")
def openapi(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    from inprocess import serve_in_process

    with serve_in_process(tmp_path_factory.mktemp("openapi") / "state", max_shortlist=8,
                          max_pool_size=16, max_image_pixels=1024) as srv, srv.http() as h:
        return dict(h.get("/openapi.json").json())


def _validator(openapi: dict[str, Any], name: str) -> Any:
    doc = {"$ref": f"#/components/schemas/{name}", "components": openapi["components"]}
    return jsonschema_rs.Draft202012Validator(doc)


def _rules(openapi: dict[str, Any]) -> set[str]:
    return {r for s in openapi["components"]["schemas"].values() for r in s.get(RULES_KEY, [])}


@pytest.mark.parametrize("model, body, schema_ok, model_ok, rule", CASES,
                         ids=[f"{c[0].__name__}-{i}" for i, c in enumerate(CASES)])
def test_the_schema_accepts_what_the_model_accepts(openapi: dict[str, Any],
                                                   model: type[BaseModel], body: dict[str, Any],
                                                   schema_ok: bool, model_ok: bool,
                                                   rule: str | None) -> None:
    assert _validator(openapi, model.__name__).is_valid(body) == schema_ok
    try:
        model.model_validate(copy.deepcopy(body))
        accepted = True
    except ValidationError as exc:
        accepted = False
        assert all(e["loc"] or e["type"] == "value_error" for e in exc.errors())
    assert accepted == model_ok
    if schema_ok != model_ok:  # only a rule JSON Schema cannot state may tell them apart
        assert schema_ok and rule in _rules(openapi), rule


def test_the_servers_limits_are_in_the_schema(openapi: dict[str, Any]) -> None:
    c = openapi["components"]["schemas"]
    assert c["PoolIn"]["properties"]["poses"]["maxItems"] == 16
    size = c["SelectDefaults"]["properties"]["shortlist_size"]
    assert size["maximum"] == 8 and size["default"] == 8
    assert c["SelectRequest"]["properties"]["shortlist_size"]["anyOf"][0]["maximum"] == 8
    assert c["AnchorConfigPatch"]["properties"]["resolution"]["anyOf"][0]["maximum"] == 32
    assert c["Intrinsics"]["properties"]["width"]["maximum"] == 1024
    # a settings patch is typed in requests and answers alike
    assert c["SelectConfigPatch"]["properties"]["anchor"] == {
        "$ref": "#/components/schemas/AnchorConfigPatch", **{
            k: v for k, v in c["SelectConfigPatch"]["properties"]["anchor"].items()
            if k != "$ref"}}
    assert json.dumps(openapi).count('"ge"') == 0  # every bound is a JSON Schema keyword


def test_links_chain_created_ids_to_the_operations_that_use_them(openapi: dict[str, Any]
                                                                 ) -> None:
    paths = openapi["paths"]

    def links(op_name: str) -> dict[str, Any]:
        op = OPERATIONS[op_name]
        return dict(paths[op.http_path][op.http_method.lower()]["responses"]["200"]["links"])

    session_ops = {op.name for op in OPERATIONS.values() if op.scope == "session"}
    created = links("create_session")
    assert set(created) == session_ops
    assert all(link["parameters"] == {"session": "$response.body#/id"}
               for link in created.values())
    assert links("select")["commit"]["requestBody"] == {
        "candidate_id": "$response.body#/chosen/id"}
    assert "requestBody" not in links("set_pool")["commit"]  # a pool may be empty
    assert links("commit")["add_observations"]["requestBody"] == {
        "observations": [{"view_id": "$response.body#/id"}]}
    assert links("select")["get_information"]["parameters"] == {
        "session": "$request.path.session"}
    assert links("delete_session") == {}


def test_a_limit_the_schema_states_is_the_one_the_server_applies(api_factory: Any) -> None:
    srv: InProcess = api_factory(max_shortlist=4, max_image_pixels=4096)
    with srv.http() as h:
        schema = h.get("/openapi.json").json()["components"]["schemas"]
        top = schema["SelectRequest"]["properties"]["shortlist_size"]["anyOf"][0]["maximum"]
        width = schema["AnchorConfigPatch"]["properties"]["resolution"]["anyOf"][0]["maximum"]
        assert (top, width) == (4, 64)
        r = h.post("/v1/sessions", json={"id": "lim", "intrinsics": INTR, "bounds": BOUNDS,
                                         "init_gaussians": 50,
                                         "pool": {"poses": [{"matrix": p.tolist()}
                                                            for p in ring_poses(6)]}})
        assert r.status_code == 200 and r.json()["defaults"]["shortlist_size"] == 4
        assert h.post("/v1/sessions/lim/select", json={"shortlist_size": top}).status_code == 200
        over = h.post("/v1/sessions/lim/select", json={"shortlist_size": top + 1})
        assert over.status_code == 422 and over.json()["error"]["field"] == "body.shortlist_size"
        wide = h.post("/v1/sessions/lim/select",
                      json={"method": "agile", "config": {"anchor": {"resolution": width + 1}}})
        assert wide.status_code == 422 and wide.json()["error"]["code"] == "limit_exceeded"
        assert wide.json()["error"]["field"] == "body.config.anchor.resolution"
