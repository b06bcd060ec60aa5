"""ROS 2 messages <-> the service's operations: request bodies built from messages, and the
messages built from the answers. No Zenoh here (:mod:`.adapter` is the glue).

A request body built here is plain data that the gateway validates as it validates an
HTTP body (the same checks, the same field names: ``body.poses[2].orientation_xyzw``);
what only a ROS message can get wrong (an encoding, a frame id, a camera info) is refused
here with a :class:`~agilegs.client.ros2.frames.FieldError` naming the message field.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from agilegs.client.ros2 import FieldError, axes_of_frame
from agilegs.client.ros2 import messages as m
from agilegs.client.ros2.frames import Axes, intrinsics_of, matrix_to_pose_msg, pose_msg_to_wire
from agilegs.schemas import SelectResponse

__all__ = [
    "DEFAULT_CAMERA_FRAME",
    "DEFAULT_WORLD_FRAME",
    "Binding",
    "check_world_frame",
    "create_body",
    "decision_msgs",
    "frame_body",
    "pool_body",
    "pose_part",
    "select_body",
    "select_response_msg",
    "status_msg",
]

DEFAULT_WORLD_FRAME = "map"
DEFAULT_CAMERA_FRAME = "camera_optical_frame"


@dataclass(frozen=True)
class Binding:
    """What a namespace's topics act on: the session, the world frame every pose is in, the
    camera frame the camera poses are of (its axes from its name), and whether a frame waits
    for a depth image."""

    session: str
    world_frame: str = DEFAULT_WORLD_FRAME
    camera_frame: str = DEFAULT_CAMERA_FRAME
    expect_depth: bool = False

    @classmethod
    def of(cls, req: Any, session: str) -> Binding:
        """The binding a CreateSession / OpenSession request asks for."""
        return cls(session=session,
                   world_frame=req.world_frame.strip() or DEFAULT_WORLD_FRAME,
                   camera_frame=req.camera_frame.strip() or DEFAULT_CAMERA_FRAME,
                   expect_depth=bool(req.expect_depth))

    @property
    def axes(self) -> Axes:
        return axes_of_frame(self.camera_frame)


def check_world_frame(header: Any, binding: Binding, topic: str) -> None:
    """FieldError unless ``header.frame_id`` is the binding's world frame (or empty)."""
    given = header.frame_id.strip().strip("/")
    if given and given != binding.world_frame.strip("/"):
        raise FieldError(f"{topic}.header.frame_id", f"{header.frame_id!r} is not the world "
                         f"frame {binding.world_frame!r} this namespace was opened with "
                         "(agilegs does not look up TF)")


# ----------------------------------------------------------------------------- requests
def pool_body(poses: Any, binding: Binding) -> dict[str, Any]:
    """The ``set_pool`` body of a ``geometry_msgs/PoseArray`` of camera poses."""
    check_world_frame(poses.header, binding, "candidates")
    return {"poses": [pose_msg_to_wire(p, binding.axes) for p in poses.poses]}


def pose_part(pose: Any, binding: Binding) -> dict[str, list[float]]:
    """The wire pose of a ``camera_pose`` PoseStamped (refused in another world frame)."""
    check_world_frame(pose.header, binding, "camera_pose")
    return pose_msg_to_wire(pose.pose, binding.axes)


def frame_body(rgb: np.ndarray, pose: dict[str, list[float]],
               depth: tuple[np.ndarray, float] | None, intrinsics: dict[str, Any] | None
               ) -> dict[str, Any]:
    """The ``add_observations`` body of one frame: RGB uint8 [H, W, 3] (``image_to_rgb``),
    its wire pose (:func:`pose_part`), ``(depth [H, W], depth_scale)`` (``depth_to_array``)
    or None, and the camera's intrinsics (None: the session's)."""
    obs: dict[str, Any] = {
        "pose": pose,
        "image": {"encoding": "raw", "dtype": "uint8", "shape": list(rgb.shape),
                  "data": rgb.tobytes()},
    }
    if intrinsics is not None:
        if (intrinsics["height"], intrinsics["width"]) != rgb.shape[:2]:
            raise FieldError("image.width", f"the image is {rgb.shape[1]}x{rgb.shape[0]} but "
                             f"camera_info says {intrinsics['width']}x{intrinsics['height']}")
        obs["intrinsics"] = intrinsics
    if depth is not None:
        d, scale = depth
        if d.shape != rgb.shape[:2]:
            raise FieldError("depth.width", f"the depth image is {d.shape[1]}x{d.shape[0]}, "
                             f"the colour image {rgb.shape[1]}x{rgb.shape[0]} (publish the "
                             "depth aligned to colour)")
        obs["depth"] = {"dtype": d.dtype.name, "shape": list(d.shape),
                        "data": np.ascontiguousarray(d, dtype=d.dtype.newbyteorder("<"))
                        .tobytes()}
        obs["depth_scale"] = scale
    return {"observations": [obs]}


def create_body(req: Any, camera: Any | None) -> dict[str, Any]:
    """The ``create_session`` body of a CreateSession request; ``camera`` is the last
    ``camera_info`` of the namespace (used when the request's has width 0)."""
    info = req.camera_info if int(req.camera_info.width) else camera
    if info is None:
        raise FieldError("camera_info.width", "no camera: fill camera_info, or publish "
                         "<namespace>/camera_info first")
    body: dict[str, Any] = {}
    if req.options_json.strip():
        try:
            body = json.loads(req.options_json)
        except json.JSONDecodeError as exc:
            raise FieldError("options_json", f"not JSON ({exc})") from None
        if not isinstance(body, dict):
            raise FieldError("options_json", "must be a JSON object of session fields")
        for key in ("id", "intrinsics", "bounds"):
            if key in body:
                raise FieldError(f"options_json.{key}", "is set by the request's own fields")
    body["intrinsics"] = intrinsics_of(info, "camera_info")
    lo, hi = req.bounds_min, req.bounds_max
    if any(float(v) != 0.0 for v in (lo.x, lo.y, lo.z, hi.x, hi.y, hi.z)):
        body["bounds"] = {"min": [lo.x, lo.y, lo.z], "max": [hi.x, hi.y, hi.z]}
    if req.session.strip():
        body["id"] = req.session.strip()
    return body


