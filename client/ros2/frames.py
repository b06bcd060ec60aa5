"""ROS 2 geometry and sensor messages <-> agilegs' conventions (numpy and wire dicts).

Frames (REP-103, REP-105):

* agilegs' poses are camera-to-world with OpenCV camera axes (x right, y down, z forward).
  A ROS camera's *optical* frame (by convention named ``*_optical_frame``, or ``*_optical``)
  has exactly those axes, so a pose of an optical frame is taken as it is.
* Any other camera frame has REP-103 *body* axes (x forward, y left, z up). Its pose
  ``T_world_body`` is turned into the optical frame's pose by the fixed rotation
  ``T_world_optical = T_world_body · R_body_optical``, where ``R_body_optical`` (the static
  transform ``camera_link -> camera_optical_frame``, roll -90°, yaw -90°) is
  :data:`R_BODY_OPTICAL`; a decision going back is rotated by its inverse. On quaternions
  (x, y, z, w) this is ``q_optical = q_body ⊗ Q_BODY_OPTICAL``, which keeps the norm, so a
  non-unit quaternion is still refused by the server's checks as over HTTP.
* ``header.frame_id`` of a pose message names the world frame it is given in.

Cameras: ``sensor_msgs/CameraInfo`` puts the centre of pixel (0, 0) at (0, 0) (OpenCV);
agilegs at (0.5, 0.5) (see ``docs/conventions.md``), so ``cx = K[2] + 0.5`` and
``cy = K[5] + 0.5``. The images a service receives are rectified, so the intrinsics are the
projection matrix ``P``'s (``K``'s when ``P`` is all zero); binning and a region of interest
are refused.

Images: ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8`` and ``mono8`` colour images (alpha dropped,
grey repeated), with any row ``step`` and either byte order; depth as ``16UC1`` (or
``mono16``) millimetres, kept as uint16 with ``depth_scale`` 0.001, or ``32FC1`` metres,
where NaN and infinities (REP-118: no return, too near, too far) become 0, agilegs' "no
depth". Scene units are metres.

Each refusal is a :class:`FieldError` naming the message field (``image.encoding``,
``camera_info.k``).
"""

from __future__ import annotations

import io
import math
from typing import Any, Literal

import numpy as np

from .messages import msg

__all__ = [
    "COLOR_ENCODINGS",
    "DEPTH_ENCODINGS",
    "Q_BODY_OPTICAL",
    "R_BODY_OPTICAL",
    "Axes",
    "FieldError",
    "axes_of_frame",
    "camera_info_msg",
    "compressed_to_rgb",
    "depth_image_msg",
    "depth_to_array",
    "image_to_rgb",
    "intrinsics_of",
    "matrix_to_pose_msg",
    "pose_msg_to_matrix",
    "pose_msg_to_wire",
    "quaternion_multiply",
    "rgb_image_msg",
]

Axes = Literal["optical", "body"]

R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""The optical frame's axes in the body frame (columns: optical x = -body y, optical y =
-body z, optical z = body x)."""
Q_BODY_OPTICAL = (-0.5, 0.5, -0.5, 0.5)
""":data:`R_BODY_OPTICAL` as a quaternion (x, y, z, w)."""

COLOR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8")
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")
MM = 0.001


class FieldError(ValueError):
    """A message field that agilegs cannot take; ``field`` names it."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


def axes_of_frame(frame_id: str) -> Axes:
    """``optical`` for a frame named ``*_optical_frame`` or ``*_optical`` (or ``optical``),
    ``body`` for any other."""
    name = frame_id.strip().rstrip("/").rsplit("/", 1)[-1]
    if name == "optical" or name.endswith(("_optical_frame", "_optical")):
        return "optical"
    return "body"


# ----------------------------------------------------------------------------- poses
def quaternion_multiply(a: Any, b: Any) -> tuple[float, float, float, float]:
    """The Hamilton product ``a ⊗ b`` of quaternions (x, y, z, w): ``R(a ⊗ b) = R(a) R(b)``."""
    x1, y1, z1, w1 = (float(v) for v in a)
    x2, y2, z2, w2 = (float(v) for v in b)
    return (
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
    )


