"""A fleet on a real S3 API: three ``agilegs serve`` processes keeping their sessions in one
object store (moto's server on loopback), driven from outside with the client SDK."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from conftest import SMALL_INTRINSICS, ServerProcess
from s3api import S3Api, s3_api

from agilegs.client import Client, ConflictError

BOUNDS = {"min": [-0.5] * 3, "max": [0.5] * 3}


@pytest.fixture(scope="module")
def api() -> Iterator[S3Api]:
    with s3_api() as running:
        yield running


def start_fleet(api: S3Api, root: Path, prefix: str, n: int = 3, *, zenoh: bool = False,
                env: dict[str, str] | None = None) -> list[ServerProcess]:
    servers = []
    for i in range(n):
        srv = ServerProcess(root / f"local-{i}", zenoh=zenoh,
                            env={**api.env, "AGILEGS_STATE_URL": api.url(prefix),
                                 "AGILEGS_INSTANCE_ID": f"i{i}", **(env or {})})
        servers.append(srv.start())
    return servers


def test_100_concurrent_creations_of_one_id_on_three_instances_make_one(
        api: S3Api, tmp_path: Path) -> None:
    servers = start_fleet(api, tmp_path, "race")
    try:
        outcomes: list[int] = []
        gate = threading.Barrier(100)
        body = {"id": "same", "intrinsics": SMALL_INTRINSICS, "bounds": BOUNDS,
                "init_gaussians": 20}

        def attempt(url: str) -> None:
            with httpx.Client(base_url=url, timeout=60) as http:
                gate.wait()
                outcomes.append(http.post("/v1/sessions", json=body).status_code)

        threads = [threading.Thread(target=attempt, args=(servers[i % 3].url,))
                   for i in range(100)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert sorted(set(outcomes)) == [200, 409] and outcomes.count(200) == 1, outcomes
        # the winner's session is whole in the store: a fresh instance loads it
        late = start_fleet(api, tmp_path / "late", "race", 1)[0]
        try:
            with Client(late.url) as c:
                assert [s.id for s in c.list_sessions().sessions] == ["same"]
                assert c.get_session("same").version == 1
                with pytest.raises(ConflictError):
                    c.create_session(SMALL_INTRINSICS, id="same", bounds=BOUNDS)
        finally:
            late.stop()
    finally:
        for srv in servers:
            srv.stop()