def select_body(req: Any, binding: Binding) -> dict[str, Any]:
    """The ``select`` body of a Select request (0, "" and an empty ``targets`` take the
    session's defaults; ``config_json`` is the body's ``config``)."""
    body: dict[str, Any] = {"commit": bool(req.commit)}
    if req.method.strip():
        body["method"] = req.method.strip()
    if int(req.shortlist_size):
        body["shortlist_size"] = int(req.shortlist_size)
    if int(req.embodied_k):
        body["embodied_k"] = int(req.embodied_k)
    if req.use_current_pose:
        body["current_pose"] = pose_msg_to_wire(req.current_pose, binding.axes)
    if req.config_json.strip():
        try:
            config = json.loads(req.config_json)
        except json.JSONDecodeError as exc:
            raise FieldError("config_json", f"not JSON ({exc})") from None
        if not isinstance(config, dict):
            raise FieldError("config_json", "must be a JSON object of SelectConfig fields")
        body["config"] = config
    if len(req.targets):
        body["targets"] = [pose_msg_to_wire(p, binding.axes) for p in req.targets]
    return body


# ----------------------------------------------------------------------------- answers
def status_msg(status: int = 200, code: str = "", message: str = "", field: str | None = None,
               *, session: str = "", topic: str = "", stamp: Any = None,
               retry_after: float | None = None) -> Any:
    """An ``agilegs_interfaces/msg/Status``."""
    return m.msg(m.STATUS, status=int(status), code=str(code), message=message,
                 field=field or "", session=session, topic=topic,
                 stamp=stamp if stamp is not None else m.stamp_msg(0),
                 retry_after=float(retry_after or 0.0))


def _header(binding: Binding, t: float) -> Any:
    return m.msg("std_msgs/msg/Header", stamp=m.stamp_msg(t), frame_id=binding.world_frame)


def _pose_array(matrices: list[np.ndarray], binding: Binding, t: float) -> Any:
    return m.msg(m.POSE_ARRAY, header=_header(binding, t),
                 poses=[matrix_to_pose_msg(c2w, binding.axes) for c2w in matrices])


def _shortlist(resp: SelectResponse, poses: dict[int, np.ndarray]) -> list[tuple[int, float]]:
    """The shortlist's (id, score) whose pose is known (the chosen one's always is)."""
    known = dict(poses)
    known[resp.chosen.id] = resp.chosen.pose.to_matrix()
    return [(c.id, math.nan if c.score is None else float(c.score)) for c in resp.shortlist
            if c.id in known]


def decision_msgs(resp: SelectResponse, poses: dict[int, np.ndarray], binding: Binding
                  ) -> tuple[Any, Any]:
    """``(PoseStamped of the chosen view, PoseArray of the shortlist)`` of a decision, in the
    binding's world frame and camera axes, stamped with the decision's time; ``poses`` maps
    candidate ids to camera-to-world matrices (the pool)."""
    known = dict(poses)
    known[resp.chosen.id] = resp.chosen.pose.to_matrix()
    chosen = m.msg(m.POSE_STAMPED, header=_header(binding, resp.time),
                   pose=matrix_to_pose_msg(known[resp.chosen.id], binding.axes))
    ids = [i for i, _ in _shortlist(resp, poses)]
    return chosen, _pose_array([known[i] for i in ids], binding, resp.time)


def select_response_msg(resp: SelectResponse | None, status: Any, poses: dict[int, np.ndarray],
                        binding: Binding | None) -> Any:
    """The Select response: the decision (``resp``) with ``status``, or only ``status`` (a
    refusal: ``chosen_id`` -1, empty lists)."""
    empty_pose = matrix_to_pose_msg(np.eye(4))
    world = binding or Binding(session="")
    if resp is None:
        return m.msg(
            m.response_type(m.SELECT), status=status, chosen_id=-1,
            chosen=m.msg(m.POSE_STAMPED, header=_header(world, 0.0), pose=empty_pose),
            shortlist_ids=np.zeros(0, np.int64), shortlist_scores=np.zeros(0),
            shortlist=_pose_array([], world, 0.0), has_anchor=False, anchor=empty_pose,
            view_id=-1, latency_ms=0.0, server_ms=0.0, version=0)
    chosen, shortlist = decision_msgs(resp, poses, world)
    listed = _shortlist(resp, poses)
    return m.msg(
        m.response_type(m.SELECT), status=status, chosen_id=resp.chosen.id, chosen=chosen,
        shortlist_ids=np.array([i for i, _ in listed], np.int64),
        shortlist_scores=np.array([s for _, s in listed], np.float64), shortlist=shortlist,
        has_anchor=resp.anchor is not None,
        anchor=(matrix_to_pose_msg(resp.anchor.to_matrix(), world.axes)
                if resp.anchor is not None else empty_pose),
        view_id=resp.committed.id if resp.committed is not None else -1,
        latency_ms=float(resp.latency_ms.get("total", 0.0)),
        server_ms=float(resp.server_ms or 0.0), version=int(resp.version))
