"""A ROS 2 robot's side of agilegs over Zenoh, as zenoh-bridge-ros2dds delivers it: CDR
messages put on the namespace's keys, and service requests as Zenoh queries whose payload
is the request's CDR (the 4-byte encapsulation header, then the request) with the bridge's
request-id attachment.

For scripts, demos and tests that play the robot without ROS::

    from agilegs.client.ros2.robot import Ros2Robot

    with Ros2Robot("/bot1/agilegs", connect=["tcp/127.0.0.1:7447"]) as robot:
        robot.publish_camera_info(intrinsics)
        sid = robot.create_session(bounds=([-1, -1, -1], [1, 1, 1])).session
        robot.publish_candidates(poses)                 # [D, 4, 4] camera-to-world
        robot.publish_frame(rgb, c2w, depth=depth_mm)   # stamped alike
        answer = robot.select(method="agile")          # the Select response message
"""

from __future__ import annotations

import itertools
import json
import os
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from agilegs.schemas.requests import new_request_id

from .._retry import RETRY_WINDOW, backoff
from . import messages as m
from .frames import (
    axes_of_frame,
    camera_info_msg,
    depth_image_msg,
    matrix_to_pose_msg,
    rgb_image_msg,
)
from .keys import INPUT_TOPICS, OUTPUT_TOPICS, SERVICES, Namespace

__all__ = ["Ros2Robot", "request_header_attachment"]

_CLIENT_GUID = int.from_bytes(os.urandom(8), "little")


def request_header_attachment(client_guid: int, sequence: int) -> bytes:
    """The attachment zenoh-bridge-ros2dds (0.11 and later) puts on a service query: ``rqh``
    then the 16-byte request id (8 bytes of client GUID, 8 of sequence number, here
    little-endian) and a little-endian flag."""
    return (b"rqh" + client_guid.to_bytes(8, "little") + sequence.to_bytes(8, "little")
            + b"\x01")


