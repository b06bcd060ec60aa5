"""What the HTTP answers promise beyond their bodies: the headers of 405, 406 and 415, a pose
the wire accepts is never refused by the maths, a pool sent again with a selection changes
nothing, a session may start from RGB frames alone."""

from __future__ import annotations

import uuid

import msgpack
import numpy as np
from conftest import SMALL_INTRINSICS, InProcess, ring_poses

from agilegs.config.geometry import ORTHONORMAL_ATOL
from agilegs.schemas import PoolIn, Pose

BOUNDS = {"min": [-0.5] * 3, "max": [0.5] * 3}


def _sid() -> str:
    return f"c-{uuid.uuid4().hex[:8]}"


def test_405_carries_allow_and_406_415_say_what_is_supported(api: InProcess) -> None:
    with api.http() as h:
        r = h.request("PATCH", "/v1/sessions/abc")
        assert r.status_code == 405 and r.headers["allow"] == "DELETE, GET"
        assert r.json()["error"]["supported"] == ["DELETE", "GET"]
        r = h.get("/v1/sessions/abc/select")
        assert r.status_code == 405 and r.headers["allow"] == "POST"
        r = h.request("OPTIONS", "/v1/sessions/abc/pool")
        assert r.headers["allow"] == "GET, POST, PUT"
        r = h.get("/v1/sessions", headers={"accept": "text/html"})
        assert r.status_code == 406
        assert r.json()["error"]["supported"] == ["application/json", "application/msgpack"]
        r = h.put("/v1/sessions/abc/pool", content=b"{}", headers={"content-type": "text/csv"})
        assert r.status_code == 415
        assert r.headers["accept"] == "application/json, application/msgpack"
        r = h.put("/v1/sessions/abc/gaussians", content=b"{}",
                  headers={"content-type": "text/csv", "accept": "application/msgpack"})
        assert r.status_code == 415 and "application/octet-stream" in r.headers["accept"]
        assert "application/x-ply" in msgpack.unpackb(r.content)["error"]["supported"]


def _at_the_tolerance(n: int) -> np.ndarray:
    """``n`` ring poses, rolled about their optical axis and skewed so that max |R^T R - I|
    is just within the wire's tolerance in float64 and just over it once rounded to float32
    (the maths' dtype)."""
    rng = np.random.default_rng(3)
    out = []
    for p in ring_poses(4 * n):
        a = rng.uniform(0, 2 * np.pi)
        roll = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        p[:3, :3] = p[:3, :3] @ roll
        p[:3, 0] *= np.sqrt(1 + ORTHONORMAL_ATOL * (1 - 1e-7))
        r = p[:3, :3].astype(np.float32)
        if np.abs(r.T @ r - np.eye(3, dtype=np.float32)).max() > ORTHONORMAL_ATOL:
            out.append(p)
    assert len(out) >= n
    return np.stack(out[:n])


def test_a_pose_the_wire_accepts_is_never_refused_by_the_maths(api: InProcess) -> None:
    poses = _at_the_tolerance(12)
    for p in poses:
        Pose.from_matrix(p)  # the wire takes each of them
    sid = _sid()
    with api.client() as c:
        c.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=150, pool=poses)
        c.commit(sid, pose=poses[0])
        for method in ("random", "fisherrf", "cover", "agile", "agile_plus"):
            d = c.select(sid, method=method, current_pose=poses[1], embodied_k=6)
            assert d.chosen.id in range(12), method


def test_a_pool_sent_again_with_a_selection_changes_nothing(api: InProcess) -> None:
    sid = _sid()
    poses = ring_poses(10)
    with api.client() as c:
        c.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=100)
        first = c.select(sid, method="random", pool=poses)  # a new pool: persisted, new ids
        assert c.get_pool(sid).ids() == list(range(10))
        again = c.select(sid, method="random", pool=poses)  # the same pool: nothing changes
        assert again.version == first.version and c.get_pool(sid).ids() == list(range(10))
        assert again.chosen.id == first.chosen.id
        other = c.select(sid, method="random", pool=poses[:9])  # another pool: replaced
        assert other.version == first.version + 1 and c.get_pool(sid).ids() == list(
            range(10, 19))
        same_ids = c.select(sid, method="random",
                            pool=PoolIn.from_numpy(poses[:9], ids=list(range(10, 19))))
        assert same_ids.version == other.version
        moved = c.select(sid, method="random",
                         pool=PoolIn.from_numpy(poses[:9], ids=list(range(50, 59))))
        assert moved.version == other.version + 1 and c.get_pool(sid).ids()[0] == 50