def _quat_of(pose: Any) -> tuple[float, float, float, float]:
    o = pose.orientation
    return float(o.x), float(o.y), float(o.z), float(o.w)


def pose_msg_to_wire(pose: Any, axes: Axes) -> dict[str, list[float]]:
    """A ``geometry_msgs/Pose`` of a camera frame with ``axes`` as an agilegs wire pose
    ``{"position", "orientation_xyzw"}`` (OpenCV axes). Left unvalidated: the server's
    checks (finite, unit quaternion, coordinate range) name the field as over HTTP."""
    q = _quat_of(pose)
    if axes == "body":
        q = quaternion_multiply(q, Q_BODY_OPTICAL)
    p = pose.position
    return {"position": [float(p.x), float(p.y), float(p.z)], "orientation_xyzw": list(q)}


def _rotation(q: tuple[float, float, float, float], field: str) -> np.ndarray:
    x, y, z, w = q
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not math.isfinite(n) or n < 1e-12:
        raise FieldError(field, f"quaternion {list(q)} has zero or non-finite norm")
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def pose_msg_to_matrix(pose: Any, axes: Axes = "optical", field: str = "pose") -> np.ndarray:
    """Camera-to-world [4, 4] float64 (OpenCV axes) of a ``geometry_msgs/Pose`` of a camera
    frame with ``axes`` (the quaternion normalised); FieldError for a zero or non-finite
    quaternion or position."""
    out = np.eye(4)
    out[:3, :3] = _rotation(_quat_of(pose), f"{field}.orientation")
    if axes == "body":
        out[:3, :3] = out[:3, :3] @ R_BODY_OPTICAL
    p = pose.position
    out[:3, 3] = [float(p.x), float(p.y), float(p.z)]
    if not np.isfinite(out[:3, 3]).all():
        raise FieldError(f"{field}.position", "must be finite")
    return out


