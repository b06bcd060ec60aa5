"""The HTTP routes, in process (the app behind an httpx transport): the loop through the SDK,
HTTP errors, concurrency, metrics."""

from __future__ import annotations

import json
import threading
import time
import uuid
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import httpx
import msgpack
import numpy as np
import pytest
from conftest import SMALL_INTRINSICS, InProcess, ring_poses

from agilegs.client import AsyncClient, ConflictError, NotFoundError, ValidationError
from agilegs.schemas import ObservationIn

BOUNDS = {"min": [-0.5] * 3, "max": [0.5] * 3}


def new_id() -> str:
    return f"t-{uuid.uuid4().hex[:8]}"


@pytest.mark.parametrize("encoding", ["msgpack", "json"])
def test_full_loop_through_the_sdk(api: InProcess, encoding: str) -> None:
    sid = new_id()
    poses = ring_poses(20)
    with api.client(encoding=encoding) as c:  # type: ignore[arg-type]
        info = c.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=250,
                                defaults={"method": "agile", "shortlist_size": 4})
        assert info.gaussians.count == 250 and info.pool_size == 0
        pool = c.set_pool(sid, poses)
        assert pool.ids() == list(range(20))
        np.testing.assert_allclose(pool.matrices(), poses, atol=1e-12)
        d = c.select(sid)
        assert d.method == "agile" and len(d.shortlist) == 4 and d.anchor is not None
        assert d.chosen.id in [s.id for s in d.shortlist]
        assert d.server_ms is not None and d.server_ms >= d.latency_ms["total"]
        view = c.commit(sid, d.chosen.id)
        assert view.candidate_id == d.chosen.id
        np.testing.assert_allclose(view.pose.to_matrix(), poses[d.chosen.id], atol=1e-12)
        img = np.random.default_rng(0).integers(0, 255, (32, 32, 3), dtype=np.uint8)
        out = c.add_observations(sid, [ObservationIn.from_numpy(view_id=view.id, image=img,
                                                                 image_encoding="png")])
        assert out.views[0].has_image
        d2 = c.select(sid, method="agile_plus", commit=True)
        assert d2.committed is not None and d2.chosen.id not in (view.candidate_id,)
        state = c.get_session(sid)
        assert state.num_views == 2 and state.pool_size == 18
        h = c.get_information(sid).arrays()
        assert h["means"].shape == (250, 3) and (h["means"] > 0).all()
        assert sid in [s.id for s in c.list_sessions().sessions]
        assert c.delete_session(sid).deleted
        with pytest.raises(NotFoundError):
            c.get_session(sid)


def test_async_client_against_the_server(api: InProcess) -> None:
    import asyncio

    sid = new_id()

    async def main() -> None:
        async with AsyncClient(api.url, transport=httpx.ASGITransport(app=api.app)) as c:
            await c.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=100,
                                   pool=ring_poses(8))
            d = await c.select(sid, method="random", seed=3)
            assert 0 <= d.chosen.id < 8
            await c.delete_session(sid)

    asyncio.run(main())


def _raw(api: InProcess, method: str, path: str, **kw: object) -> httpx.Response:
    with api.http(timeout=30) as h:
        return h.request(method, path, **kw)  # type: ignore[arg-type]


def _error(r: httpx.Response) -> dict:
    body = r.json()["error"]
    assert body["status"] == r.status_code
    return body


