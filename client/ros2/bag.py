"""Posed frames from a rosbag2 (MCAP or sqlite3), and bags written from frames, with
``rosbags`` (no ROS install).

A bag is a folder with ``metadata.yaml`` (any storage), or a single ``.mcap`` / ``.db3``
file. :func:`read_bag` turns it into :class:`BagFrame` objects, one per colour image:

* **image**: a ``sensor_msgs/Image`` (rgb8, bgr8, rgba8, bgra8, mono8) or
  ``sensor_msgs/CompressedImage`` topic;
* **camera_info**: the ``sensor_msgs/CameraInfo`` topic; each frame takes the last one at
  or before its stamp (the first one for frames before it);
* **depth** (optional): a ``sensor_msgs/Image`` in ``16UC1`` / ``mono16`` (millimetres) or
  ``32FC1`` (metres), registered to the colour image (the same size: a RealSense's
  ``aligned_depth_to_color``); each frame takes the depth image with the nearest stamp
  within ``sync_s``;
* **pose**: either the TF tree (``/tf`` and ``/tf_static``: the chain from ``world_frame``
  to the image's ``header.frame_id``, dynamic transforms interpolated at the image stamp,
  linearly in position and spherically in rotation), or a ``geometry_msgs/PoseStamped``
  topic (interpolated the same way) giving the pose of ``camera_frame``.

Frames are in the image's ``header.stamp`` order; a frame whose pose cannot be had (before
the first or after the last pose, a gap over ``max_gap_s``, a TF chain that does not reach
the world frame) is left out and counted in the log. The conventions are those of
:mod:`agilegs.client.ros2.frames`: a camera frame named ``*_optical_frame`` has OpenCV axes,
any other is a REP-103 body frame and is rotated.

:class:`BagTopics` chooses the topics; what it leaves unset is found by type (a unique
candidate; among several depth topics one whose name holds ``aligned``). It parses from
``image=/cam/color/image_raw,pose=tf,world=map`` (:meth:`BagTopics.parse`).
"""

from __future__ import annotations

import logging
import math
from bisect import bisect_left
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from . import messages as m
from .frames import (
    axes_of_frame,
    camera_info_msg,
    compressed_to_rgb,
    depth_image_msg,
    depth_to_array,
    image_to_rgb,
    intrinsics_of,
    matrix_to_pose_msg,
    pose_msg_to_matrix,
    rgb_image_msg,
)

__all__ = ["BagFrame", "BagTopics", "is_bag", "observations_from_bag", "read_bag",
           "write_bag"]

log = logging.getLogger(__name__)

_TF, _TF_STATIC = "/tf", "/tf_static"


@dataclass(frozen=True)
class BagTopics:
    """Which topics of a bag make the frames (None: found by type; see the module docstring).

    Attributes:
        image: the colour image topic.
        depth: the depth image topic ("" or "none": no depth).
        camera_info: the camera info topic.
        pose: ``tf`` (the TF tree), or a PoseStamped topic (None: ``tf`` when the bag has
            ``/tf`` or ``/tf_static``, else the only PoseStamped topic).
        world_frame: the frame of the poses (TF: None is the root of the camera's tree).
        camera_frame: the frame the poses are of (None: the image's ``header.frame_id``).
        sync_s: largest stamp difference of a depth image to its colour image (s).
        max_gap_s: largest gap between two poses interpolated across (s).
    """

    image: str | None = None
    depth: str | None = None
    camera_info: str | None = None
    pose: str | None = None
    world_frame: str | None = None
    camera_frame: str | None = None
    sync_s: float = 0.02
    max_gap_s: float = 0.5

    _ALIASES = {"world": "world_frame", "camera": "camera_frame", "info": "camera_info"}

    @classmethod
    def parse(cls, spec: str) -> BagTopics:
        """From ``key=value`` pairs, comma-separated (keys: the attributes, or ``world``,
        ``camera``, ``info``); ValueError naming an unknown key or a bad number."""
        out: dict[str, Any] = {}
        names = {f.name for f in fields(cls)}
        for part in (p.strip() for p in spec.split(",") if p.strip()):
            key, sep, value = part.partition("=")
            key = cls._ALIASES.get(key.strip(), key.strip())
            if not sep or key not in names:
                raise ValueError(f"bag topics {part!r}: expected key=value with a key among "
                                 f"{sorted(names | set(cls._ALIASES))}")
            if key in ("sync_s", "max_gap_s"):
                try:
                    out[key] = float(value)
                except ValueError:
                    raise ValueError(f"bag topics {key}: not a number: {value!r}") from None
            else:
                out[key] = value.strip()
        return cls(**out)

    def describe(self) -> str:
        """The non-default settings as ``key=value,...`` (what :meth:`parse` reads)."""
        default = BagTopics()
        return ",".join(f"{f.name}={getattr(self, f.name)}" for f in fields(self)
                        if getattr(self, f.name) != getattr(default, f.name))