def matrix_to_pose_msg(c2w: Any, axes: Axes = "optical") -> Any:
    """The ``geometry_msgs/Pose`` of a camera frame with ``axes`` whose optical frame has the
    camera-to-world matrix ``c2w`` [4, 4] (OpenCV axes); the quaternion has w >= 0."""
    from agilegs.schemas.geometry import matrix_to_quaternion_xyzw

    m = np.asarray(c2w, dtype=np.float64)
    r = m[:3, :3] @ R_BODY_OPTICAL.T if axes == "body" else m[:3, :3]
    x, y, z, w = (float(v) for v in matrix_to_quaternion_xyzw(r))
    t = m[:3, 3]
    return msg("geometry_msgs/msg/Pose",
               position=msg("geometry_msgs/msg/Point", x=float(t[0]), y=float(t[1]),
                            z=float(t[2])),
               orientation=msg("geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=w))


# ----------------------------------------------------------------------------- cameras
def intrinsics_of(info: Any, field: str = "camera_info") -> dict[str, Any]:
    """agilegs intrinsics ``{fx, fy, cx, cy, width, height}`` of a ``sensor_msgs/CameraInfo``
    (see the module docstring); FieldError naming what is missing or unsupported."""
    width, height = int(info.width), int(info.height)
    if width < 1 or height < 1:
        raise FieldError(f"{field}.width", f"the image size must be set, got {width}x{height}")
    bx, by = int(info.binning_x), int(info.binning_y)
    if bx > 1 or by > 1:
        raise FieldError(f"{field}.binning_x", f"binning {bx}x{by} is not supported (publish "
                         "the camera info of the binned image)")
    roi = info.roi
    if int(roi.width) or int(roi.height) or int(roi.x_offset) or int(roi.y_offset):
        if (int(roi.width), int(roi.height)) not in ((0, 0), (width, height)) or int(
                roi.x_offset) or int(roi.y_offset):
            raise FieldError(f"{field}.roi", "a region of interest is not supported (publish "
                             "the camera info of the cropped image)")
    p = np.asarray(info.p, dtype=np.float64).reshape(-1)
    k = np.asarray(info.k, dtype=np.float64).reshape(-1)
    if p.size == 12 and p[0] != 0 and p[5] != 0:
        fx, fy, cx, cy, name = p[0], p[5], p[2], p[6], "p"
    elif k.size == 9:
        fx, fy, cx, cy, name = k[0], k[4], k[2], k[5], "k"
    else:
        raise FieldError(f"{field}.k", "needs 9 values (or p 12)")
    if not (np.isfinite([fx, fy, cx, cy]).all() and fx > 0 and fy > 0):
        raise FieldError(f"{field}.{name}", f"focal lengths must be positive and finite, got "
                         f"fx={fx}, fy={fy}, cx={cx}, cy={cy}")
    return {"fx": float(fx), "fy": float(fy), "cx": float(cx) + 0.5, "cy": float(cy) + 0.5,
            "width": width, "height": height}


def camera_info_msg(intrinsics: Any, *, frame_id: str = "camera_optical_frame",
                    stamp: Any = None) -> Any:
    """The ``sensor_msgs/CameraInfo`` (no distortion, ``K`` = ``P``'s left block) of agilegs
    intrinsics (an object or a dict with fx, fy, cx, cy, width, height)."""
    from .messages import stamp_msg

    def g(key: str) -> Any:
        return intrinsics[key] if isinstance(intrinsics, dict) else getattr(intrinsics, key)

    fx, fy = float(g("fx")), float(g("fy"))
    cx, cy = float(g("cx")) - 0.5, float(g("cy")) - 0.5
    k = np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], dtype=np.float64)
    p = np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], dtype=np.float64)
    return msg(
        "sensor_msgs/msg/CameraInfo",
        header=_header(frame_id, stamp if stamp is not None else stamp_msg(0)),
        height=int(g("height")), width=int(g("width")), distortion_model="plumb_bob",
        d=np.zeros(5), k=k, r=np.eye(3).reshape(-1), p=p, binning_x=0, binning_y=0,
        roi=msg("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0,
                do_rectify=False),
    )


def _header(frame_id: str, stamp: Any) -> Any:
    return msg("std_msgs/msg/Header", stamp=stamp, frame_id=frame_id)


# ----------------------------------------------------------------------------- images
def _pixels(img: Any, channels: int, dtype: str, field: str) -> np.ndarray:
    """The pixel array [H, W, C] of a ``sensor_msgs/Image`` (row ``step`` and byte order
    honoured)."""
    h, w, step = int(img.height), int(img.width), int(img.step)
    item = np.dtype(dtype).itemsize
    row = w * channels * item
    if h < 1 or w < 1:
        raise FieldError(f"{field}.width", f"the image is {w}x{h}")
    if step < row:
        raise FieldError(f"{field}.step", f"step {step} is shorter than a row ({row} bytes)")
    data = np.asarray(img.data, dtype=np.uint8).reshape(-1)
    if data.size < step * (h - 1) + row:
        raise FieldError(f"{field}.data", f"{data.size} bytes for {h} rows of step {step}")
    rows = np.lib.stride_tricks.as_strided(data, shape=(h, row), strides=(step, 1))
    big = int(img.is_bigendian) and item > 1
    dt = np.dtype(dtype).newbyteorder(">" if big else "<")
    out = np.ascontiguousarray(rows).view(dt).reshape(h, w, channels)
    return out.astype(np.dtype(dtype).newbyteorder("="), copy=False)