def test_bad_http_input_gets_4xx_naming_the_field(api: InProcess) -> None:
    sid = new_id()
    with api.client() as c:
        c.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=100)
    base = f"/v1/sessions/{sid}"
    before = _raw(api, "GET", base).json()
    js = {"content-type": "application/json"}
    cases = [
        (_raw(api, "PUT", base + "/pool", content=b"{not json", headers=js), 400, "body"),
        (_raw(api, "PUT", base + "/pool", content=b"", headers=js), 422, "body"),
        (_raw(api, "PUT", base + "/pool", content=b"{}", headers={"content-type": "text/csv"}),
         415, "header.content-type"),
        (_raw(api, "PUT", base + "/pool", content=b'{"poses": [{"matrix": [[NaN,0,0,0],'
              b'[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}', headers=js), 422,
         "body.poses[0].matrix[0][0]"),
        (_raw(api, "PUT", base + "/pool", content=b"x" * (9 * 2**20), headers=js), 413, "body"),
        (_raw(api, "POST", base + "/select", json={}), 409, "pool"),
        (_raw(api, "POST", base + "/select", json={"shortlist_size": -1}), 422,
         "body.shortlist_size"),
        (_raw(api, "POST", base + "/views", json={"candidate_id": 4}), 409, "body.candidate_id"),
        (_raw(api, "GET", base, headers={"accept": "text/html"}), 406, "header.accept"),
        (_raw(api, "GET", "/v1/sessions/no-such"), 404, "session"),
        (_raw(api, "GET", "/v1/sessions/bad%20id"), 422, "path.session"),
        (_raw(api, "POST", "/v1/sessions", content=msgpack.packb({"id": 5}),
              headers={"content-type": "application/msgpack"}), 422, "body.id"),
    ]
    for r, status, field in cases:
        assert r.status_code == status, (r.request.url, r.text)
        assert _error(r)["field"] == field, r.text
    after = _raw(api, "GET", base).json()
    assert after == before  # nothing refused changed anything


def test_error_bodies_follow_accept(api: InProcess) -> None:
    r = _raw(api, "GET", "/v1/sessions/no-such", headers={"accept": "application/msgpack"})
    assert r.status_code == 404 and r.headers["content-type"] == "application/msgpack"
    assert msgpack.unpackb(r.content)["error"]["code"] == "not_found"


def test_unknown_routes_and_methods_use_the_error_body(api: InProcess) -> None:
    assert _error(_raw(api, "GET", "/nowhere"))["code"] == "not_found"
    assert _error(_raw(api, "DELETE", "/healthz"))["code"] == "method_not_allowed"


def test_healthz_answers_during_a_long_selection(api: InProcess,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    # the pure-torch path: a selection that takes long enough for the test to mean much
    monkeypatch.setenv("AGILEGS_KERNELS", "torch")
    sid = new_id()
    intr = {"fx": 56.0, "fy": 56.0, "cx": 32.0, "cy": 32.0, "width": 64, "height": 64}
    with api.client() as c:
        c.create_session(intr, id=sid, bounds=BOUNDS, init_gaussians=1000, pool=ring_poses(16))
        result: dict[str, object] = {}

        def long_select() -> None:
            t = time.perf_counter()
            result["r"] = c.select(sid, method="fisherrf")
            result["s"] = time.perf_counter() - t

        th = threading.Thread(target=long_select)
        th.start()
        time.sleep(0.2)
        latencies = []
        while th.is_alive():
            t = time.perf_counter()
            assert _raw(api, "GET", "/healthz").status_code == 200
            latencies.append(time.perf_counter() - t)
            time.sleep(0.05)
        th.join()
    assert result["s"] > 0.5, "the selection should take a while for this test to mean much"
    assert len(latencies) >= 3
    assert max(latencies) < 0.5, latencies


def test_concurrent_sessions_lose_nothing(api: InProcess) -> None:
    ids = [new_id() for _ in range(8)]
    poses = ring_poses(16)

    def robot(sid: str) -> list:
        out = []
        with api.client() as c:
            c.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=150,
                             pool=poses, defaults={"shortlist_size": 4})
            for _ in range(3):
                out.append(c.select(sid, method="agile", commit=True))
            c.add_observations(sid, {"pose": poses[0]})
        return out

    with ThreadPoolExecutor(8) as ex:
        results = list(ex.map(robot, ids))
    with api.client() as c:
        for sid, decisions in zip(ids, results):
            state = c.get_session(sid)
            assert state.num_views == 4 and state.pool_size == 16 - 3
            views = c.list_views(sid).views
            assert [v.candidate_id for v in views[:3]] == [d.chosen.id for d in decisions]
    # the server's own timings show selections of different sessions overlapping in time
    spans = sorted((d.time - d.core_ms / 1e3, d.time) for ds in results for d in ds)
    assert any(b[0] < a[1] for a, b in zip(spans, spans[1:]))


