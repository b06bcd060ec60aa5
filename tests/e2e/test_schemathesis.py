"""Schemathesis, as an outside tool runs it, against a live server's OpenAPI schema.

``schemathesis run --checks all`` runs the fuzzing phase (positive and negative data for every
operation) and the stateful phase (which follows the schema's links from a created session to
the operations that use its id), over JSON and msgpack (the hooks in
``schemathesis_hooks.py`` pack msgpack bodies, unpack msgpack answers, and make positive data
meet the rules JSON Schema cannot state). A run fails on any failure of any check, on any
5xx, and unless select, commit, observations, the pool and Ĥ answered 200 on live sessions.

Two sizes, both in the heavy lane (``pytest -m heavy``, which ``.ci/run`` runs after the
suite): a short run (:data:`CI`, under a minute on two cores) and the long one (:data:`FULL`:
every phase, the coverage phase's boundary cases included). Each is followed by a
stateful-only run over the robot's loop (:data:`WORKFLOW`) on the same server. ``docs/benchmarks.md`` has the command of the long run
(10,000+ cases).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
from conftest import CI, FULL, Fuzz, ServerProcess, stateful_toml

HERE = Path(__file__).resolve().parent

#: tight limits keep whatever the fuzzer creates small (and exercise the limits)
FUZZ_ENV = {
    "AGILEGS_MAX_GAUSSIANS": "300", "AGILEGS_MAX_IMAGE_PIXELS": "1024",
    "AGILEGS_MAX_POOL_SIZE": "16", "AGILEGS_MAX_SESSIONS": "100000", "AGILEGS_MAX_VIEWS": "64",
    "AGILEGS_MAX_SHORTLIST": "8", "AGILEGS_MAX_BODY_BYTES": str(2**20),
    "AGILEGS_MAX_POLL_WAIT": "0.2",  # decisions polls and streams end quickly
}


#: operations that must have answered 200 (on a live session, as only those do)
REACHED = {
    ("POST", "/v1/sessions/{session}/select"),
    ("POST", "/v1/sessions/{session}/views"),
    ("POST", "/v1/sessions/{session}/observations"),
    ("PUT", "/v1/sessions/{session}/pool"),
    ("GET", "/v1/sessions/{session}/information"),
}


def _route(url: str) -> str:
    path = "/" + url.split("/", 3)[3].split("?", 1)[0]
    parts = path.split("/")
    if len(parts) > 3 and parts[1:3] == ["v1", "sessions"]:
        parts[3] = "{session}"
    return "/".join(parts)


#: the robot's loop, whose operations a second, stateful-only run follows alone: among all
#: of them (every session operation links to every other) a select is followed by an
#: observation too seldom for one run to reach it on every seed
WORKFLOW = ("create_session", "set_pool", "select", "commit", "add_observations",
            "get_information")


def _run(srv: ServerProcess, tmp_path: Path, name: str, size: Fuzz, args: list[str],
         timeout: float) -> tuple[dict[str, Any], Counter[tuple[str, str, int]]]:
    """One schemathesis run of ``args`` against ``srv``: its JSON summary (checked: no
    failure, no error, every phase it ran succeeded, no 5xx) and its (method, route, status)
    counts."""
    exe = shutil.which("schemathesis") or str(Path(sys.executable).parent / "schemathesis")
    report = tmp_path / name
    config = tmp_path / f"{name}.toml"
    config.write_text(stateful_toml(size))
    env = {**os.environ, "PYTHONPATH": str(HERE), "SCHEMATHESIS_HOOKS": "schemathesis_hooks"}
    cmd = [exe, "--config-file", str(config), "run", f"{srv.url}/openapi.json",
           "--checks", "all", "--seed", "7", "--request-timeout", "60",
           "--max-response-time", "60", "--workers", "1",
           "--report", "json,har", "--report-dir", str(report), *args]
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=timeout)
    (report / "output.txt").write_text(proc.stdout + proc.stderr)  # the whole, for a failure
    out = proc.stdout[-6000:] + proc.stderr[-2000:]
    summary = json.loads(next(report.glob("json-*.json")).read_text())
    assert summary["failures"] == [] and summary["errors"] == [], out
    assert proc.returncode == 0, out
    phases = summary["phases"]
    ran = [p for p in ("coverage", "fuzzing", "stateful") if phases[p]["status"] != "skip"]
    assert ran and all(phases[p]["status"] == "success" for p in ran), phases
    entries = json.loads(next(report.glob("har-*.json")).read_text())["log"]["entries"]
    statuses = Counter((e["request"]["method"], _route(e["request"]["url"]),
                        e["response"]["status"]) for e in entries)
    assert not [k for k in statuses if k[2] >= 500], statuses
    return summary, statuses


def fuzz(tmp_path: Path, size: Fuzz) -> None:
    """Run schemathesis of ``size`` against a fresh server, then its stateful phase over the
    robot's loop alone, and check both reports."""
    srv = ServerProcess(tmp_path / "state", zenoh=False, env=FUZZ_ENV).start()
    try:
        summary, statuses = _run(srv, tmp_path, "report", size,
                                 ["--phases", size.phases, "--max-examples",
                                  str(size.max_examples)], size.timeout)
        only = [a for op in WORKFLOW for a in ("--include-operation-id", op)]
        _, loop = _run(srv, tmp_path, "workflow", size, ["--phases", "stateful", *only],
                       size.timeout)
    finally:
        srv.stop()
    reached = {(m, r) for m, r, status in statuses + loop if status == 200}
    assert REACHED <= reached, sorted(REACHED - reached)
    assert summary["test_cases"]["generated"] >= size.min_cases, summary["test_cases"]