@dataclass
class BagFrame:
    """One posed frame of a bag.

    Attributes:
        stamp_ns: the colour image's ``header.stamp`` (ns).
        rgb: the image, RGB uint8 [H, W, 3].
        intrinsics: agilegs intrinsics (fx, fy, cx, cy, width, height; pixel centres +0.5).
        c2w: camera-to-world [4, 4] float64 with OpenCV axes, in the world frame.
        depth: [H, W] uint16 (times ``depth_scale`` metres) or float32 metres, 0 where
            unknown, or None.
        depth_scale: metres per depth unit (0.001 for 16UC1, 1 for 32FC1).
        frame_id: the image's ``header.frame_id``.
    """

    stamp_ns: int
    rgb: np.ndarray
    intrinsics: dict[str, Any]
    c2w: np.ndarray
    depth: np.ndarray | None = None
    depth_scale: float = 1.0
    frame_id: str = ""

    def depth_m(self) -> np.ndarray | None:
        """The depth in metres, float32 [H, W] (0 where unknown), or None."""
        if self.depth is None:
            return None
        return (self.depth.astype(np.float64) * self.depth_scale).astype(np.float32)


# ----------------------------------------------------------------------------- poses in time
def _slerp(q0: np.ndarray, q1: np.ndarray, a: float) -> np.ndarray:
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + a * (q1 - q0)
    else:
        th = math.acos(d)
        q = (math.sin((1 - a) * th) * q0 + math.sin(a * th) * q1) / math.sin(th)
    return q / np.linalg.norm(q)


