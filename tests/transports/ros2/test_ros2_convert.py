"""ROS 2 messages -> operation bodies (validated by the service's own models) and decisions ->
messages, without Zenoh; frames paired from their topics."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import SMALL_INTRINSICS, ring_poses

from agilegs.client.ros2 import FieldError
from agilegs.client.ros2 import messages as m
from agilegs.client.ros2.frames import (
    camera_info_msg,
    depth_image_msg,
    depth_to_array,
    image_to_rgb,
    matrix_to_pose_msg,
    pose_msg_to_matrix,
    rgb_image_msg,
)
from agilegs.schemas import (
    Candidate,
    ObservationsIn,
    PoolIn,
    Pose,
    ScoredCandidate,
    SelectRequest,
    SelectResponse,
    SessionCreate,
)
from agilegs.service.transports.ros2.assembler import DEPTH_SYNC_NS, FrameAssembler
from agilegs.service.transports.ros2.convert import (
    Binding,
    create_body,
    decision_msgs,
    frame_body,
    pool_body,
    pose_part,
    select_body,
    select_response_msg,
)


def _header(frame_id: str = "map", t: int = 7) -> object:
    return m.msg("std_msgs/msg/Header", stamp=m.stamp_msg(t, ns=True), frame_id=frame_id)


def _pose_array(poses: np.ndarray, axes: str = "optical", frame_id: str = "map") -> object:
    return m.msg(m.POSE_ARRAY, header=_header(frame_id),
                 poses=[matrix_to_pose_msg(p, axes) for p in poses])  # type: ignore[arg-type]


@pytest.mark.parametrize(("camera_frame", "axes"), [("camera_optical_frame", "optical"),
                                                    ("camera_link", "body")])
def test_a_pose_array_is_a_pool_at_the_same_poses(camera_frame: str, axes: str) -> None:
    poses = ring_poses(5)
    body = pool_body(_pose_array(poses, axes), Binding("s", camera_frame=camera_frame))
    pool = PoolIn.model_validate(json.loads(json.dumps(body)))
    np.testing.assert_allclose(np.stack([p.to_matrix() for p in pool.poses]), poses, atol=1e-12)


def test_a_pose_in_another_frame_is_refused() -> None:
    with pytest.raises(FieldError) as err:
        pool_body(_pose_array(ring_poses(2), frame_id="odom"), Binding("s"))
    assert err.value.field == "candidates.header.frame_id"
    pool_body(_pose_array(ring_poses(2), frame_id="/map"), Binding("s"))  # the same frame
    pool_body(_pose_array(ring_poses(2), frame_id=""), Binding("s"))  # unstated: the world


def test_a_non_unit_quaternion_reaches_the_model_as_sent() -> None:
    msg = _pose_array(ring_poses(3), "body")
    msg.poses[1].orientation.w *= 1.5  # type: ignore[attr-defined]
    body = pool_body(msg, Binding("s", camera_frame="camera_link"))
    with pytest.raises(ValueError, match=r"poses.1.orientation_xyzw"):
        PoolIn.model_validate(body)


def test_a_frame_is_an_observation_with_its_camera() -> None:
    h, w = SMALL_INTRINSICS["height"], SMALL_INTRINSICS["width"]
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    mm = rng.integers(0, 4000, (h, w), dtype=np.uint16)
    c2w = ring_poses(4)[2]
    info = camera_info_msg(SMALL_INTRINSICS)
    from agilegs.client.ros2.frames import intrinsics_of

    pose = pose_part(m.msg(m.POSE_STAMPED, header=_header(), pose=matrix_to_pose_msg(c2w)),
                     Binding("s"))
    body = frame_body(image_to_rgb(rgb_image_msg(rgb, encoding="bgr8")), pose,
                      depth_to_array(depth_image_msg(mm)), intrinsics_of(info))
    obs = ObservationsIn.model_validate(body).observations[0]
    np.testing.assert_array_equal(obs.image.to_numpy(), rgb)  # type: ignore[union-attr]
    np.testing.assert_array_equal(obs.depth.to_numpy(), mm)  # type: ignore[union-attr]
    assert obs.depth_scale == 0.001
    assert obs.intrinsics.model_dump() == SMALL_INTRINSICS  # type: ignore[union-attr]
    np.testing.assert_allclose(obs.pose.to_matrix(), c2w, atol=1e-12)  # type: ignore[union-attr]
    with pytest.raises(FieldError) as err:
        frame_body(rgb[:, :-1], pose, None, intrinsics_of(info))
    assert err.value.field == "image.width"
    with pytest.raises(FieldError) as err:
        frame_body(rgb, pose, (mm[:-1], 0.001), None)
    assert err.value.field == "depth.width"
    with pytest.raises(FieldError) as err:
        pose_part(m.msg(m.POSE_STAMPED, header=_header("odom")), Binding("s"))
    assert err.value.field == "camera_pose.header.frame_id"


def test_create_and_select_requests() -> None:
    req = m.msg(m.request_type(m.CREATE_SESSION), session="s1",
                camera_info=camera_info_msg(SMALL_INTRINSICS),
                bounds_min=m.msg("geometry_msgs/msg/Point", x=-1.0, y=-1.0, z=-1.0),
                bounds_max=m.msg("geometry_msgs/msg/Point", x=1.0, y=1.0, z=1.0),
                options_json='{"init_gaussians": 50, "defaults": {"method": "cover"}}')
    made = SessionCreate.model_validate(create_body(req, None))
    assert made.id == "s1" and made.intrinsics.model_dump() == SMALL_INTRINSICS
    assert made.init_gaussians == 50 and made.defaults.method == "cover"
    assert made.bounds is not None and made.bounds.max == [1.0, 1.0, 1.0]
    # no camera in the request: the namespace's last camera_info
    req.camera_info = m.msg(m.CAMERA_INFO)
    with pytest.raises(FieldError, match="camera_info"):
        create_body(req, None)
    assert create_body(req, camera_info_msg(SMALL_INTRINSICS))["intrinsics"] == SMALL_INTRINSICS
    for bad, field in (("[1]", "options_json"), ("{", "options_json"),
                       ('{"id": "x"}', "options_json.id")):
        req.options_json = bad
        with pytest.raises(FieldError) as err:
            create_body(req, camera_info_msg(SMALL_INTRINSICS))
        assert err.value.field == field

    sel = m.msg(m.request_type(m.SELECT), method="agile", shortlist_size=3, commit=True)
    assert SelectRequest.model_validate(select_body(sel, Binding("s"))) == SelectRequest(
        method="agile", shortlist_size=3, commit=True)
    assert select_body(m.msg(m.request_type(m.SELECT)), Binding("s")) == {"commit": False}
    sel = m.msg(m.request_type(m.SELECT), embodied_k=4, use_current_pose=True,
                current_pose=matrix_to_pose_msg(ring_poses(3)[1], "body"))
    got = SelectRequest.model_validate(select_body(sel, Binding("s", camera_frame="cam_link")))
    assert got.embodied_k == 4 and got.current_pose is not None
    np.testing.assert_allclose(got.current_pose.to_matrix(), ring_poses(3)[1], atol=1e-12)
    # the objective through config_json, the targets as poses
    sel = m.msg(m.request_type(m.SELECT), method="full_eig",
                config_json='{"objective": "target", "target_views": 2}',
                targets=[matrix_to_pose_msg(p, "body") for p in ring_poses(4)[[0, 2]]])
    got = SelectRequest.model_validate(select_body(sel, Binding("s", camera_frame="cam_link")))
    assert got.config is not None and got.config.objective == "target"
    assert got.targets is not None and len(got.targets) == 2
    np.testing.assert_allclose(got.targets[1].to_matrix(), ring_poses(4)[2], atol=1e-12)
    for bad in ("[1]", "{"):
        with pytest.raises(FieldError) as err:
            select_body(m.msg(m.request_type(m.SELECT), config_json=bad), Binding("s"))
        assert err.value.field == "config_json"


def test_a_decision_as_messages() -> None:
    poses = ring_poses(6)
    resp = SelectResponse(
        session="s", method="agile", chosen=Candidate(id=4, pose=Pose.from_matrix(poses[4])),
        shortlist=[ScoredCandidate(id=4, score=2.5), ScoredCandidate(id=1, score=None),
                   ScoredCandidate(id=9, score=1.0)],
        anchor=Pose.from_matrix(poses[0]), scores=[], eligible=[0, 1, 4], psi_trace=[],
        latency_ms={"total": 12.5}, core_ms=13.0, server_ms=14.0, committed=None, version=3,
        time=1700000000.25)
    pool = {i: p for i, p in enumerate(poses) if i != 4}  # the chosen one was committed
    binding = Binding("s", world_frame="odom", camera_frame="camera_link")
    chosen, shortlist = decision_msgs(resp, pool, binding)
    chosen = m.deserialize(m.serialize(chosen), m.POSE_STAMPED)
    assert chosen.header.frame_id == "odom"
    assert (chosen.header.stamp.sec, chosen.header.stamp.nanosec) == (1700000000, 250000000)
    np.testing.assert_allclose(pose_msg_to_matrix(chosen.pose, "body"), poses[4], atol=1e-12)
    # id 9 is in no pool: left out of the pose array and the id list alike
    assert len(shortlist.poses) == 2  # type: ignore[attr-defined]
    out = m.deserialize(m.serialize(select_response_msg(resp, m.msg(m.STATUS, status=200), pool,
                                                        binding)), m.response_type(m.SELECT))
    assert out.chosen_id == 4 and list(out.shortlist_ids) == [4, 1]
    assert out.shortlist_scores[0] == 2.5 and np.isnan(out.shortlist_scores[1])
    np.testing.assert_allclose(pose_msg_to_matrix(out.shortlist.poses[1], "body"), poses[1],
                               atol=1e-12)
    assert out.has_anchor and out.view_id == -1 and out.version == 3
    assert out.latency_ms == 12.5 and out.server_ms == 14.0
    refused = select_response_msg(None, m.msg(m.STATUS, status=409, code="empty_pool"), {}, None)
    refused = m.deserialize(m.serialize(refused), m.response_type(m.SELECT))
    assert refused.chosen_id == -1 and refused.status.code == "empty_pool"


def test_frames_pair_by_stamp_in_any_order() -> None:
    fa = FrameAssembler(expect_depth=True)
    assert fa.add("camera_pose", 2_000, "p2") == ([], [])
    assert fa.add("image", 1_000, "i1") == ([], [])
    assert fa.add("depth", 2_000, "d2") == ([], [])
    (done,), dropped = fa.add("image", 2_000, "i2")
    assert (done.image, done.depth, done.camera_pose) == ("i2", "d2", "p2") and not dropped
    assert fa.add("image", 2_000, "again") == ([], [])  # its frame is complete: ignored
    assert 2_000 not in fa.pending and 1_000 in fa.pending
    # a depth image pairs with the image nearest in time, within DEPTH_SYNC_NS
    fa.add("camera_pose", 1_000, "p1")
    assert fa.add("depth", 1_000 + DEPTH_SYNC_NS + 1, "too late") == ([], [])
    (done,), _ = fa.add("depth", 1_000 + DEPTH_SYNC_NS // 2, "d1")
    assert (done.image, done.depth) == ("i1", "d1")
    no_depth = FrameAssembler(expect_depth=False)
    no_depth.add("depth", 5_000_001, "d")
    no_depth.add("image", 5_000_000, "i")
    (done,), _ = no_depth.add("camera_pose", 5_000_000, "p")
    assert done.depth == "d"  # a depth that arrived in time joins the frame
    no_depth.add("image", 9 * 10**9, "i")
    (done,), _ = no_depth.add("camera_pose", 9 * 10**9, "p")
    assert done.depth is None  # none came: the frame does not wait for one
    small = FrameAssembler(expect_depth=False, max_pending=2)
    small.add("image", 10, "a")
    small.add("image", 11, "b")
    done_list, dropped = small.add("camera_pose", 12, "c")
    assert not done_list and [(d.stamp_ns, d.missing) for d in dropped] == [
        (10, ("camera_pose",))]
    with pytest.raises(ValueError):
        small.add("cmd_vel", 1, "x")


def test_incomplete_frames_are_dropped_past_their_deadline() -> None:
    fa = FrameAssembler(expect_depth=True, deadline=10.0)
    fa.add("image", 1_000, "i1")
    fa.add("camera_pose", 2_000, "p2")
    fa.add("depth", 50 * 10**9, "lone depth")
    t0 = fa.pending[1_000].arrived
    assert fa.expire(t0 + 9.0) == []  # within the deadline: they wait
    dropped = fa.expire(t0 + 60.0)
    assert [(d.stamp_ns, d.missing) for d in dropped] == [
        (1_000, ("camera_pose", "depth")), (2_000, ("image", "depth"))]
    assert fa.pending == {} and fa.depths == {}  # their parts are freed
    assert fa.expire(t0 + 120.0) == []


@pytest.mark.parametrize("field, topic", [
    ("observations.0.depth.shape", "depth"), ("observations.0.depth_scale", "depth"),
    ("depth.width", "depth"), ("observations.0.pose.orientation_xyzw", "camera_pose"),
    ("observations.0.intrinsics.fx", "camera_info"), ("image.width", "image"),
    ("observations.0.image.data", "image"), ("body", "camera_pose"), (None, "camera_pose"),
])
def test_a_refused_frame_names_the_part_at_fault(field: str | None, topic: str) -> None:
    from agilegs.service.transports.ros2.adapter import faulty_part

    # the part whose arrival completed the frame (here its pose) is named only when the field
    # names no part
    assert faulty_part(field, "camera_pose") == topic