def test_a_session_may_start_from_rgb_frames_alone(api: InProcess) -> None:
    from agilegs.client import ConflictError
    from agilegs.schemas import ObservationIn

    sid = _sid()
    frame = ObservationIn.from_numpy(ring_poses(3)[0], image=np.zeros((32, 32, 3), np.uint8))
    with api.client() as c:
        info = c.create_session(SMALL_INTRINSICS, id=sid, frames=[frame], pool=ring_poses(4))
        assert info.gaussians.count == 0 and info.num_views == 1
        try:
            c.select(sid)
            raise AssertionError("a selection without Gaussians must be refused")
        except ConflictError as exc:
            assert exc.code == "map_empty"
        # spread reads no map: it chooses from the first frame
        out = c.select(sid, method="spread", commit=True)
        assert out.committed is not None and out.chosen.id in out.eligible


def test_a_select_carries_the_target_objective_and_its_targets(api: InProcess) -> None:
    from agilegs.client import ValidationError

    sid = _sid()
    poses = ring_poses(6)
    with api.client() as c:
        c.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=80, pool=poses)
        cfg = {"objective": "target", "target_views": 2}
        out = c.select(sid, method="full_eig", config=cfg, targets=poses[[0, 3]])
        assert out.latency_ms["scoring.targets"] > 0
        try:
            c.select(sid, method="full_eig", targets=poses[[0]])
            raise AssertionError("targets without the target objective must be refused")
        except ValidationError as exc:
            assert exc.field == "body.targets"


def test_a_value_over_a_limit_is_a_422_naming_the_field(api_factory: object) -> None:
    from agilegs.client import LimitExceededError

    srv = api_factory(max_image_pixels=100, max_pool_size=3)  # type: ignore[operator]
    with srv.client() as c:
        try:
            c.create_session(SMALL_INTRINSICS, bounds=BOUNDS)  # 32 x 32 pixels
            raise AssertionError("over max_image_pixels")
        except LimitExceededError as exc:
            assert (exc.status, exc.field) == (422, "body.intrinsics")


def test_every_parameter_the_schema_bounds_is_checked(api_factory: object) -> None:
    srv = api_factory(max_image_pixels=1024)  # type: ignore[operator]
    sid = _sid()
    with srv.client() as c, srv.http() as h:
        c.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=50)
        before = h.get(f"/v1/sessions/{sid}").json()
        # intrinsics over the pixel limit, with no image to check them against
        r = h.post(f"/v1/sessions/{sid}/observations", json={"observations": [{
            "pose": {"matrix": np.eye(4).tolist()},
            "intrinsics": {**SMALL_INTRINSICS, "width": 64, "height": 64}}]})
        assert r.status_code == 422
        assert r.json()["error"]["field"] == "body.observations[0].intrinsics"
        # a format outside its enum, even where the body does not use it
        r = h.put(f"/v1/sessions/{sid}/gaussians?format=zip", json={"format": "splat",
                                                                    "data": ""})
        assert r.status_code == 422 and r.json()["error"]["field"] == "query.format"
        assert h.get(f"/v1/sessions/{sid}").json() == before


def test_the_smallest_settings_the_schema_allows_are_answered(api: InProcess) -> None:
    """The lower bounds of the selection settings (a relative ridge of 1e-12, the softest
    widths) select; below them, 422 naming the field."""
    sid = _sid()
    with api.client() as c, api.http() as h:
        c.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=100,
                         pool=ring_poses(8))
        low = {"scoring": {"ridge": 1e-12, "eps": 1e-12, "gamma": 1e-12},
               "anchor": {"near_fraction": 1e-6, "edge_softness": 1e-6, "step_size": 1e-6}}
        for method in ("agile", "agile_plus"):
            r = h.post(f"/v1/sessions/{sid}/select", json={"method": method, "config": low})
            assert r.status_code == 200, r.text
        r = h.post(f"/v1/sessions/{sid}/select",
                   json={"method": "agile", "config": {"scoring": {"ridge": 1e-13}}})
        assert r.status_code == 422
        assert r.json()["error"]["field"] == "body.config.scoring.ridge"