class Ros2Robot:
    """Publishes a robot's topics and calls agilegs' services under ``namespace``.

    Args:
        namespace: the namespace the server serves (``agilegs serve --ros2 NAMESPACE``).
        connect: Zenoh endpoints to connect to (the server's, or a router's).
        session: an open Zenoh session to use instead (not closed by :meth:`close`).
        credentials: the server's ``<state-dir>/zenoh/client.json`` (a server with a token
            requires its Zenoh user and password; its endpoints serve when ``connect`` is
            empty).
        world_frame: the ``header.frame_id`` of the poses published.
        camera_frame: the frame the camera poses are of (its name sets its axes).
        timeout: seconds a service call may take.
        wait: seconds the first message on a topic (or call of a service) waits for agilegs
            to be reachable on its key, as a ROS 2 publisher waits for its subscriber.
        retry_window: seconds a service call answered with a ``Status.retry_after`` (a fleet
            handing the session over) is sent again, with its ``request_id`` and backoff, as
            the SDK's clients do (:mod:`agilegs.client._retry`); 0: never.
    """

    def __init__(self, namespace: str, connect: Sequence[str] = (), *, session: Any = None,
                 world_frame: str = "map", camera_frame: str = "camera_optical_frame",
                 timeout: float = 120.0, wait: float = 10.0,
                 credentials: str | Path | None = None,
                 retry_window: float = RETRY_WINDOW) -> None:
        self.ns = Namespace(namespace)
        self.retry_window = retry_window
        self.world_frame = world_frame
        self.camera_frame = camera_frame
        self.timeout = timeout
        self.wait = wait
        self._own = session is None
        if session is None:
            from agilegs.client.zenoh_rpc import credentials as zenoh_credentials
            from agilegs.client.zenoh_rpc import open_session, read_credentials

            extra = None
            if credentials is not None:
                saved = read_credentials(credentials)
                connect = connect or saved["connect"]
                extra = zenoh_credentials(user=saved["user"], password=saved["password"],
                                          root_ca=saved.get("tls_root_ca"))
            session = open_session((), connect, extra=extra)
        self.session = session
        self._seq = itertools.count(1)
        self._subs: list[Any] = []
        self._declared: dict[str, Any] = {}
        self.token = ""

    def close(self) -> None:
        for entity in [*self._subs, *self._declared.values()]:
            entity.undeclare()
        self._subs.clear()
        self._declared.clear()
        if self._own:
            self.session.close()

    def __enter__(self) -> Ros2Robot:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ raw
    def put(self, leaf: str, payload: bytes) -> None:
        """Put raw bytes on the namespace's topic ``leaf`` (as the bridge forwards a
        publication: the CDR bytes alone)."""
        if leaf not in INPUT_TOPICS:
            raise ValueError(f"{leaf!r} is no topic agilegs subscribes to")
        self._entity(leaf).put(payload)

    def publish(self, leaf: str, message: Any) -> None:
        """Publish ``message`` (of the topic's type) on ``leaf`` as CDR."""
        self.put(leaf, m.serialize(message, INPUT_TOPICS[leaf]))

    def call_raw(self, leaf: str, payload: bytes) -> bytes:
        """The reply payload of a service query carrying ``payload`` (TimeoutError if none
        came)."""
        if leaf not in SERVICES:
            raise ValueError(f"{leaf!r} is no agilegs service")
        attachment = request_header_attachment(_CLIENT_GUID, next(self._seq))
        for reply in self._entity(leaf).get(payload=payload, attachment=attachment):
            if reply.ok is not None:
                return bytes(reply.ok.payload.to_bytes())
            raise RuntimeError(f"{leaf}: error reply {reply.err.payload.to_bytes()!r}")
        raise TimeoutError(f"{leaf}: no reply within {self.timeout} s")

    def _entity(self, leaf: str) -> Any:
        """The publisher (topic) or querier (service) of ``leaf``, declared on first use and
        given up to ``wait`` seconds to match agilegs' subscriber or queryable."""
        import zenoh

        entity = self._declared.get(leaf)
        if entity is None:
            key = self.ns.key(leaf)
            if leaf in SERVICES:
                entity = self.session.declare_querier(key, timeout=self.timeout)
            else:
                entity = self.session.declare_publisher(
                    key, congestion_control=zenoh.CongestionControl.BLOCK)
            self._declared[leaf] = entity
            deadline = time.monotonic() + self.wait
            while not entity.matching_status.matching and time.monotonic() < deadline:
                time.sleep(0.01)
        return entity

    def call(self, leaf: str, **fields: Any) -> Any:
        """Call the service ``leaf`` with ``fields`` (the rest take their zero values) and
        return the response message; sent again while its status says ``retry_after`` and
        ``retry_window`` seconds are not spent (a service with a ``request_id`` field gets a
        fresh one unless given, and every retry carries it: applied once)."""
        service = SERVICES[leaf]
        if "request_id" in m.field_names(m.request_type(service)):
            fields.setdefault("request_id", new_request_id())
        payload = m.serialize(m.msg(m.request_type(service), **fields))
        deadline = time.monotonic() + self.retry_window
        attempt = 0
        while True:
            resp = m.deserialize(self.call_raw(leaf, payload), m.response_type(service))
            hint = float(resp.status.retry_after)
            delay = backoff(attempt, hint)
            if hint <= 0 or time.monotonic() + delay > deadline:
                return resp
            time.sleep(delay)
            attempt += 1

    def subscribe(self, leaf: str, callback: Callable[[Any], None]) -> None:
        """Call ``callback`` with each message agilegs publishes on ``leaf`` (decision,
        shortlist, errors), decoded."""
        typename = OUTPUT_TOPICS[leaf]
        self._subs.append(self.session.declare_subscriber(
            self.ns.key(leaf), lambda s: callback(m.deserialize(s.payload.to_bytes(),
                                                                typename))))

    # ------------------------------------------------------------------ topics
    def _stamp(self, stamp_ns: int | None) -> Any:
        return m.stamp_msg(stamp_ns if stamp_ns is not None else 0, ns=True)

    def _header(self, stamp_ns: int | None) -> Any:
        return m.msg("std_msgs/msg/Header", stamp=self._stamp(stamp_ns),
                     frame_id=self.world_frame)

    def publish_camera_info(self, intrinsics: Any, stamp_ns: int | None = None) -> None:
        """The camera (agilegs intrinsics, an object or a dict) on ``camera_info``."""
        self.publish("camera_info", camera_info_msg(intrinsics, frame_id=self.camera_frame,
                                                    stamp=self._stamp(stamp_ns)))

    def publish_candidates(self, poses: Any, stamp_ns: int | None = None) -> None:
        """The pool: camera-to-world matrices [D, 4, 4] (OpenCV axes) as a PoseArray of the
        camera frame's poses."""
        axes = axes_of_frame(self.camera_frame)
        self.publish("candidates", m.msg(m.POSE_ARRAY, header=self._header(stamp_ns), poses=[
            matrix_to_pose_msg(p, axes) for p in np.asarray(poses, dtype=np.float64)]))

    def publish_frame(self, rgb: Any, c2w: Any, *, depth: Any = None, stamp_ns: int = 1,
                      encoding: str = "rgb8", depth_encoding: str | None = None) -> None:
        """A frame: the depth image (uint16 mm as 16UC1, float metres as 32FC1), the colour
        image (RGB uint8 [H, W, 3] in ``encoding``) and the camera pose (camera-to-world
        [4, 4], OpenCV axes), all stamped ``stamp_ns``."""
        stamp = self._stamp(stamp_ns)
        if depth is not None:
            d = np.asarray(depth)
            enc = depth_encoding or ("16UC1" if d.dtype == np.uint16 else "32FC1")
            self.publish("depth", depth_image_msg(d, encoding=enc, frame_id=self.camera_frame,
                                                  stamp=stamp))
        self.publish("image", rgb_image_msg(rgb, encoding=encoding,
                                            frame_id=self.camera_frame, stamp=stamp))
        self.publish("camera_pose", m.msg(
            m.POSE_STAMPED, header=self._header(stamp_ns),
            pose=matrix_to_pose_msg(c2w, axes_of_frame(self.camera_frame))))

    # ------------------------------------------------------------------ services
    def create_session(self, *, bounds: tuple[Sequence[float], Sequence[float]],
                       session: str = "", intrinsics: Any = None, expect_depth: bool = False,
                       options: dict[str, Any] | None = None) -> Any:
        """``create_session``: the camera from ``intrinsics`` (None: the last
        ``camera_info`` published), scene ``bounds`` (min, max); the response message."""
        lo, hi = bounds
        fields: dict[str, Any] = {
            "token": self.token, "session": session, "world_frame": self.world_frame,
            "camera_frame": self.camera_frame, "expect_depth": expect_depth,
            "bounds_min": _point(lo), "bounds_max": _point(hi),
            "options_json": json.dumps(options) if options else ""}
        if intrinsics is not None:
            fields["camera_info"] = camera_info_msg(intrinsics, frame_id=self.camera_frame)
        return self.call("create_session", **fields)

    def open_session(self, session: str, *, expect_depth: bool = False) -> Any:
        """``open_session``: bind the namespace to ``session``; the response message."""
        return self.call("open_session", token=self.token, session=session,
                         world_frame=self.world_frame, camera_frame=self.camera_frame,
                         expect_depth=expect_depth)

    def select(self, *, method: str = "", shortlist_size: int = 0, embodied_k: int = 0,
               current_pose: Any = None, commit: bool = False,
               config: Mapping[str, Any] | None = None, targets: Any = None) -> Any:
        """``select``; the response message (``chosen``, ``shortlist``, ``status``).
        ``config``: SelectConfig fields (e.g. ``{"objective": "target"}``); ``targets``: the
        target objective's camera-to-world matrices [T, 4, 4]."""
        fields: dict[str, Any] = {"token": self.token, "method": method,
                                  "shortlist_size": shortlist_size, "embodied_k": embodied_k,
                                  "commit": commit}
        axes = axes_of_frame(self.camera_frame)
        if current_pose is not None:
            fields["use_current_pose"] = True
            fields["current_pose"] = matrix_to_pose_msg(current_pose, axes)
        if config:
            fields["config_json"] = json.dumps(dict(config))
        if targets is not None:
            fields["targets"] = [matrix_to_pose_msg(t, axes) for t in targets]
        return self.call("select", **fields)


def _point(v: Sequence[float]) -> Any:
    return m.msg("geometry_msgs/msg/Point", x=float(v[0]), y=float(v[1]), z=float(v[2]))
