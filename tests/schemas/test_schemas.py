"""The wire contract: pose conventions, arrays, codecs, keys, the operation table."""

from __future__ import annotations

import json
import math
from typing import Any

import msgpack
import numpy as np
import pytest
from pydantic import ValidationError

from agilegs.schemas import (
    OPERATIONS,
    CommitRequest,
    GaussiansIn,
    ImageData,
    NDArray,
    ObservationIn,
    PoolIn,
    Pose,
    SelectRequest,
    SessionCreate,
    codec,
    keys,
)
from agilegs.schemas.geometry import (
    PoseArrayList,
    matrix_to_quaternion_xyzw,
    quaternion_xyzw_to_matrix,
)


def _rot(axis: str, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    r = {"z": [[c, -s, 0], [s, c, 0], [0, 0, 1]], "x": [[1, 0, 0], [0, c, -s], [0, s, c]]}[axis]
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = [1.0, 2.0, 3.0]
    return m


def _loc(exc: ValidationError) -> list[tuple[object, ...]]:
    return [e["loc"] for e in exc.errors()]


def test_pose_matrix_round_trip_and_quaternion_ros_order() -> None:
    m = _rot("z", 90)
    p = Pose.from_matrix(m)
    np.testing.assert_allclose(p.to_matrix(), m)
    pos, q = p.to_position_quaternion()
    # 90 degrees about z in ROS order (x, y, z, w)
    np.testing.assert_allclose(q, [0, 0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-12)
    np.testing.assert_allclose(pos, [1, 2, 3])
    p2 = Pose(position=[1, 2, 3], orientation_xyzw=list(q))
    np.testing.assert_allclose(p2.to_matrix(), m, atol=1e-12)


@pytest.mark.parametrize("deg", [0.0, 30.0, 179.0, -120.0])
def test_quaternion_matrix_round_trip(deg: float) -> None:
    r = _rot("x", deg)[:3, :3] @ _rot("z", deg / 2)[:3, :3]
    np.testing.assert_allclose(quaternion_xyzw_to_matrix(matrix_to_quaternion_xyzw(r)), r,
                               atol=1e-12)


@pytest.mark.parametrize(
    "matrix, fragment",
    [
        ((np.eye(4) * 2).tolist(), "last row"),
        (np.diag([1.0, 1.0, 1.1, 1.0]).tolist(), "not orthonormal"),
        (np.diag([1.0, 1.0, -1.0, 1.0]).tolist(), "det"),
        ([[1, 0, 0, 2e6], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "translation"),
    ],
)
def test_pose_rejects_bad_matrices_naming_the_field(matrix: list, fragment: str) -> None:
    with pytest.raises(ValidationError) as exc:
        PoolIn(poses=[Pose(matrix=np.eye(4).tolist()), {"matrix": matrix}])
    assert _loc(exc.value)[0] == ("poses", 1, "matrix")
    assert fragment in str(exc.value)


def test_pose_tolerance_is_documented_value() -> None:
    m = np.eye(4)
    m[0, 0] = 1 + 4e-4  # |R^T R - I| ~ 8e-4 <= 1e-3: accepted
    Pose(matrix=m.tolist())
    m[0, 0] = 1 + 6e-4  # ~1.2e-3: refused
    with pytest.raises(ValidationError):
        Pose(matrix=m.tolist())


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_pose_rejects_non_finite(bad: float) -> None:
    m = np.eye(4).tolist()
    m[1][3] = bad
    with pytest.raises(ValidationError) as exc:
        Pose(matrix=m)
    assert _loc(exc.value)[0][:2] == ("matrix", 1)


def test_pose_forms_are_exclusive_and_quaternion_unit() -> None:
    with pytest.raises(ValidationError, match="not both"):
        Pose(matrix=np.eye(4).tolist(), position=[0, 0, 0], orientation_xyzw=[0, 0, 0, 1])
    with pytest.raises(ValidationError, match="give matrix"):
        Pose(position=[0, 0, 0])
    with pytest.raises(ValidationError) as exc:
        Pose(position=[0, 0, 0], orientation_xyzw=[0, 0, 0.3, 1])  # |q| = 1.044
    assert _loc(exc.value)[0] == ("orientation_xyzw",)
    with pytest.raises(ValidationError) as exc:  # a component over the published bound
        Pose(position=[0, 0, 0], orientation_xyzw=[0, 0, 0, 2])
    assert _loc(exc.value)[0] == ("orientation_xyzw", 3)


def test_ndarray_round_trips_through_json_and_msgpack() -> None:
    a = np.arange(24, dtype=np.float32).reshape(2, 3, 4)
    nd = NDArray.from_numpy(a)
    as_json = json.loads(nd.model_dump_json())
    assert isinstance(as_json["data"], str)  # base64 in JSON
    np.testing.assert_array_equal(NDArray.model_validate(as_json).to_numpy(), a)
    packed = msgpack.packb(nd.model_dump(), use_bin_type=True)
    back = msgpack.unpackb(packed)
    assert isinstance(back["data"], bytes)  # raw bytes in msgpack
    np.testing.assert_array_equal(NDArray.model_validate(back).to_numpy(), a)


def test_ndarray_checks_size_and_base64() -> None:
    with pytest.raises(ValidationError, match="need 8"):
        NDArray(dtype="float32", shape=[2], data=b"\0" * 7)
    with pytest.raises(ValidationError, match="base64"):
        NDArray.model_validate({"dtype": "uint8", "shape": [1], "data": "***"})
    with pytest.raises(ValidationError):
        NDArray.model_validate({"dtype": "complex64", "shape": [1], "data": ""})


def test_image_data_raw_and_png() -> None:
    img = (np.arange(4 * 5 * 3) % 255).astype(np.uint8).reshape(4, 5, 3)
    raw = ImageData.from_numpy(img)
    np.testing.assert_array_equal(raw.to_numpy(), img)
    png = ImageData.from_numpy(img, "png")
    assert png.data[:4] == b"\x89PNG"
    np.testing.assert_array_equal(png.to_numpy(), img)
    with pytest.raises(ValidationError, match=r"\[H, W, 3\]"):
        ImageData(encoding="raw", data=b"\0" * 8, dtype="uint8", shape=[2, 4, 1])
    with pytest.raises(ValidationError, match="no dtype"):
        ImageData(encoding="png", data=b"x", dtype="uint8")


def test_observation_and_commit_rules() -> None:
    with pytest.raises(ValidationError, match="give pose, candidate_id, or view_id"):
        ObservationIn()
    with pytest.raises(ValidationError, match="view_id takes no pose"):
        ObservationIn(view_id=1, pose=Pose.from_matrix(np.eye(4)))
    o = ObservationIn.from_numpy(np.eye(4), depth=np.ones((2, 3)))
    assert o.depth is not None and o.depth.dtype == "float32" and o.depth.shape == [2, 3]
    with pytest.raises(ValidationError, match="exactly one"):
        CommitRequest()
    with pytest.raises(ValidationError, match="unique"):
        PoolIn(poses=[Pose.from_matrix(np.eye(4))] * 2, ids=[3, 3])
    with pytest.raises(ValidationError, match="entries"):
        PoolIn(poses=[Pose.from_matrix(np.eye(4))], ids=[1, 2])


def test_session_create_needs_a_scene_and_gaussians_format() -> None:
    intr = {"fx": 1, "fy": 1, "cx": 0, "cy": 0, "width": 2, "height": 2}
    with pytest.raises(ValidationError, match="bounds, gaussians, or frames"):
        SessionCreate(intrinsics=intr)
    with pytest.raises(ValidationError) as exc:
        SessionCreate(intrinsics=intr, id="bad id!", bounds={"min": [0] * 3, "max": [1] * 3})
    assert _loc(exc.value)[0] == ("id",)
    with pytest.raises(ValidationError, match="below max"):
        SessionCreate(intrinsics=intr, bounds={"min": [0] * 3, "max": [1, 0, 1]})
    with pytest.raises(ValidationError, match="takes data"):
        GaussiansIn(format="ply")


def test_select_request_limits() -> None:
    with pytest.raises(ValidationError) as exc:
        SelectRequest(shortlist_size=0)
    assert _loc(exc.value)[0] == ("shortlist_size",)
    with pytest.raises(ValidationError):
        SelectRequest(method="best")
    with pytest.raises(ValidationError, match="not both"):
        SelectRequest(current_id=1, current_pose=Pose.from_matrix(np.eye(4)))


def test_codec_negotiation_and_round_trip() -> None:
    assert codec.negotiate(None) == codec.JSON
    assert codec.negotiate("application/msgpack") == codec.MSGPACK
    assert codec.negotiate("application/json;q=0.5, application/x-msgpack") == codec.MSGPACK
    assert codec.negotiate("*/*") == codec.JSON
    assert codec.negotiate("text/html") is None
    assert codec.media_type("application/json; charset=utf-8") == codec.JSON
    assert codec.media_type("application/msgpack") == codec.MSGPACK
    assert codec.media_type("text/plain") is None
    req = SelectRequest(method="agile", shortlist_size=5, commit=True)
    for kind in (codec.JSON, codec.MSGPACK):
        assert SelectRequest.model_validate(codec.load(codec.dump(req, kind), kind)) == req
    with pytest.raises(codec.DecodeError):
        codec.load(b"{not json", codec.JSON)
    with pytest.raises(codec.DecodeError):
        codec.load(b"\xc1", codec.MSGPACK)


def test_keys_are_defined_once_and_match_operations() -> None:
    assert keys.session_key("s-1_a", "select") == "agilegs/s-1_a/select"
    assert keys.service_key("create_session") == "agilegs/@service/create_session"
    assert keys.parse_session_key("agilegs/abc/commit") == ("abc", "commit")
    with pytest.raises(ValueError):
        keys.session_key("a/b", "select")
    with pytest.raises(ValueError):
        keys.session_key("a", "explode")
    ops = {name for name, op in OPERATIONS.items() if op.scope == "session"}
    assert ops == set(keys.SESSION_OPS)
    assert {name for name, op in OPERATIONS.items() if op.scope == "service"} == set(
        keys.SERVICE_OPS)
    routes = {(op.http_method, op.http_path) for op in OPERATIONS.values()}
    assert len(routes) == len(OPERATIONS)  # every operation has its own route


def _near_tolerance_rotations(rng: np.random.Generator, n: int) -> list[list[list[float]]]:
    """Rotations perturbed so that max |R^T R - I| lands on both sides of the tolerance."""
    out = []
    for i in range(n):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        q *= np.sign(np.linalg.det(q))
        m = np.eye(4)
        m[:3, :3] = q
        m[:3, 3] = rng.normal(size=3)
        scale = 1 + (i % 7 - 3) * 1.666e-4  # err = |s^2 - 1| around 1e-3
        m[:3, 0] *= scale
        out.append(m.tolist())
    return out


def test_pose_lists_are_validated_as_an_array_with_the_per_pose_rules() -> None:
    """A pool's poses are checked as one array; the outcome, the poses and every error (its
    path and message) are those of validating each pose on its own."""
    from pydantic import TypeAdapter

    per_pose = TypeAdapter(list[Pose])
    rng = np.random.default_rng(0)
    eye = np.eye(4).tolist()
    lists: list[list[Any]] = [
        [{"matrix": m} for m in _near_tolerance_rotations(rng, 40)],
        [{"matrix": [[int(v) for v in row] for row in eye]}] * 3,  # ints
        [{"matrix": eye}, {"matrix": [[True, 0, 0, 0]] + eye[1:]}],  # a bool
        [{"matrix": eye}, {"matrix": [["1", 0, 0, 0]] + eye[1:]}],  # a string
        [{"matrix": eye}, {"matrix": [[float("nan"), 0, 0, 0]] + eye[1:]}],
        [{"matrix": eye}, {"matrix": eye[:3]}],  # 3 rows
        [{"matrix": eye}, {"matrix": [row[:3] for row in eye]}],  # 3 columns
        [{"matrix": eye}, {"matrix": np.diag([1.0, 1.0, -1.0, 1.0]).tolist()}],  # reflection
        [{"matrix": eye}, {"matrix": [[1, 0, 0, 2e6]] + eye[1:]}],  # far away
        [{"matrix": eye}, {"matrix": eye[:3] + [[0, 0, 1e-5, 1]]}],  # last row
        [{"matrix": eye}, {"matrix": eye, "position": [0, 0, 0]}],  # two forms
        [{"matrix": eye}, {"position": [0, 0, 1], "orientation_xyzw": [0, 0, 0, 1]}],
        [{"matrix": eye, "position": None, "orientation_xyzw": None}],
        [{"matrix": eye, "extra": 1}],
        [{"matrix": 10 ** 400}], [], "not a list",
    ]
    for poses in lists:
        try:
            want = per_pose.validate_python(poses)
        except ValidationError as exc:
            with pytest.raises(ValidationError) as got:
                PoolIn.model_validate({"poses": poses})
            assert [(("poses", *e["loc"]), e["msg"]) for e in exc.errors()] == [
                (e["loc"], e["msg"]) for e in got.value.errors()]
            continue
        pool = PoolIn.model_validate({"poses": poses})
        assert pool.poses == want
        assert [p.model_fields_set for p in pool.poses] == [p.model_fields_set for p in want]
    # the common case went through the array check, and holds the array
    pool = PoolIn.model_validate({"poses": [{"matrix": m}
                                            for m in _near_tolerance_rotations(rng, 40)[3::7]]})
    assert isinstance(pool.poses, PoseArrayList) and pool.poses.matrices.shape == (6, 4, 4)
