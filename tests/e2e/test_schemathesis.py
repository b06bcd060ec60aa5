"""Schemathesis against a live server's OpenAPI schema: no 5xx, no schema violation.

Each operation is fuzzed with positive (schema-valid) and negative (schema-violating) data,
once with random session ids and once against an existing session, so that valid bodies
reach the selection core.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgpack
import pytest
import schemathesis
from conftest import SMALL_INTRINSICS, ServerProcess, ring_poses
from hypothesis import HealthCheck, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from agilegs.client import Client

CHECKS = [not_a_server_error, response_schema_conformance, status_code_conformance,
          content_type_conformance]


def _packable(value: Any) -> Any:
    # msgpack carries 64-bit integers; the fuzzer's bigger ones travel as strings
    if isinstance(value, int) and not isinstance(value, bool) and not -2**63 <= value < 2**64:
        return str(value)
    if isinstance(value, list):
        return [_packable(v) for v in value]
    if isinstance(value, dict):
        return {k: _packable(v) for k, v in value.items()}
    return value


@schemathesis.serializer("application/msgpack")
def _msgpack(ctx: object, value: object) -> bytes:
    return msgpack.packb(_packable(value), use_bin_type=True)


@pytest.fixture(scope="module")
def fuzz_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    root: Path = tmp_path_factory.mktemp("fuzz")
    # tight limits keep whatever the fuzzer creates small (and exercise the limits)
    srv = ServerProcess(root / "state", zenoh=False, env={
        "AGILEGS_MAX_GAUSSIANS": "300", "AGILEGS_MAX_IMAGE_PIXELS": "1024",
        "AGILEGS_MAX_POOL_SIZE": "16", "AGILEGS_MAX_SESSIONS": "50",
        "AGILEGS_MAX_BODY_BYTES": str(2**20), "AGILEGS_MAX_VIEWS": "8",
        "AGILEGS_MAX_POLL_WAIT": "0.2",  # decisions polls and streams end quickly
    }).start()
    with Client(srv.url) as c:
        c.create_session(SMALL_INTRINSICS, id="fuzz", init_gaussians=200, pool=ring_poses(12),
                         bounds={"min": [-0.5] * 3, "max": [0.5] * 3})
        c.commit("fuzz", 0)
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def api_schema(fuzz_server: ServerProcess) -> schemathesis.BaseSchema:
    return schemathesis.openapi.from_url(fuzz_server.url + "/openapi.json")


@pytest.mark.parametrize("mode", [schemathesis.GenerationMode.POSITIVE,
                                  schemathesis.GenerationMode.NEGATIVE])
@pytest.mark.parametrize("session", [None, "fuzz"])
def test_api_never_fails_and_matches_its_schema(api_schema: schemathesis.BaseSchema,
                                                fuzz_server: ServerProcess,
                                                mode: schemathesis.GenerationMode,
                                                session: str | None) -> None:
    # one Hypothesis run per operation (schemathesis' pytest plugin does not run on pytest 9)
    statuses: Counter[tuple[str, int]] = Counter()
    for result in api_schema.get_all_operations():
        operation = result.ok()
        kwargs: dict[str, Any] = {"generation_mode": mode}
        if session is not None:
            if "{session}" not in operation.path or operation.method.upper() == "DELETE":
                continue
            kwargs["path_parameters"] = {"session": session}

        label = operation.label

        @settings(max_examples=12, deadline=None, derandomize=True, database=None,
                  suppress_health_check=list(HealthCheck))
        @given(case=operation.as_strategy(**kwargs))
        def run(case: schemathesis.Case) -> None:
            response = case.call_and_validate(checks=CHECKS, timeout=60)
            statuses[(label, response.status_code)] += 1  # noqa: B023 (run before the next loop)

        if session is not None:  # earlier operations may have emptied the pool
            with Client(fuzz_server.url) as c:
                c.set_pool(session, ring_poses(12))
        try:
            run()
        except Unsatisfiable:  # nothing to make negative (no parameters, no body)
            assert mode == schemathesis.GenerationMode.NEGATIVE
    # every operation ran (negative data needs a parameter or a body to break)
    positive = mode == schemathesis.GenerationMode.POSITIVE
    want = (15 if positive else 12) if session is None else (10 if positive else 6)
    assert len({label for label, _ in statuses}) >= want, statuses
    if session is not None and mode == schemathesis.GenerationMode.POSITIVE:
        # valid bodies reached the core: some selections succeeded
        assert statuses[("POST /v1/sessions/{session}/select", 200)] > 0, statuses