@dataclass
class _Track:
    """A rigid transform over time: stamps (ns, sorted), positions [3], quaternions xyzw."""

    stamps: list[int] = field(default_factory=list)
    samples: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)

    def add(self, t: int, p: np.ndarray, q: np.ndarray) -> None:
        i = bisect_left(self.stamps, t)
        if i < len(self.stamps) and self.stamps[i] == t:
            self.samples[i] = (p, q)
            return
        self.stamps.insert(i, t)
        self.samples.insert(i, (p, q))

    def at(self, t: int, max_gap_ns: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The transform at ``t``: a sample stamped ``t`` exactly, else interpolated between
        its neighbours (None outside the track or across a gap over ``max_gap_ns``)."""
        i = bisect_left(self.stamps, t)
        if i < len(self.stamps) and self.stamps[i] == t:
            return self.samples[i]
        if i == 0 or i == len(self.stamps):
            return None
        t0, t1 = self.stamps[i - 1], self.stamps[i]
        if t1 - t0 > max_gap_ns:
            return None
        a = (t - t0) / (t1 - t0)
        (p0, q0), (p1, q1) = self.samples[i - 1], self.samples[i]
        return p0 + a * (p1 - p0), _slerp(q0, q1, a)


def _pq(transform_or_pose: Any) -> tuple[np.ndarray, np.ndarray]:
    """``(position [3], quaternion xyzw [4])`` of a Transform or a Pose message."""
    is_tf = hasattr(transform_or_pose, "translation")
    t = transform_or_pose.translation if is_tf else transform_or_pose.position
    r = transform_or_pose.rotation if is_tf else transform_or_pose.orientation
    q = np.array([r.x, r.y, r.z, r.w], dtype=np.float64)
    return np.array([t.x, t.y, t.z], dtype=np.float64), q


def _matrix(p: np.ndarray, q: np.ndarray, what: str, axes: Any = "optical") -> np.ndarray:
    """[4, 4] of a position and a quaternion (``optical``: as it is, a plain transform)."""
    pose = m.msg("geometry_msgs/msg/Pose",
                 position=m.msg("geometry_msgs/msg/Point", x=p[0], y=p[1], z=p[2]),
                 orientation=m.msg("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2],
                                   w=q[3]))
    return pose_msg_to_matrix(pose, axes, what)


class _TfTree:
    """Static and dynamic TF edges (child -> parent) from TFMessage objects."""

    def __init__(self) -> None:
        self.static: dict[str, tuple[str, np.ndarray]] = {}
        self.dynamic: dict[str, tuple[str, _Track]] = {}

    def add(self, tf_msg: Any, static: bool) -> None:
        for ts in tf_msg.transforms:
            child, parent = ts.child_frame_id.strip("/"), ts.header.frame_id.strip("/")
            p, q = _pq(ts.transform)
            if static:
                self.static[child] = (parent, _matrix(p, q, f"tf_static {parent}->{child}"))
            else:
                track = self.dynamic.setdefault(child, (parent, _Track()))[1]
                track.add(m.stamp_ns(ts.header.stamp), p, q)

    def parent(self, frame: str) -> str | None:
        if frame in self.dynamic:
            return self.dynamic[frame][0]
        return self.static[frame][0] if frame in self.static else None

    def root(self, frame: str) -> str:
        seen = {frame}
        while (up := self.parent(frame)) is not None and up not in seen:
            seen.add(up)
            frame = up
        return frame

    def lookup(self, world: str, frame: str, t: int, max_gap_ns: int) -> np.ndarray | None:
        """``T_world_frame`` [4, 4] at ``t``, or None when the chain breaks at ``t``."""
        out = np.eye(4)
        seen = set()
        while frame != world:
            if frame in seen:
                return None
            seen.add(frame)
            if frame in self.dynamic:
                parent, track = self.dynamic[frame]
                got = track.at(t, max_gap_ns)
                if got is None:
                    return None
                edge = _matrix(got[0], got[1], f"tf {parent}->{frame}")
            elif frame in self.static:
                parent, edge = self.static[frame]
            else:
                return None
            out = edge @ out
            frame = parent
        return out


# ----------------------------------------------------------------------------- reading
def is_bag(path: str | Path) -> bool:
    """A rosbag2 folder (with ``metadata.yaml``) or an ``.mcap`` / ``.db3`` file."""
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").is_file()
    return p.is_file() and p.suffix.lower() in (".mcap", ".db3")


def _choose(kind: str, given: str | None, topics: dict[str, str], types: Sequence[str],
            prefer: str | None = None, required: bool = True) -> str | None:
    if given is not None:
        if given in ("", "none"):
            return None
        if given not in topics:
            raise ValueError(f"bag has no topic {given!r} ({kind}); its topics: "
                             f"{sorted(topics)}")
        if topics[given] not in types:
            raise ValueError(f"bag topic {given!r} ({kind}) is a {topics[given]}, not "
                             f"{' or '.join(types)}")
        return given
    found = sorted(t for t, ty in topics.items() if ty in types)
    if prefer is not None and len(found) > 1:
        found = [t for t in found if prefer in t] or found
    if len(found) == 1:
        return found[0]
    if not found and not required:
        return None
    raise ValueError(f"bag: {'no' if not found else 'several'} {kind} topics "
                     f"({' or '.join(types)}){': ' + ', '.join(found) if found else ''}; "
                     f"name one ({kind}=TOPIC)")


def _image_kinds(reader: Any) -> dict[str, str]:
    """``colour`` or ``depth`` of every image topic, by its first message's encoding
    (a CompressedImage is colour)."""
    out: dict[str, str] = {}
    for conn in reader.connections:
        if conn.topic in out or conn.msgtype not in (m.IMAGE, m.COMPRESSED_IMAGE):
            continue
        out[conn.topic] = "colour"
        if conn.msgtype == m.IMAGE:
            for _c, _t, raw in reader.messages(connections=[conn]):
                enc = reader.deserialize(raw, conn.msgtype).encoding
                out[conn.topic] = "depth" if enc in ("16UC1", "mono16", "32FC1") else "colour"
                break
    return out


def read_bag(path: str | Path, topics: BagTopics | None = None, *,
             max_frames: int | None = None) -> list[BagFrame]:
    """The posed frames of the bag at ``path`` (see the module docstring); at most
    ``max_frames`` of them, evenly spaced over the colour images, are decoded.

    Raises:
        FileNotFoundError: no bag there.
        ValueError: the topics cannot be chosen or read, naming the topic.
    """
    from rosbags.highlevel import AnyReader

    tp = topics or BagTopics()
    p = Path(path)
    if not is_bag(p):
        raise FileNotFoundError(f"{p}: no rosbag2 (a folder with metadata.yaml, or an .mcap "
                                "or .db3 file)")
    with AnyReader([p], default_typestore=m.typestore()) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        kinds = _image_kinds(reader)
        image = tp.image if tp.image is not None else _choose(
            "image", None, {t: types[t] for t, k in kinds.items() if k == "colour"},
            (m.IMAGE, m.COMPRESSED_IMAGE), "color")
        image = _choose("image", image, types, (m.IMAGE, m.COMPRESSED_IMAGE))
        assert image is not None
        info = _choose("camera_info", tp.camera_info, types, (m.CAMERA_INFO,),
                       image.rsplit("/", 1)[0])
        if tp.depth is None:
            depth = _choose("depth", None, {t: types[t] for t, k in kinds.items()
                                            if k == "depth" and t != image}, (m.IMAGE,),
                            "aligned", required=False)
        else:
            depth = _choose("depth", tp.depth, types, (m.IMAGE,))
        pose = tp.pose
        if pose is None:
            pose = "tf" if (_TF in types or _TF_STATIC in types) else _choose(
                "pose", None, types, (m.POSE_STAMPED,))
        elif pose != "tf":
            _choose("pose", pose, types, (m.POSE_STAMPED,))
        return _read_frames(reader, tp, image, info, depth, pose, max_frames)


def _read_frames(reader: Any, tp: BagTopics, image: str, info: str | None, depth: str | None,
                 pose: str | None, max_frames: int | None) -> list[BagFrame]:
    conns = {c.topic: c for c in reader.connections}
    n_images = conns[image].msgcount
    keep = None
    if max_frames is not None and n_images > max_frames:
        keep = {int(math.floor((i + 0.5) * n_images / max_frames)) for i in range(max_frames)}
    tree = _TfTree()
    pose_track = _Track()
    pose_frame = ""
    infos: list[tuple[int, dict[str, Any]]] = []
    depths: list[tuple[int, np.ndarray, float]] = []
    colour: list[tuple[int, np.ndarray, str]] = []
    wanted = [conns[t] for t in (image, info, depth) if t] + (
        [conns[t] for t in (_TF, _TF_STATIC) if t in conns] if pose == "tf" else
        [conns[pose]] if pose else [])
    i_image = -1
    for conn, _t, raw in reader.messages(connections=wanted):
        topic = conn.topic
        if topic == image:
            i_image += 1
            if keep is not None and i_image not in keep:
                continue
        msg = reader.deserialize(raw, conn.msgtype)
        try:
            if topic == image:
                rgb = (compressed_to_rgb(msg, topic) if conn.msgtype == m.COMPRESSED_IMAGE
                       else image_to_rgb(msg, topic))
                colour.append((m.stamp_ns(msg.header.stamp), rgb, msg.header.frame_id))
            elif topic == info:
                infos.append((m.stamp_ns(msg.header.stamp), intrinsics_of(msg, topic)))
            elif topic == depth:
                d, scale = depth_to_array(msg, topic)
                depths.append((m.stamp_ns(msg.header.stamp), d, scale))
            elif topic in (_TF, _TF_STATIC):
                tree.add(msg, static=topic == _TF_STATIC)
            else:
                pose_frame = pose_frame or msg.header.frame_id
                pos, q = _pq(msg.pose)
                pose_track.add(m.stamp_ns(msg.header.stamp), pos, q)
        except ValueError as exc:
            raise ValueError(f"bag topic {topic}: {exc}") from None
    if not infos:
        raise ValueError(f"bag: no camera info ({info or 'no CameraInfo topic'})")
    colour.sort(key=lambda c: c[0])
    infos.sort(key=lambda c: c[0])
    depths.sort(key=lambda c: c[0])
    return _assemble(tp, colour, infos, depths, tree, pose_track, pose, depth)


def _assemble(tp: BagTopics, colour: list[tuple[int, np.ndarray, str]],
              infos: list[tuple[int, dict[str, Any]]], depths: list[tuple[int, np.ndarray, float]],
              tree: _TfTree, track: _Track, pose: str | None, depth: str | None
              ) -> list[BagFrame]:
    gap = int(tp.max_gap_s * 1e9)
    sync = int(tp.sync_s * 1e9)
    info_t = [t for t, _ in infos]
    depth_t = [t for t, _, _ in depths]
    out: list[BagFrame] = []
    skipped: dict[str, int] = {}
    for t, rgb, frame_id in colour:
        cam = tp.camera_frame or frame_id
        if pose == "tf":
            world = tp.world_frame or tree.root(cam.strip("/"))
            t_wc = tree.lookup(world.strip("/"), cam.strip("/"), t, gap)
            c2w = None if t_wc is None else (
                t_wc if axes_of_frame(cam) == "optical" else _body_to_optical(t_wc))
        else:
            got = track.at(t, gap)
            c2w = None if got is None else _matrix(got[0], got[1], "pose", axes_of_frame(cam))
        if c2w is None:
            skipped["no pose"] = skipped.get("no pose", 0) + 1
            continue
        k = infos[max(0, bisect_left(info_t, t + 1) - 1)][1]
        if (k["height"], k["width"]) != rgb.shape[:2]:
            raise ValueError(f"bag: the camera info is {k['width']}x{k['height']} but the "
                             f"image at {t} ns is {rgb.shape[1]}x{rgb.shape[0]}")
        frame = BagFrame(stamp_ns=t, rgb=rgb, intrinsics=k, c2w=c2w, frame_id=frame_id)
        if depth is not None:
            j = _nearest(depth_t, t)
            if j is None or abs(depth_t[j] - t) > sync:
                skipped["no depth within sync_s"] = skipped.get("no depth within sync_s", 0) + 1
            elif depths[j][1].shape != rgb.shape[:2]:
                raise ValueError(f"bag topic {depth}: depth {depths[j][1].shape} is not "
                                 f"registered to the colour image {rgb.shape[:2]} (use the "
                                 "aligned depth topic)")
            else:
                frame.depth, frame.depth_scale = depths[j][1], depths[j][2]
        out.append(frame)
    if skipped:
        log.warning("bag: %d of %d frames kept (%s)", len(out), len(colour),
                    ", ".join(f"{v} {k}" for k, v in skipped.items()))
    return out


def _nearest(stamps: list[int], t: int) -> int | None:
    if not stamps:
        return None
    i = bisect_left(stamps, t)
    near = [j for j in (i - 1, i) if 0 <= j < len(stamps)]
    return min(near, key=lambda j: abs(stamps[j] - t))


def _body_to_optical(t_wb: np.ndarray) -> np.ndarray:
    from .frames import R_BODY_OPTICAL

    out = t_wb.copy()
    out[:3, :3] = t_wb[:3, :3] @ R_BODY_OPTICAL
    return out


def observations_from_bag(path: str | Path, topics: BagTopics | None = None, *,
                          max_frames: int | None = None,
                          image_encoding: str = "png") -> list[Any]:
    """The bag's frames as :class:`~agilegs.schemas.ObservationIn` (each at its pose, with
    its intrinsics, image and depth), ready for ``client.add_observations`` (at most 256
    per call)."""
    from agilegs.schemas import Intrinsics, ObservationIn

    return [ObservationIn.from_numpy(
        f.c2w, image=f.rgb, depth=f.depth, depth_scale=f.depth_scale,
        intrinsics=Intrinsics(**f.intrinsics), image_encoding=image_encoding)  # type: ignore[arg-type]
        for f in read_bag(path, topics, max_frames=max_frames)]


# ----------------------------------------------------------------------------- writing
def write_bag(path: str | Path, frames: Iterable[BagFrame], *, storage: str = "mcap",
              poses: str = "tf", world_frame: str = "map",
              camera_frame: str = "camera_color_optical_frame",
              prefix: str = "/camera") -> Path:
    """Write ``frames`` as a rosbag2 folder at ``path`` (``storage``: ``mcap`` or
    ``sqlite3``): ``<prefix>/color/image_raw`` (rgb8), ``<prefix>/color/camera_info``,
    ``<prefix>/aligned_depth_to_color/image_raw`` (16UC1 when the depth is uint16, else
    32FC1; frames with depth only) and the poses, ``poses="tf"``: ``/tf`` (``world_frame``
    -> ``camera_link``, the body frame) plus ``/tf_static`` (``camera_link`` ->
    ``camera_frame``, the optical rotation), or ``poses="pose"``: ``<prefix>/pose``
    (PoseStamped of ``camera_frame`` in ``world_frame``). Each message is stamped with its
    frame's ``stamp_ns``."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
    store = m.typestore()
    frames = list(frames)
    out = Path(path)
    names = {"image": f"{prefix}/color/image_raw", "info": f"{prefix}/color/camera_info",
             "depth": f"{prefix}/aligned_depth_to_color/image_raw", "pose": f"{prefix}/pose"}
    with Writer(out, version=9, storage_plugin=plugin) as w:
        conn = {"image": w.add_connection(names["image"], m.IMAGE, typestore=store),
                "info": w.add_connection(names["info"], m.CAMERA_INFO, typestore=store)}
        if any(f.depth is not None for f in frames):
            conn["depth"] = w.add_connection(names["depth"], m.IMAGE, typestore=store)
        if poses == "tf":
            conn["tf"] = w.add_connection(_TF, m.TF_MESSAGE, typestore=store)
            conn["static"] = w.add_connection(_TF_STATIC, m.TF_MESSAGE, typestore=store)
            static = _tf_msg([("camera_link", camera_frame, np.zeros(3),
                               np.array([-0.5, 0.5, -0.5, 0.5]), 0)])
            t0 = min((f.stamp_ns for f in frames), default=0)
            w.write(conn["static"], t0, m.serialize(static, m.TF_MESSAGE))
        else:
            conn["pose"] = w.add_connection(names["pose"], m.POSE_STAMPED, typestore=store)
        for f in frames:
            stamp = m.stamp_msg(f.stamp_ns, ns=True)
            _write(w, conn["info"], f.stamp_ns,
                   camera_info_msg(f.intrinsics, frame_id=camera_frame, stamp=stamp))
            _write(w, conn["image"], f.stamp_ns,
                   rgb_image_msg(f.rgb, frame_id=camera_frame, stamp=stamp))
            if f.depth is not None:
                enc = "16UC1" if f.depth.dtype == np.uint16 else "32FC1"
                _write(w, conn["depth"], f.stamp_ns,
                       depth_image_msg(f.depth, encoding=enc, frame_id=camera_frame,
                                       stamp=stamp))
            if poses == "tf":
                body = matrix_to_pose_msg(f.c2w, "body")
                p, q = _pq(body)
                _write(w, conn["tf"], f.stamp_ns,
                       _tf_msg([(world_frame, "camera_link", p, q, f.stamp_ns)]))
            else:
                _write(w, conn["pose"], f.stamp_ns, m.msg(
                    m.POSE_STAMPED, header=m.msg("std_msgs/msg/Header", stamp=stamp,
                                                 frame_id=world_frame),
                    pose=matrix_to_pose_msg(f.c2w, axes_of_frame(camera_frame))))
    return out


def _write(writer: Any, conn: Any, t: int, message: Any) -> None:
    writer.write(conn, t, m.serialize(message))


def _tf_msg(edges: Sequence[tuple[str, str, np.ndarray, np.ndarray, int]]) -> Any:
    vec = lambda v: m.msg("geometry_msgs/msg/Vector3", x=float(v[0]), y=float(v[1]),  # noqa: E731
                          z=float(v[2]))
    return m.msg(m.TF_MESSAGE, transforms=[m.msg(
        "geometry_msgs/msg/TransformStamped",
        header=m.msg("std_msgs/msg/Header", stamp=m.stamp_msg(t, ns=True), frame_id=parent),
        child_frame_id=child,
        transform=m.msg("geometry_msgs/msg/Transform", translation=vec(p),
                        rotation=m.msg("geometry_msgs/msg/Quaternion", x=float(q[0]),
                                       y=float(q[1]), z=float(q[2]), w=float(q[3]))))
        for parent, child, p, q, t in edges])

