"""The ROS 2 transport in process: CDR bytes on the keys zenoh-bridge-ros2dds uses, as the
bridge delivers them; the token and bad input behave as over HTTP and Zenoh (nothing
changes, the refusal names the field).

Peers meet on a loopback TCP endpoint with multicast and gossip scouting off.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import SMALL_INTRINSICS, free_port, ring_poses

from agilegs.client.ros2 import messages as m
from agilegs.client.ros2.frames import matrix_to_pose_msg, pose_msg_to_matrix, rgb_image_msg
from agilegs.client.ros2.robot import Ros2Robot
from agilegs.schemas import ErrorBody, codec
from agilegs.service.server import Server
from agilegs.service.settings import Settings

NS = "/bot/agilegs"
OTHER = "/other/agilegs"
BOUNDS = ([-0.5] * 3, [0.5] * 3)
H, W = SMALL_INTRINSICS["height"], SMALL_INTRINSICS["width"]
OPTIONS = {"init_gaussians": 150, "defaults": {
    "shortlist_size": 4, "config": {"anchor": {"iterations": 1, "num_starts": 1}}}}


class Listener:
    """The raw payloads published on a key."""

    def __init__(self, session: Any, key: str) -> None:
        self.payloads: list[bytes] = []
        self.arrived = threading.Event()
        self.sub = session.declare_subscriber(key, self._on)

    def _on(self, sample: Any) -> None:
        self.payloads.append(sample.payload.to_bytes())
        self.arrived.set()

    def wait(self, count: int = 1, timeout: float = 20.0) -> list[bytes]:
        deadline = time.monotonic() + timeout
        while len(self.payloads) < count and time.monotonic() < deadline:
            time.sleep(0.02)
        assert len(self.payloads) >= count, f"{len(self.payloads)} of {count} publications"
        return self.payloads


@contextmanager
def _serve(tmp_path: Path, **settings: Any) -> Iterator[tuple[Server, str]]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    srv = Server(Settings(state_dir=tmp_path / "state", http=False, zenoh_listen=[ep],
                          mapper=False, workers=2, ros2=[NS, OTHER], warmup=False, **settings))
    srv.start()
    try:
        yield srv, ep
    finally:
        srv.close()


@pytest.fixture
def served(tmp_path: Path) -> Iterator[tuple[Server, str]]:
    with _serve(tmp_path) as served:
        yield served


def _robot(ep: str, ns: str = NS, **kwargs: Any) -> Ros2Robot:
    return Ros2Robot(ns, connect=[ep], **{"timeout": 60, **kwargs})


def _frame(robot: Ros2Robot, c2w: np.ndarray, stamp: int) -> None:
    rgb = np.random.default_rng(stamp).integers(0, 256, (H, W, 3), dtype=np.uint8)
    robot.publish_frame(rgb, c2w, depth=np.full((H, W), 1200, np.uint16), stamp_ns=stamp)


def _state(srv: Server, sid: str) -> tuple[int, int, int]:
    info = srv.gateway.execute("get_session", sid, None)
    return info.version, info.pool_size, info.num_views  # type: ignore[attr-defined]


def _until(cond: Any, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)


def test_a_robot_drives_a_session_with_cdr(served: tuple[Server, str]) -> None:
    srv, ep = served
    with _robot(ep) as robot:
        decisions = Listener(robot.session, robot.ns.key("decision"))
        shortlists = Listener(robot.session, robot.ns.key("shortlist"))
        time.sleep(0.3)  # let the subscriptions reach the server
        robot.publish_camera_info(SMALL_INTRINSICS)
        made = robot.create_session(bounds=BOUNDS, session="r1", expect_depth=True,
                                    options=OPTIONS)
        assert (made.status.status, made.session) == (200, "r1")
        robot.publish_candidates(ring_poses(8))
        _frame(robot, ring_poses(8)[0], stamp=11)
        answer = robot.select(method="agile")
        assert answer.status.status == 200 and answer.status.code == ""
        # the frame was applied before the selection (one ordered queue per namespace)
        views = srv.gateway.execute("list_views", "r1", None).views  # type: ignore[attr-defined]
        assert len(views) == 1 and views[0].has_image and views[0].has_depth
        assert views[0].intrinsics.model_dump() == SMALL_INTRINSICS
        np.testing.assert_allclose(views[0].pose.to_matrix(), ring_poses(8)[0], atol=1e-9)
        # the chosen pose comes back in the reply and as a PoseStamped on <ns>/decision
        chosen = ring_poses(8)[answer.chosen_id]
        np.testing.assert_allclose(pose_msg_to_matrix(answer.chosen.pose), chosen, atol=1e-9)
        raw = decisions.wait()[0]
        assert raw[:4] == b"\x00\x01\x00\x00"
        published = m.deserialize(raw, m.POSE_STAMPED)
        assert published.header.frame_id == "map" and published.header.stamp.sec > 0
        np.testing.assert_allclose(pose_msg_to_matrix(published.pose), chosen, atol=1e-9)
        shortlist = m.deserialize(shortlists.wait()[0], m.POSE_ARRAY)
        assert len(shortlist.poses) == len(answer.shortlist_ids) == 4
        for i, p in zip(answer.shortlist_ids, shortlist.poses, strict=True):
            np.testing.assert_allclose(pose_msg_to_matrix(p), ring_poses(8)[i], atol=1e-9)
        # a decision made over another transport is published to the robot too
        from agilegs.schemas import SelectRequest

        srv.gateway.execute("select", "r1", SelectRequest(method="random"))
        decisions.wait(2)
        # open_session binds another namespace to the same session
        with _robot(ep, OTHER) as other:
            opened = other.open_session("r1")
            assert (opened.status.status, opened.num_views, opened.pool_size) == (200, 1, 8)
            assert other.select(method="random").chosen_id >= 0


def _errors(robot: Ros2Robot) -> Listener:
    return Listener(robot.session, robot.ns.key("errors"))


def test_bad_input_is_refused_naming_the_field_and_changes_nothing(
        served: tuple[Server, str]) -> None:
    srv, ep = served
    with _robot(ep) as robot:
        errors = _errors(robot)
        bodies = Listener(robot.session, "agilegs/r2/errors")
        time.sleep(0.3)
        assert robot.create_session(bounds=BOUNDS, session="r2", intrinsics=SMALL_INTRINSICS,
                                    options=OPTIONS).status.status == 200
        robot.publish_candidates(ring_poses(6))
        _until(lambda: _state(srv, "r2")[1] == 6)
        before = _state(srv, "r2")
        bad_quaternion = m.msg(m.POSE_ARRAY, header=m.msg("std_msgs/msg/Header", frame_id="map"),
                               poses=[matrix_to_pose_msg(p) for p in ring_poses(3)])
        bad_quaternion.poses[1].orientation.w += 0.5
        wrong_frame = m.msg(m.POSE_STAMPED,
                            header=m.msg("std_msgs/msg/Header", frame_id="odom",
                                         stamp=m.stamp_msg(5, ns=True)),
                            pose=matrix_to_pose_msg(ring_poses(3)[0]))
        yuv = rgb_image_msg(np.zeros((H, W, 3), np.uint8), stamp=m.stamp_msg(6, ns=True))
        yuv.encoding = "yuv422"
        cases = [
            (lambda: robot.put("candidates", b"\x00\x01\x00\x00\xff\xff"), 400,
             "candidates.payload"),
            (lambda: robot.put("camera_pose", b"not cdr at all"), 400, "camera_pose.payload"),
            (lambda: robot.publish("candidates", bad_quaternion), 422,
             "body.poses[1].orientation_xyzw"),
            (lambda: robot.publish("camera_pose", wrong_frame), 422,
             "camera_pose.header.frame_id"),
            (lambda: (robot.publish("image", yuv), robot.publish("camera_pose", m.msg(
                m.POSE_STAMPED, header=m.msg("std_msgs/msg/Header", frame_id="map",
                                             stamp=m.stamp_msg(6, ns=True)),
                pose=matrix_to_pose_msg(ring_poses(3)[0])))), 422, "image.encoding"),
        ]
        for i, (send, status, field) in enumerate(cases):
            send()
            got = m.deserialize(errors.wait(i + 1)[i], m.STATUS)
            assert (got.status, got.field, got.session) == (status, field, "r2"), got
        assert _state(srv, "r2") == before
        body = ErrorBody.model_validate(codec.load(bodies.wait(len(cases))[2], codec.MSGPACK))
        assert body.error.field == "body.poses[1].orientation_xyzw"
        # service requests: an undecodable request, a bad value
        bad = m.deserialize(robot.call_raw("select", b"\x00\x01\x00\x00\x05"),
                            m.response_type(m.SELECT))
        assert (bad.status.status, bad.status.field, bad.chosen_id) == (400, "request.payload",
                                                                         -1)
        nope = robot.select(method="nope")
        assert (nope.status.status, nope.status.field) == (422, "body.method")
        assert _state(srv, "r2") == before
        # a namespace bound to no session changes nothing either
    with _robot(ep, OTHER) as other:
        errors = _errors(other)
        time.sleep(0.3)
        other.publish_candidates(ring_poses(2))
        got = m.deserialize(errors.wait()[0], m.STATUS)
        assert (got.status, got.field, got.session) == (404, "namespace", "")
        assert other.select().status.status == 404
        missing = other.open_session("no-such-session")
        assert (missing.status.status, missing.status.code) == (404, "not_found")
    assert _state(srv, "r2") == before


def test_the_token_guards_every_service_and_binds_the_topics(tmp_path: Path) -> None:
    with _serve(tmp_path, token="s3cret") as (srv, ep):
        # with a token the server makes Zenoh credentials: a robot without them gets nothing
        with _robot(ep, timeout=2) as stranger:
            with pytest.raises(TimeoutError):
                stranger.create_session(bounds=BOUNDS, session="t0",
                                        intrinsics=SMALL_INTRINSICS)
        creds = tmp_path / "state" / "zenoh" / "client.json"
        with _robot(ep, credentials=creds) as robot:
            errors = _errors(robot)
            time.sleep(0.3)
            denied = robot.create_session(bounds=BOUNDS, session="t1",
                                          intrinsics=SMALL_INTRINSICS)
            assert (denied.status.status, denied.status.field) == (401, "token")
            assert srv.gateway.execute("list_sessions", None, None).sessions == []  # type: ignore[attr-defined]
            robot.publish_candidates(ring_poses(3))  # no binding: nothing to act on
            assert m.deserialize(errors.wait()[0], m.STATUS).status == 404
            robot.token = "wrong"
            assert robot.select().status.status == 401
            robot.token = "s3cret"
            assert robot.create_session(bounds=BOUNDS, session="t1",
                                        intrinsics=SMALL_INTRINSICS,
                                        options=OPTIONS).status.status == 200
            robot.publish_candidates(ring_poses(5))  # bound by an authorised call
            _until(lambda: _state(srv, "t1")[1] == 5)
            before = _state(srv, "t1")
            robot.token = ""
            refused = robot.select(method="random", commit=True)
            assert (refused.status.status, refused.status.code) == (401, "unauthorized")
            assert _state(srv, "t1") == before
            robot.token = "s3cret"
            assert robot.select(method="random", commit=True).view_id == 0


def test_a_select_sent_again_with_its_request_id_commits_once(
        served: tuple[Server, str]) -> None:
    srv, ep = served
    with _robot(ep) as robot:
        robot.publish_camera_info(SMALL_INTRINSICS)
        assert robot.create_session(bounds=BOUNDS, session="r2").status.status == 200
        robot.publish_candidates(ring_poses(8))
        first = robot.call("select", token="", method="random", commit=True,
                           request_id="ros2-select-01")
        _until(lambda: _state(srv, "r2")[2] == 1)
        again = robot.call("select", token="", method="random", commit=True,
                           request_id="ros2-select-01")
        assert again.status.status == 200 and again.view_id == first.view_id >= 0
        assert again.chosen_id == first.chosen_id and _state(srv, "r2")[2] == 1
        bad = robot.call("select", token="", method="random", request_id="bad id")
        assert (bad.status.status, bad.status.field) == (400, "request_id")


def test_the_robot_rides_through_a_handover_with_one_request_id() -> None:
    sent: list[bytes] = []
    answers = [m.msg(m.response_type(m.SELECT), chosen_id=-1, status=m.msg(
        m.STATUS, status=404, code="session_unavailable", retry_after=0.01)),
        m.msg(m.response_type(m.SELECT), chosen_id=3, status=m.msg(m.STATUS, status=200))]
    robot = Ros2Robot(NS, session=object())

    def call_raw(leaf: str, payload: bytes) -> bytes:
        sent.append(payload)
        return m.serialize(answers[len(sent) - 1])

    robot.call_raw = call_raw  # type: ignore[method-assign]
    assert robot.select(method="random", commit=True).chosen_id == 3
    ids = [m.deserialize(p, m.request_type(m.SELECT)).request_id for p in sent]
    assert len(ids) == 2 and ids[0] == ids[1] and len(ids[0]) == 32
    sent.clear()
    robot.retry_window = 0.0  # off: the refusal is the answer
    assert robot.select(method="random").status.status == 404 and len(sent) == 1
