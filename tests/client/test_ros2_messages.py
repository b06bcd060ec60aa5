"""ROS 2 messages without ROS: CDR bytes, the bridge's keys, frames (REP-103 / optical),
camera infos and images, checked against independent constructions."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT

from agilegs.client.ros2 import (
    FieldError,
    Namespace,
    axes_of_frame,
    name_to_key,
    normalize_namespace,
)
from agilegs.client.ros2 import messages as m
from agilegs.client.ros2.frames import (
    Q_BODY_OPTICAL,
    R_BODY_OPTICAL,
    camera_info_msg,
    depth_image_msg,
    depth_to_array,
    image_to_rgb,
    intrinsics_of,
    matrix_to_pose_msg,
    pose_msg_to_matrix,
    pose_msg_to_wire,
    quaternion_multiply,
    rgb_image_msg,
)
from agilegs.schemas import Pose
from agilegs.schemas.geometry import quaternion_xyzw_to_matrix


def _rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll), the fixed-axis roll-pitch-yaw of ROS (tf2)."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch),
                              math.sin(pitch), math.cos(yaw), math.sin(yaw))
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _random_pose(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    out = np.eye(4)
    out[:3, :3] = quaternion_xyzw_to_matrix(q / np.linalg.norm(q))
    out[:3, 3] = rng.uniform(-3, 3, 3)
    return out


# ----------------------------------------------------------------------------- frames
def test_the_optical_rotation_is_the_camera_link_to_optical_frame_transform() -> None:
    # the static transform every ROS camera driver publishes: rpy (-pi/2, 0, -pi/2)
    np.testing.assert_allclose(R_BODY_OPTICAL, _rpy(-math.pi / 2, 0.0, -math.pi / 2),
                               atol=1e-15)
    np.testing.assert_allclose(quaternion_xyzw_to_matrix(Q_BODY_OPTICAL), R_BODY_OPTICAL,
                               atol=1e-15)
    # optical z (forward) is body x, optical x (right) is body -y, optical y (down) body -z
    np.testing.assert_array_equal(R_BODY_OPTICAL @ [0, 0, 1], [1, 0, 0])
    np.testing.assert_array_equal(R_BODY_OPTICAL @ [1, 0, 0], [0, -1, 0])
    np.testing.assert_array_equal(R_BODY_OPTICAL @ [0, 1, 0], [0, 0, -1])


def test_frame_names_give_their_axes() -> None:
    for name in ("camera_color_optical_frame", "/cam/depth_optical_frame", "head_optical",
                 "optical"):
        assert axes_of_frame(name) == "optical"
    for name in ("camera_link", "base_link", "camera_color_frame", "opticalish"):
        assert axes_of_frame(name) == "body"


def test_quaternion_product_composes_rotations() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        a, b = rng.normal(size=4), rng.normal(size=4)
        a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
        np.testing.assert_allclose(quaternion_xyzw_to_matrix(quaternion_multiply(a, b)),
                                   quaternion_xyzw_to_matrix(a) @ quaternion_xyzw_to_matrix(b),
                                   atol=1e-12)


@pytest.mark.parametrize("axes", ["optical", "body"])
def test_poses_go_both_ways(axes: str) -> None:
    rng = np.random.default_rng(1)
    for _ in range(20):
        c2w = _random_pose(rng)
        msg = matrix_to_pose_msg(c2w, axes)  # type: ignore[arg-type]
        assert msg.orientation.w >= 0
        np.testing.assert_allclose(pose_msg_to_matrix(msg, axes), c2w,  # type: ignore[arg-type]
                                   atol=1e-12)
        wire = Pose.model_validate(pose_msg_to_wire(msg, axes))  # type: ignore[arg-type]
        np.testing.assert_allclose(wire.to_matrix(), c2w, atol=1e-12)


def test_a_body_frame_pose_is_rotated_into_the_optical_frame() -> None:
    # a camera body at (1, 2, 3) looking along world +y (yaw 90 deg), z up: its optical
    # axis (OpenCV z) is world +y, image right (x) world +x, image down (y) world -z
    pose = m.msg("geometry_msgs/msg/Pose",
                 position=m.msg("geometry_msgs/msg/Point", x=1.0, y=2.0, z=3.0),
                 orientation=m.msg("geometry_msgs/msg/Quaternion", x=0.0, y=0.0,
                                   z=math.sin(math.pi / 4), w=math.cos(math.pi / 4)))
    c2w = pose_msg_to_matrix(pose, "body")
    np.testing.assert_allclose(c2w[:3, 2], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(c2w[:3, 0], [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(c2w[:3, 1], [0, 0, -1], atol=1e-15)
    np.testing.assert_array_equal(c2w[:3, 3], [1, 2, 3])
    # the same pose given as the optical frame's is taken as it is: a different camera
    assert not np.allclose(pose_msg_to_matrix(pose, "optical")[:3, :3], c2w[:3, :3])


def test_a_zero_quaternion_is_refused_naming_the_field() -> None:
    pose = m.msg("geometry_msgs/msg/Pose", position=m.msg("geometry_msgs/msg/Point"),
                 orientation=m.msg("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=0.0))
    with pytest.raises(FieldError) as err:
        pose_msg_to_matrix(pose, "optical", "camera_pose.pose")
    assert err.value.field == "camera_pose.pose.orientation"


# ----------------------------------------------------------------------------- cameras
def test_camera_info_puts_pixel_centres_at_integers() -> None:
    k = {"fx": 50.0, "fy": 52.0, "cx": 32.0, "cy": 24.0, "width": 64, "height": 48}
    info = camera_info_msg(k, frame_id="cam_optical_frame")
    assert list(info.k) == [50.0, 0, 31.5, 0, 52.0, 23.5, 0, 0, 1]
    assert list(info.p) == [50.0, 0, 31.5, 0, 0, 52.0, 23.5, 0, 0, 0, 1, 0]
    assert intrinsics_of(info) == k
    # the same 3D point in both conventions: agilegs' coordinate is OpenCV's + 0.5 (the
    # optical axis hits the image centre: (31.5, 23.5) for OpenCV, (32, 24) for agilegs)
    for x, y, z in ((0.0, 0.0, 2.0), (0.5, -0.25, 2.0)):
        u_cv, v_cv = info.k[0] * x / z + info.k[2], info.k[4] * y / z + info.k[5]
        u, v = k["fx"] * x / z + k["cx"], k["fy"] * y / z + k["cy"]
        assert (u - u_cv, v - v_cv) == (0.5, 0.5)
    assert (info.k[2], info.k[5]) == ((64 - 1) / 2, (48 - 1) / 2)


def test_camera_info_prefers_the_rectified_projection() -> None:
    info = camera_info_msg({"fx": 50.0, "fy": 50.0, "cx": 32.0, "cy": 32.0, "width": 64,
                            "height": 64})
    info.k = np.array([40.0, 0, 30.0, 0, 41.0, 29.0, 0, 0, 1])  # the raw camera
    assert intrinsics_of(info)["fx"] == 50.0
    info.p = np.zeros(12)
    assert intrinsics_of(info) == {"fx": 40.0, "fy": 41.0, "cx": 30.5, "cy": 29.5,
                                   "width": 64, "height": 64}


@pytest.mark.parametrize(("change", "field"), [
    ({"width": 0}, "camera_info.width"),
    ({"binning_x": 2}, "camera_info.binning_x"),
    ({"k": np.zeros(9), "p": np.zeros(12)}, "camera_info.k"),
])
def test_a_camera_info_agilegs_cannot_use_is_refused(change: dict, field: str) -> None:
    info = camera_info_msg({"fx": 50.0, "fy": 50.0, "cx": 32.0, "cy": 32.0, "width": 64,
                            "height": 64})
    for k, v in change.items():
        setattr(info, k, v)
    with pytest.raises(FieldError) as err:
        intrinsics_of(info)
    assert err.value.field == field


# ----------------------------------------------------------------------------- images
@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8"])
def test_colour_images_come_back_as_rgb(encoding: str) -> None:
    rgb = np.random.default_rng(2).integers(0, 256, (5, 7, 3), dtype=np.uint8)
    msg = m.deserialize(m.serialize(rgb_image_msg(rgb, encoding=encoding)), m.IMAGE)
    np.testing.assert_array_equal(image_to_rgb(msg), rgb)


def test_mono_and_padded_rows() -> None:
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4)
    padded = np.zeros((3, 8), np.uint8)
    padded[:, :4] = grey  # step 8 > width 4: padding at the end of each row
    msg = m.msg(m.IMAGE, header=m.msg("std_msgs/msg/Header", stamp=m.stamp_msg(0),
                                      frame_id=""),
                height=3, width=4, encoding="mono8", is_bigendian=0, step=8,
                data=padded.reshape(-1))
    np.testing.assert_array_equal(image_to_rgb(msg), np.repeat(grey[..., None], 3, axis=2))


def test_depth_encodings_of_a_realsense() -> None:
    mm = np.array([[0, 1, 1500], [65535, 2, 3]], dtype=np.uint16)
    d, scale = depth_to_array(depth_image_msg(mm, encoding="16UC1"))
    assert d.dtype == np.uint16 and scale == 0.001
    np.testing.assert_array_equal(d, mm)
    # big-endian 16UC1 from a driver that says so
    big = depth_image_msg(mm, encoding="16UC1")
    big.is_bigendian = 1
    big.data = mm.astype(">u2").view(np.uint8).reshape(-1)
    np.testing.assert_array_equal(depth_to_array(big)[0], mm)
    metres = np.array([[np.nan, 1.25, np.inf], [-np.inf, 0.0, 2.5]], dtype=np.float32)
    d, scale = depth_to_array(depth_image_msg(metres, encoding="32FC1"))
    assert scale == 1.0
    np.testing.assert_array_equal(d, [[0, 1.25, 0], [0, 0, 2.5]])


@pytest.mark.parametrize(("encoding", "fn", "field"), [
    ("yuv422", image_to_rgb, "image.encoding"), ("rgb8", depth_to_array, "depth.encoding")])
def test_an_unknown_encoding_is_refused_naming_the_field(encoding: str, fn: object,
                                                         field: str) -> None:
    msg = rgb_image_msg(np.zeros((2, 2, 3), np.uint8))
    msg.encoding = encoding
    with pytest.raises(FieldError) as err:
        fn(msg, field.split(".")[0])  # type: ignore[operator]
    assert err.value.field == field


def test_an_image_shorter_than_its_size_is_refused() -> None:
    msg = rgb_image_msg(np.zeros((4, 4, 3), np.uint8))
    msg.data = msg.data[:-3]
    with pytest.raises(FieldError) as err:
        image_to_rgb(msg)
    assert err.value.field == "image.data"


# ----------------------------------------------------------------------------- CDR
def test_cdr_bytes_are_what_a_ros2_publisher_writes() -> None:
    pose = m.msg(m.POSE_STAMPED, header=m.msg("std_msgs/msg/Header",
                                              stamp=m.stamp_msg(12, ns=True), frame_id="map"),
                 pose=matrix_to_pose_msg(np.eye(4)))
    raw = m.serialize(pose)
    assert raw[:4] == b"\x00\x01\x00\x00"  # CDR little-endian encapsulation
    # header: stamp (int32 sec, uint32 nanosec), frame_id (uint32 length with the NUL, bytes)
    sec, nsec, n = struct.unpack_from("<iII", raw, 4)
    assert (sec, nsec, n) == (0, 12, 4) and raw[16:20] == b"map\x00"
    # then the pose's 7 float64, 8-aligned from the start of the message
    vals = struct.unpack_from("<7d", raw, 4 + 16)
    assert vals == (0, 0, 0, 0, 0, 0, 1)
    big = bytes(m.typestore().serialize_cdr(pose, m.POSE_STAMPED, little_endian=False))
    assert big[:2] == b"\x00\x00" and m.deserialize(big, m.POSE_STAMPED) == pose


@pytest.mark.parametrize("raw", [b"", b"\x00\x01", b"\x00\x01\x00\x00\x01",
                                 b"\x07\x07\x00\x00" + bytes(60), b"junk" * 20])
def test_malformed_cdr_is_a_cdr_error(raw: bytes) -> None:
    with pytest.raises(m.CdrError):
        m.deserialize(raw, m.POSE_ARRAY)


def test_the_interface_package_is_registered_and_shipped() -> None:
    store = m.typestore()
    defs = m.interface_definitions()
    assert set(defs) == {"agilegs_interfaces/msg/Status"} | {
        f"agilegs_interfaces/srv/{s}_{half}" for s in ("CreateSession", "OpenSession", "Select")
        for half in ("Request", "Response")}
    for name in defs:
        assert name in store.types
    cmake = (m.INTERFACES_DIR / "CMakeLists.txt").read_text()
    for path in sorted(m.INTERFACES_DIR.rglob("*.*sg")) + sorted(
            m.INTERFACES_DIR.rglob("*.srv")):
        assert f'"{path.relative_to(m.INTERFACES_DIR)}"' in cmake
    # deploy/ros2/agilegs_interfaces is the same package (a link for colcon workspaces)
    deployed = ROOT / "deploy" / "ros2" / "agilegs_interfaces"
    assert deployed.resolve() == Path(m.INTERFACES_DIR).resolve()


# ----------------------------------------------------------------------------- keys
def test_keys_follow_the_bridge_mapping() -> None:
    assert name_to_key("/agilegs/candidates") == "agilegs/candidates"
    assert name_to_key("/agilegs/candidates", "/bot1") == "bot1/agilegs/candidates"
    assert name_to_key("/tf", "/bot1/") == "bot1/tf"
    ns = Namespace("bot1/agilegs/")
    assert ns.name == "/bot1/agilegs" and ns.key("select") == "bot1/agilegs/select"
    assert ns.leaf("bot1/agilegs/camera_pose") == "camera_pose"
    assert ns.leaf("bot2/agilegs/camera_pose") is None
    for bad in ("", "/", "/9lives", "/a b", "/a//b/c-d"):
        with pytest.raises(ValueError):
            normalize_namespace(bad)
    with pytest.raises(ValueError):
        ns.key("cmd_vel")