@pytest.mark.timeout(600)
@pytest.mark.heavy
def test_schemathesis_finds_nothing(tmp_path: Path) -> None:
    fuzz(tmp_path, CI)


@pytest.mark.heavy
@pytest.mark.timeout(1800)
def test_schemathesis_finds_nothing_in_any_phase(tmp_path: Path) -> None:
    fuzz(tmp_path, FULL)


def test_the_hooks_repair_exactly_what_json_schema_cannot_state() -> None:
    """Data that the schema allows but the server's unstated rules refuse is repaired into
    data the request models accept (the fuzz test relies on it for positive cases)."""
    sys.path.insert(0, str(HERE))
    try:
        import schemathesis_hooks as hooks
    finally:
        sys.path.remove(str(HERE))
    from pydantic import ValidationError

    from agilegs import schemas as m

    body = {
        "intrinsics": {"fx": 5.0, "fy": 5.0, "cx": 1.0, "cy": 1.0, "width": 900, "height": 700},
        "bounds": {"min": [0.0, 2.0, 1.0], "max": [0.0, 1.0, 3.0]},
        "gaussians": {"format": "splat", "data": "AAAA"},
        "frames": [{"pose": {"position": [0, 0, 0], "orientation_xyzw": [0.0, 0.0, 0.0, 0.5]},
                    "depth": {"dtype": "uint16", "shape": [3, 4], "data": ""},
                    "image": {"encoding": "png", "data": "AAAA"}}],
        "pool": {"poses": [{"matrix": [[1.0, 0.3, 0, 0], [0, 1.0, 0, 0], [0, 0, -1.0, 0],
                                       [0.0, 0.0, 0.0, 1.0]]}] * 2, "ids": [4]},
    }
    with pytest.raises(ValidationError):
        m.SessionCreate.model_validate(body)
    hooks.repair(body)
    m.SessionCreate.model_validate(body)  # every rule met
    assert body["intrinsics"]["width"] <= hooks.SIDE and body["pool"]["ids"][0] == 4
    # a select's targets come with the target objective
    select = {"targets": [{"matrix": [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0],
                                      [0, 0, 0, 1.0]]}], "config": None}
    hooks.repair(select)
    assert m.SelectRequest.model_validate(select).config.objective == "target"


def test_a_body_given_by_a_link_gets_a_media_type(tmp_path: Path) -> None:
    """schemathesis (4.x) builds the case of a link that gives the whole body
    (``merge_body: false``) without a media type and asks the operation for its only one;
    the document's targets take two (JSON and msgpack), so without the hooks it raises and
    the stateful phase ends there. With the hooks the case goes as JSON."""
    import schemathesis
    from schemathesis.core.errors import IncorrectUsage

    from agilegs.service.server import Server
    from agilegs.service.settings import Settings
    from agilegs.service.transports.http.app import create_app

    app = create_app(Server(Settings(state_dir=tmp_path / "state", zenoh=False)), start=False)
    doc = app.openapi()
    schema = schemathesis.openapi.from_dict(doc)
    commit = schema["/v1/sessions/{session}/views"]["POST"]
    whole_body = [link for path in doc["paths"].values() for method in path.values()
                  for link in method["responses"]["200"].get("links", {}).values()
                  if link.get("x-schemathesis") == {"merge_body": False}]
    assert {link["operationId"] for link in whole_body} == {"commit", "add_observations"}
    assert commit.get_request_payload_content_types() == ["application/json",
                                                           "application/msgpack"]
    sys.path.insert(0, str(HERE))
    try:
        import schemathesis_hooks  # noqa: F401  (patches on import)
    finally:
        sys.path.remove(str(HERE))
    case = schema.make_case(operation=commit, body={"candidate_id": 1})
    assert case.media_type == "application/json"
    with pytest.raises(IncorrectUsage):  # an operation with one media type still says so
        from schemathesis.schemas import APIOperation

        fake = type("Op", (), {"get_request_payload_content_types":
                               lambda self: ["text/plain", "application/xml"]})()
        APIOperation._get_default_media_type(fake)  # type: ignore[arg-type]