def image_to_rgb(img: Any, field: str = "image") -> np.ndarray:
    """RGB uint8 [H, W, 3] of a colour ``sensor_msgs/Image`` (:data:`COLOR_ENCODINGS`)."""
    enc = str(img.encoding).lower()
    if enc not in COLOR_ENCODINGS:
        raise FieldError(f"{field}.encoding", f"{img.encoding!r} is not a colour encoding "
                         f"agilegs reads ({', '.join(COLOR_ENCODINGS)})")
    channels = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}[enc]
    px = _pixels(img, channels, "uint8", field)
    if enc == "mono8":
        return np.repeat(px, 3, axis=2)
    rgb = px[..., :3]
    return np.ascontiguousarray(rgb[..., ::-1] if enc.startswith("bgr") else rgb)


def compressed_to_rgb(img: Any, field: str = "image") -> np.ndarray:
    """RGB uint8 [H, W, 3] of a ``sensor_msgs/CompressedImage`` (JPEG or PNG, via Pillow)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(bytes(np.asarray(img.data, dtype=np.uint8)))) as im:
            return np.asarray(im.convert("RGB"))
    except (UnidentifiedImageError, OSError) as exc:
        raise FieldError(f"{field}.data", f"not a readable {img.format!r} image ({exc})") \
            from None


def depth_to_array(img: Any, field: str = "depth") -> tuple[np.ndarray, float]:
    """``(depth [H, W], depth_scale)`` of a depth ``sensor_msgs/Image``: ``16UC1`` /
    ``mono16`` as uint16 millimetres (scale 0.001 m), ``32FC1`` as float32 metres (scale 1,
    non-finite values set to 0, the missing-depth mark)."""
    enc = str(img.encoding)
    if enc in ("16UC1", "mono16"):
        return np.ascontiguousarray(_pixels(img, 1, "uint16", field)[..., 0]), MM
    if enc == "32FC1":
        d = _pixels(img, 1, "float32", field)[..., 0].copy()
        d[~np.isfinite(d)] = 0.0
        return d, 1.0
    raise FieldError(f"{field}.encoding", f"{enc!r} is not a depth encoding agilegs reads "
                     f"({', '.join(DEPTH_ENCODINGS)})")


def rgb_image_msg(rgb: Any, *, encoding: str = "rgb8", frame_id: str = "camera_optical_frame",
                  stamp: Any = None) -> Any:
    """A ``sensor_msgs/Image`` of RGB uint8 [H, W, 3] in ``encoding`` (rgb8, bgr8, rgba8,
    bgra8 or mono8: the mean of the channels)."""
    from .messages import stamp_msg

    a = np.asarray(rgb, dtype=np.uint8)
    if encoding.startswith("bgr"):
        a = a[..., ::-1]
    if encoding in ("rgba8", "bgra8"):
        a = np.concatenate([a, np.full(a.shape[:2] + (1,), 255, np.uint8)], axis=2)
    if encoding == "mono8":
        a = a.mean(axis=2, keepdims=True).round().astype(np.uint8)
    a = np.ascontiguousarray(a)
    h, w, c = a.shape
    return msg("sensor_msgs/msg/Image",
               header=_header(frame_id, stamp if stamp is not None else stamp_msg(0)),
               height=h, width=w, encoding=encoding, is_bigendian=0, step=w * c,
               data=a.reshape(-1))


def depth_image_msg(depth: Any, *, encoding: str = "16UC1",
                    frame_id: str = "camera_optical_frame", stamp: Any = None) -> Any:
    """A depth ``sensor_msgs/Image``: ``16UC1`` of uint16 millimetres, or ``32FC1`` of
    float32 metres."""
    from .messages import stamp_msg

    if encoding not in ("16UC1", "32FC1"):
        raise ValueError(f"encoding must be 16UC1 or 32FC1, got {encoding!r}")
    a = np.ascontiguousarray(np.asarray(depth, dtype="<u2" if encoding == "16UC1" else "<f4"))
    h, w = a.shape
    return msg("sensor_msgs/msg/Image",
               header=_header(frame_id, stamp if stamp is not None else stamp_msg(0)),
               height=h, width=w, encoding=encoding, is_bigendian=0,
               step=w * a.itemsize, data=a.view(np.uint8).reshape(-1))
