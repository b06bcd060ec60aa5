"""rosbag2 round trips written by ``rosbags`` itself (no ROS install): MCAP and sqlite3, poses
from TF or a pose topic, images and depth bit for bit."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from conftest import ring_poses

from agilegs.client.ros2 import (
    BagFrame,
    BagTopics,
    is_bag,
    observations_from_bag,
    read_bag,
    write_bag,
)
from agilegs.client.ros2 import messages as m
from agilegs.client.ros2.frames import matrix_to_pose_msg
from agilegs.schemas import ObservationIn
from agilegs.schemas.geometry import quaternion_xyzw_to_matrix

K = {"fx": 20.0, "fy": 21.0, "cx": 8.0, "cy": 6.5, "width": 16, "height": 12}


def _frames(n: int = 5, depth: str | None = "16UC1") -> list[BagFrame]:
    rng = np.random.default_rng(3)
    out = []
    for i, c2w in enumerate(ring_poses(n)):
        d = None
        if depth == "16UC1":
            d = rng.integers(0, 5000, (12, 16), dtype=np.uint16)
        elif depth == "32FC1":
            d = rng.uniform(0.2, 3.0, (12, 16)).astype(np.float32)
        out.append(BagFrame(stamp_ns=1_000_000_000 + i * 100_000_000,
                            rgb=rng.integers(0, 256, (12, 16, 3), dtype=np.uint8),
                            intrinsics=dict(K), c2w=c2w, depth=d,
                            depth_scale=0.001 if depth == "16UC1" else 1.0))
    return out


def _check(got: list[BagFrame], want: list[BagFrame]) -> None:
    assert [f.stamp_ns for f in got] == [f.stamp_ns for f in want]
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g.rgb, w.rgb)
        assert g.intrinsics == w.intrinsics
        np.testing.assert_allclose(g.c2w, w.c2w, rtol=0, atol=1e-12)
        if w.depth is None:
            assert g.depth is None
        else:
            assert g.depth is not None and g.depth.dtype == w.depth.dtype
            np.testing.assert_array_equal(g.depth, w.depth)
            assert g.depth_scale == w.depth_scale


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("poses", ["tf", "pose"])
def test_a_bag_round_trips(tmp_path: Path, storage: str, poses: str) -> None:
    frames = _frames()
    bag = write_bag(tmp_path / "bag", frames, storage=storage, poses=poses)
    assert is_bag(bag) and (bag / "metadata.yaml").is_file()
    _check(read_bag(bag), frames)
    # the storage file alone reads the same
    (single,) = [p for p in bag.iterdir() if p.suffix in (".mcap", ".db3")]
    assert is_bag(single)
    _check(read_bag(single), frames)


def test_float_depth_and_no_depth(tmp_path: Path) -> None:
    frames = _frames(3, "32FC1")
    _check(read_bag(write_bag(tmp_path / "metres", frames)), frames)
    frames = _frames(3, None)
    _check(read_bag(write_bag(tmp_path / "rgb", frames, storage="sqlite3")), frames)


def test_a_body_frame_pose_topic_is_rotated(tmp_path: Path) -> None:
    frames = _frames(3)
    bag = write_bag(tmp_path / "bag", frames, poses="pose", camera_frame="camera_link")
    # the pose topic holds the body frame's pose: x forward (the optical z)
    from rosbags.highlevel import AnyReader

    with AnyReader([bag], default_typestore=m.typestore()) as r:
        conn = next(c for c in r.connections if c.topic == "/camera/pose")
        first = r.deserialize(next(r.messages(connections=[conn]))[2], conn.msgtype)
    body = matrix_to_pose_msg(frames[0].c2w, "body")
    fields = ("x", "y", "z")
    assert [getattr(first.pose.position, a) for a in fields] == [
        getattr(body.position, a) for a in fields]
    assert [getattr(first.pose.orientation, a) for a in (*fields, "w")] == [
        getattr(body.orientation, a) for a in (*fields, "w")]
    optical = matrix_to_pose_msg(frames[0].c2w, "optical")
    assert not np.isclose(first.pose.orientation.w, optical.orientation.w)
    _check(read_bag(bag), frames)


def test_a_pose_track_interpolates_between_samples() -> None:
    frames = _frames(3, None)
    from agilegs.client.ros2.bag import _Track

    track = _Track()
    for f in frames:
        pose = matrix_to_pose_msg(f.c2w, "optical")
        track.add(f.stamp_ns, np.array([pose.position.x, pose.position.y, pose.position.z]),
                  np.array([pose.orientation.x, pose.orientation.y, pose.orientation.z,
                            pose.orientation.w]))
    mid = (frames[0].stamp_ns + frames[1].stamp_ns) // 2
    p, q = track.at(mid, 10**9)  # type: ignore[misc]
    np.testing.assert_allclose(p, (frames[0].c2w[:3, 3] + frames[1].c2w[:3, 3]) / 2,
                               atol=1e-12)
    # halfway in rotation: the angle to either end is the same
    q0, q1 = track.samples[0][1], track.samples[1][1]
    a0 = 2 * math.acos(min(1.0, abs(float(np.dot(q, q0)))))
    a1 = 2 * math.acos(min(1.0, abs(float(np.dot(q, q1)))))
    assert a0 == pytest.approx(a1, abs=1e-9) and a0 > 0
    assert track.at(frames[1].stamp_ns, 10) is track.samples[1]  # a sample: exactly it
    assert track.at(frames[0].stamp_ns - 1, 10**9) is None  # before the first pose
    assert track.at(mid, 10) is None  # a gap over max_gap


def test_frames_without_a_pose_are_left_out(tmp_path: Path) -> None:
    frames = _frames(4, None)
    bag = write_bag(tmp_path / "bag", frames, poses="pose")
    late = BagFrame(stamp_ns=frames[-1].stamp_ns + 5 * 10**9, rgb=frames[0].rgb,
                    intrinsics=dict(K), c2w=np.eye(4))
    assert len(read_bag(bag)) == 4
    bag2 = write_bag(tmp_path / "bag2", [*frames, late], poses="tf")
    got = read_bag(bag2, BagTopics(max_gap_s=0.5))
    assert len(got) == 5  # the late frame has its own TF sample
    assert len(read_bag(bag2, max_frames=2)) == 2


def test_observations_from_a_bag(tmp_path: Path) -> None:
    frames = _frames(3)
    obs = observations_from_bag(write_bag(tmp_path / "bag", frames), image_encoding="raw")
    assert len(obs) == 3 and all(isinstance(o, ObservationIn) for o in obs)
    o = obs[1]
    np.testing.assert_allclose(o.pose.to_matrix(), frames[1].c2w, atol=1e-12)  # type: ignore[union-attr]
    np.testing.assert_array_equal(o.image.to_numpy(), frames[1].rgb)  # type: ignore[union-attr]
    np.testing.assert_array_equal(o.depth.to_numpy(), frames[1].depth)  # type: ignore[union-attr]
    assert o.depth_scale == 0.001 and o.intrinsics.model_dump() == K  # type: ignore[union-attr]


def test_topics_parse_and_name_what_is_wrong(tmp_path: Path) -> None:
    t = BagTopics.parse("image=/a/color, depth=none,pose=tf,world=map,sync_s=0.05")
    assert (t.image, t.depth, t.pose, t.world_frame, t.sync_s) == ("/a/color", "none", "tf",
                                                                    "map", 0.05)
    assert BagTopics.parse(t.describe()) == t
    for bad in ("colour=/x", "image", "sync_s=fast"):
        with pytest.raises(ValueError):
            BagTopics.parse(bad)
    bag = write_bag(tmp_path / "bag", _frames(2))
    with pytest.raises(ValueError, match="/nope"):
        read_bag(bag, BagTopics(image="/nope"))
    with pytest.raises(ValueError, match="not"):
        read_bag(bag, BagTopics(pose="/camera/color/image_raw"))
    assert read_bag(bag, BagTopics(depth="none"))[0].depth is None
    with pytest.raises(FileNotFoundError):
        read_bag(tmp_path)


def test_a_tf_chain_is_composed_and_interpolated_at_the_image_stamp(tmp_path: Path) -> None:
    """world -> base (dynamic: yaw 0 at t0, 90 deg at t1, moving along x) -> camera_link
    (static offset) -> camera_color_optical_frame (static optical rotation); an image halfway
    between t0 and t1 has the pose of yaw 45 deg, halfway along x, through the chain."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from agilegs.client.ros2.bag import _tf_msg
    from agilegs.client.ros2.frames import R_BODY_OPTICAL, camera_info_msg, rgb_image_msg

    def yaw(deg: float) -> np.ndarray:
        a = math.radians(deg) / 2
        return np.array([0.0, 0.0, math.sin(a), math.cos(a)])

    t0, t1 = 10**9, 10**9 + 400_000_000  # closer than max_gap_s
    mid = (t0 + t1) // 2
    cam = "camera_color_optical_frame"
    store = m.typestore()
    bag = tmp_path / "chain"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        tf = w.add_connection("/tf", m.TF_MESSAGE, typestore=store)
        static = w.add_connection("/tf_static", m.TF_MESSAGE, typestore=store)
        img = w.add_connection("/cam/color/image_raw", m.IMAGE, typestore=store)
        info = w.add_connection("/cam/color/camera_info", m.CAMERA_INFO, typestore=store)
        w.write(static, 0, m.serialize(_tf_msg([
            ("base", "camera_link", np.array([0.0, 0.5, 0.0]), yaw(0), 0),
            ("camera_link", cam, np.zeros(3), np.array([-0.5, 0.5, -0.5, 0.5]), 0)])))
        for t, x, deg in ((t0, 0.0, 0.0), (t1, 2.0, 90.0)):
            w.write(tf, t, m.serialize(_tf_msg([("world", "base", np.array([x, 0.0, 0.0]),
                                                 yaw(deg), t)])))
        stamp = m.stamp_msg(mid, ns=True)
        w.write(info, mid, m.serialize(camera_info_msg(K, frame_id=cam, stamp=stamp)))
        w.write(img, mid, m.serialize(rgb_image_msg(np.zeros((12, 16, 3), np.uint8),
                                                    frame_id=cam, stamp=stamp)))
    (frame,) = read_bag(bag)
    r45 = quaternion_xyzw_to_matrix(yaw(45))
    want = np.eye(4)
    want[:3, :3] = r45 @ R_BODY_OPTICAL
    want[:3, 3] = np.array([1.0, 0.0, 0.0]) + r45 @ [0.0, 0.5, 0.0]
    np.testing.assert_allclose(frame.c2w, want, atol=1e-12)
    assert read_bag(bag, BagTopics(world_frame="base"))[0].c2w[0, 3] == pytest.approx(0.0)
    assert read_bag(bag, BagTopics(world_frame="odom")) == []  # a frame it never reaches