def test_same_session_commits_serialise(api_factory: Any) -> None:
    api = api_factory(max_session_queue=6)  # six at once queue (the default refuses some)
    sid = new_id()
    with api.client() as c:
        c.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=100,
                         pool=ring_poses(12))

    def commit_one(_: int) -> int:
        with api.client() as c:
            return c.select(sid, method="random", commit=True).chosen.id

    with ThreadPoolExecutor(6) as ex:
        chosen = list(ex.map(commit_one, range(6)))
    assert len(set(chosen)) == 6  # each commit saw the pool left by the previous one
    with api.client() as c:
        assert c.get_session(sid).num_views == 6 and c.get_session(sid).pool_size == 6
        with pytest.raises(ConflictError):
            c.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS)


def test_metrics_and_docs(api: InProcess) -> None:
    sid = new_id()
    with api.client() as c:
        c.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=50,
                         pool=ring_poses(6))
        c.select(sid, method="random")
        with pytest.raises(ValidationError):
            c.select(sid, method="random", shortlist_size=100000)
    text = _raw(api, "GET", "/metrics").text
    assert 'agilegs_selection_seconds_bucket{le="0.001",method="random"}' in text
    assert 'agilegs_requests_total{op="select",status="200",transport="http"}' in text
    assert 'agilegs_errors_total{code="invalid",op="select",transport="http"}' in text
    assert _raw(api, "GET", "/docs").status_code == 200
    spec = _raw(api, "GET", "/openapi.json").json()
    assert "/v1/sessions/{session}/select" in spec["paths"]
    body = spec["paths"]["/v1/sessions/{session}/select"]["post"]["requestBody"]
    assert set(body["content"]) == {"application/json", "application/msgpack"}
    assert "SelectRequest" in spec["components"]["schemas"]
    assert json.dumps(spec)  # the schema is plain JSON


def test_raw_splat_upload(api: InProcess, tmp_path: object) -> None:
    from pathlib import Path

    import torch

    from agilegs.service.nbv import GaussianMap

    path = Path(str(tmp_path)) / "m.splat"
    GaussianMap.from_points(torch.rand(30, 3) - 0.5, torch.rand(30, 3), scale=0.05).save(path)
    sid = new_id()
    with api.client() as c:
        c.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=10)
        r = _raw(api, "PUT", f"/v1/sessions/{sid}/gaussians?format=splat",
                 content=path.read_bytes(), headers={"content-type": "application/octet-stream"})
        assert r.status_code == 200, r.text
        assert r.json()["gaussians"]["count"] == 30
        assert c.set_gaussians(sid, path).gaussians.count == 30  # the SDK takes a path too
        r = _raw(api, "PUT", f"/v1/sessions/{sid}/gaussians?format=ply", content=b"junk",
                 headers={"content-type": "application/octet-stream"})
        assert r.status_code == 422 and _error(r)["field"] == "body.data"


def test_a_write_sent_again_with_its_idempotency_key_is_applied_once(api: InProcess) -> None:
    with api.client() as c:
        sid = c.create_session(SMALL_INTRINSICS, bounds={"min": [-0.5] * 3, "max": [0.5] * 3},
                               init_gaussians=50, pool=ring_poses(6)).id
    with api.http(timeout=30) as h:
        url = f"/v1/sessions/{sid}/views"
        key = {"Idempotency-Key": "http-commit-0001"}
        first = h.post(url, json={"candidate_id": 2}, headers=key)
        again = h.post(url, json={"candidate_id": 2}, headers=key)
        assert first.status_code == again.status_code == 200, again.text
        assert again.json() == first.json()
        assert h.get(f"/v1/sessions/{sid}").json()["num_views"] == 1
        bad = h.post(url, json={"candidate_id": 3}, headers={"Idempotency-Key": "no good"})
        assert bad.status_code == 400, bad.text
        assert bad.json()["error"]["field"] == "header.idempotency-key"
        assert h.get(f"/v1/sessions/{sid}").json()["num_views"] == 1
