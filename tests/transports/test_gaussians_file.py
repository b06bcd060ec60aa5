"""The map out as a file: ``get_gaussians`` answers the Inria 3DGS ``.ply`` or the antimatter15
``.splat`` when Accept asks for it, and the SDK's ``save_gaussians`` writes it."""

from __future__ import annotations

import asyncio
import io
import uuid
from pathlib import Path

import httpx
import numpy as np
import pytest
import torch
from conftest import SMALL_INTRINSICS, InProcess

from agilegs.client import AsyncClient, ValidationError
from agilegs.schemas import codec
from agilegs.service.nbv import GaussianMap

BOUNDS = {"min": [-0.5] * 3, "max": [0.5] * 3}
INRIA = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
         + [f"f_rest_{i}" for i in range(45)]
         + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def _map(n: int = 50) -> GaussianMap:
    g = torch.Generator().manual_seed(0)
    return GaussianMap(means=torch.rand(n, 3, generator=g) - 0.5,
                       log_scales=torch.randn(n, 3, generator=g) - 3,
                       quats=torch.randn(n, 4, generator=g),
                       opacity_logits=torch.randn(n, generator=g),
                       sh=torch.randn(n, 16, 3, generator=g) * 0.3)


def _session(api: InProcess, gmap: GaussianMap) -> str:
    sid = f"f-{uuid.uuid4().hex[:8]}"
    with api.client() as c:
        c.create_session(SMALL_INTRINSICS, id=sid,
                         gaussians={k: v.numpy() for k, v in gmap.items()})
    return sid


def test_accept_x_ply_answers_the_inria_file_equal_to_the_map(api: InProcess,
                                                              tmp_path: Path) -> None:
    from plyfile import PlyData

    gmap = _map()
    sid = _session(api, gmap)
    with api.http() as h:
        r = h.get(f"/v1/sessions/{sid}/gaussians", headers={"accept": "application/x-ply"})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "application/x-ply"
    ply = PlyData.read(io.BytesIO(r.content))
    vertex = ply["vertex"]
    assert [p.name for p in vertex.properties] == INRIA
    assert all(vertex.data.dtype[p.name] == np.dtype("<f4") for p in vertex.properties)
    (tmp_path / "m.ply").write_bytes(r.content)
    back = GaussianMap.load(tmp_path / "m.ply")
    for name, t in gmap.items():  # float32 as they were sent
        assert torch.equal(back.tensors()[name], t.float()), name
    with api.client() as c:  # and the JSON answer holds the same arrays
        arrays = c.get_gaussians(sid).to_numpy()
    for name, t in back.items():
        np.testing.assert_array_equal(t.numpy(), arrays[name])


def test_accept_x_splat_answers_what_gaussian_map_save_writes(api: InProcess,
                                                              tmp_path: Path) -> None:
    gmap = _map()
    sid = _session(api, gmap)
    with api.http() as h:
        r = h.get(f"/v1/sessions/{sid}/gaussians",
                  headers={"accept": "application/x-splat, application/json;q=0.5"})
    assert r.status_code == 200 and r.headers["content-type"] == "application/x-splat"
    gmap.save(tmp_path / "m.splat")
    assert r.content == (tmp_path / "m.splat").read_bytes()


def test_json_and_msgpack_stay_the_default(api: InProcess) -> None:
    sid = _session(api, _map())
    with api.http() as h:
        for accept in (None, "*/*", "application/json", "application/x-ply;q=0.1, */*"):
            headers = {"accept": accept} if accept else {}
            r = h.get(f"/v1/sessions/{sid}/gaussians", headers=headers)
            assert r.status_code == 200 and r.headers["content-type"] == "application/json"


def test_an_unanswerable_accept_is_406_naming_the_types(api: InProcess) -> None:
    sid = _session(api, _map())
    with api.http() as h:
        r = h.get(f"/v1/sessions/{sid}/gaussians",
                  headers={"accept": "application/octet-stream"})
        assert r.status_code == 406
        err = r.json()["error"]
        assert err["field"] == "header.accept"
        assert err["supported"] == ["application/json", "application/msgpack",
                                    "application/x-ply", "application/x-splat"]
        assert "application/x-ply" in err["message"]
        # another operation answers no file
        r = h.get(f"/v1/sessions/{sid}", headers={"accept": "application/x-ply"})
        assert r.status_code == 406
        assert r.json()["error"]["supported"] == ["application/json", "application/msgpack"]


def test_a_format_query_parameter_is_refused_naming_accept(api: InProcess) -> None:
    sid = _session(api, _map())
    with api.http() as h:
        r = h.get(f"/v1/sessions/{sid}/gaussians?format=ply")
    assert r.status_code == 400
    err = r.json()["error"]
    assert err["field"] == "query.format" and "Accept: application/x-ply" in err["message"]


def test_a_missing_session_answers_its_error_in_json(api: InProcess) -> None:
    with api.http() as h:
        r = h.get("/v1/sessions/nope/gaussians", headers={"accept": "application/x-ply"})
    assert r.status_code == 404 and r.json()["error"]["field"] == "session"


def test_client_save_gaussians_writes_the_file(api: InProcess, tmp_path: Path) -> None:
    gmap = _map()
    sid = _session(api, gmap)
    with api.client() as c:
        assert c.save_gaussians(sid, tmp_path / "map.ply") == tmp_path / "map.ply"
        c.save_gaussians(sid, str(tmp_path / "map.splat"))
        with pytest.raises(ValidationError, match=r"\.ply"):
            c.save_gaussians(sid, tmp_path / "map.obj")
    back = GaussianMap.load(tmp_path / "map.ply")
    for name, t in gmap.items():
        assert torch.equal(back.tensors()[name], t), name
    gmap.save(tmp_path / "ref.splat")
    assert (tmp_path / "map.splat").read_bytes() == (tmp_path / "ref.splat").read_bytes()
    assert not list(tmp_path.glob(".*.part"))


def test_async_client_save_gaussians(api: InProcess, tmp_path: Path) -> None:
    gmap = _map()
    sid = _session(api, gmap)

    class Bridge(httpx.AsyncBaseTransport):  # the in-process server behind an async client
        async def handle_async_request(self, request: httpx.Request) -> httpx.Response:
            content = await request.aread()
            r = api.transport.handle_request(httpx.Request(
                request.method, request.url, headers=request.headers, content=content))
            return httpx.Response(r.status_code, headers=r.headers, content=r.content)

    async def main() -> None:
        async with AsyncClient(api.url, transport=Bridge()) as c:
            await c.save_gaussians(sid, tmp_path / "a.ply")

    asyncio.run(main())
    assert torch.equal(GaussianMap.load(tmp_path / "a.ply").means, gmap.means)


def test_preferred_file_reads_accept_by_quality() -> None:
    files = codec.GAUSSIAN_FILE_TYPES
    assert codec.preferred_file("application/x-ply", files) == "ply"
    assert codec.preferred_file("application/x-splat", files) == "splat"
    assert codec.preferred_file("application/json, application/x-ply", files) is None
    assert codec.preferred_file("application/json;q=0.4, application/x-ply", files) == "ply"
    assert codec.preferred_file("*/*", files) is None
    assert codec.preferred_file("application/x-ply;q=0", files) is None
    assert codec.preferred_file(None, files) is None


def test_the_openapi_document_lists_the_files(api: InProcess) -> None:
    with api.http() as h:
        spec = h.get("/openapi.json").json()
    content = spec["paths"]["/v1/sessions/{session}/gaussians"]["get"]["responses"]["200"][
        "content"]
    assert {"application/x-ply", "application/x-splat"} <= set(content)
    assert content["application/x-ply"]["schema"]["format"] == "binary"


def test_a_map_without_gaussians_has_no_file_409(api: InProcess) -> None:
    from agilegs.schemas import ObservationIn

    sid = f"f-{uuid.uuid4().hex[:8]}"
    image = np.zeros((32, 32, 3), dtype=np.uint8)
    with api.client() as c:  # RGB frames only: no Gaussians yet
        c.create_session(SMALL_INTRINSICS, id=sid,
                         frames=[ObservationIn.from_numpy(np.eye(4), image=image)])
        assert c.get_gaussians(sid).count == 0
    with api.http() as h:
        r = h.get(f"/v1/sessions/{sid}/gaussians", headers={"accept": "application/x-ply"})
    assert r.status_code == 409 and r.json()["error"]["field"] == "gaussians"
    assert "no Gaussians yet" in r.json()["error"]["message"]
