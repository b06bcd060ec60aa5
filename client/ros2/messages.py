"""ROS 2 messages as CDR bytes, through the ``rosbags`` type store (no ROS install needed).

:func:`typestore` is the ROS 2 Humble store of ``rosbags`` (the ``geometry_msgs``,
``sensor_msgs``, ``std_msgs``, ``tf2_msgs`` and ``builtin_interfaces`` used here are the same
in Humble and Jazzy) with the ``agilegs_interfaces`` package (its ``.msg`` / ``.srv`` files,
shipped in this folder) registered: a service ``agilegs_interfaces/srv/Select`` is the two
types ``agilegs_interfaces/srv/Select_Request`` and ``..._Response``.

A CDR payload, as ROS 2 writes it and zenoh-bridge-ros2dds forwards it, starts with the
4-byte encapsulation header ``00 01 00 00`` (CDR, little-endian; ``00 00`` is big-endian,
which :func:`deserialize` reads too) followed by the message.
"""

from __future__ import annotations

import math
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "CAMERA_INFO",
    "COMPRESSED_IMAGE",
    "CREATE_SESSION",
    "IMAGE",
    "INTERFACES_DIR",
    "OPEN_SESSION",
    "POSE_ARRAY",
    "POSE_STAMPED",
    "SELECT",
    "STATUS",
    "TF_MESSAGE",
    "CdrError",
    "deserialize",
    "field_names",
    "interface_definitions",
    "msg",
    "request_type",
    "response_type",
    "serialize",
    "stamp_msg",
    "stamp_ns",
    "typestore",
]

POSE_ARRAY = "geometry_msgs/msg/PoseArray"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
STATUS = "agilegs_interfaces/msg/Status"
CREATE_SESSION = "agilegs_interfaces/srv/CreateSession"
OPEN_SESSION = "agilegs_interfaces/srv/OpenSession"
SELECT = "agilegs_interfaces/srv/Select"

INTERFACES_DIR = Path(__file__).resolve().parent / "agilegs_interfaces"
"""The ``agilegs_interfaces`` ROS 2 package (``package.xml``, ``CMakeLists.txt``, ``msg/``,
``srv/``): copy it into a colcon workspace's ``src`` and build it there."""


class CdrError(ValueError):
    """Bytes that are not a CDR message of the expected type."""


def request_type(service: str) -> str:
    """``pkg/srv/Name_Request`` of the service ``pkg/srv/Name``."""
    return f"{service}_Request"


def response_type(service: str) -> str:
    """``pkg/srv/Name_Response`` of the service ``pkg/srv/Name``."""
    return f"{service}_Response"


def interface_definitions() -> dict[str, str]:
    """The ``agilegs_interfaces`` definitions as ``{type name: message text}``: each
    ``.msg`` under its name, each ``.srv`` as its ``_Request`` and ``_Response`` halves."""
    pkg = INTERFACES_DIR.name
    out: dict[str, str] = {}
    for path in sorted((INTERFACES_DIR / "msg").glob("*.msg")):
        out[f"{pkg}/msg/{path.stem}"] = path.read_text()
    for path in sorted((INTERFACES_DIR / "srv").glob("*.srv")):
        lines = path.read_text().splitlines()
        cut = [i for i, line in enumerate(lines) if line.strip() == "---"]
        if len(cut) != 1:
            raise ValueError(f"{path}: a service needs exactly one '---' line")
        name = f"{pkg}/srv/{path.stem}"
        out[request_type(name)] = "\n".join(lines[: cut[0]]) + "\n"
        out[response_type(name)] = "\n".join(lines[cut[0] + 1:]) + "\n"
    return out


@cache
def typestore() -> Any:
    """The ROS 2 Humble type store with ``agilegs_interfaces`` registered (built once)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    defs = interface_definitions()
    # the messages first: the services refer to them
    for name in sorted(defs, key=lambda n: "/srv/" in n):
        (fields,) = get_types_from_msg(defs[name], name).values()
        # the parser files every type under <pkg>/msg/: keep a service half's own name
        store.register({name: fields})
    return store


def field_names(typename: str) -> list[str]:
    """The field names of ``typename``, in order."""
    return [name for name, _ in typestore().fielddefs[typename][1]]


def msg(typename: str, **fields: Any) -> Any:
    """A message object of ``typename`` with ``fields`` (nested messages as objects), every
    field not given at its zero value (0, False, "", empty sequences, zeroed messages)."""
    from rosbags.interfaces import Nodetype

    store = typestore()
    values: dict[str, Any] = {}
    for name, (kind, arg) in store.fielddefs[typename][1]:
        if name in fields:
            values[name] = fields.pop(name)
        elif kind == Nodetype.NAME:
            values[name] = msg(arg)
        elif kind == Nodetype.BASE:
            values[name] = _ZERO.get(arg[0], 0)
        elif arg[0][0] == Nodetype.BASE and arg[0][1][0] != "string":  # numbers: an array
            values[name] = np.zeros(arg[1] if kind == Nodetype.ARRAY else 0,
                                    dtype=_NUMPY.get(arg[0][1][0], arg[0][1][0]))
        else:
            inner = arg[0]
            values[name] = [msg(inner[1]) if inner[0] == Nodetype.NAME else ""
                            for _ in range(arg[1] if kind == Nodetype.ARRAY else 0)]
    if fields:
        raise TypeError(f"{typename} has no field {sorted(fields)}")
    return store.types[typename](**values)


_ZERO: dict[str, Any] = {"string": "", "bool": False, "float32": 0.0, "float64": 0.0}
_NUMPY = {"bool": "bool", "octet": "uint8", "char": "uint8", "byte": "uint8"}


def serialize(message: Any, typename: str | None = None) -> bytes:
    """CDR bytes (little-endian, with the 4-byte encapsulation header) of ``message``."""
    name = typename or message.__msgtype__
    return bytes(typestore().serialize_cdr(message, name, little_endian=True))


def deserialize(data: bytes | memoryview, typename: str) -> Any:
    """The message of ``typename`` in CDR ``data``; :class:`CdrError` naming the type when
    the bytes are not one (too short, a bad header, trailing bytes, a bad string)."""
    from rosbags.serde import SerdeError

    raw = bytes(data)
    if len(raw) < 4:
        raise CdrError(f"payload: {len(raw)} bytes is no CDR {typename} (the 4-byte "
                       "encapsulation header is missing)")
    if raw[0] != 0 or raw[1] not in (0, 1):
        raise CdrError(f"payload: encapsulation header {raw[:4].hex()} is not plain CDR "
                       f"(00 00 or 00 01) for {typename}")
    try:
        return typestore().deserialize_cdr(raw, typename)
    except SerdeError as exc:
        raise CdrError(f"payload: not a CDR {typename} ({exc})") from None
    except (IndexError, OverflowError, MemoryError, TypeError, ValueError) as exc:
        raise CdrError(f"payload: not a CDR {typename} ({type(exc).__name__}: {exc})") from None


def stamp_msg(t: float | int, *, ns: bool = False) -> Any:
    """A ``builtin_interfaces/msg/Time`` of ``t`` seconds (``ns=True``: nanoseconds)."""
    if ns:
        sec, nanosec = divmod(int(t), 1_000_000_000)
    else:  # seconds and the fraction apart: a float has no nanoseconds left at 1.7e18
        sec = math.floor(float(t))
        nanosec = int(round((float(t) - sec) * 1e9))
        sec, nanosec = sec + nanosec // 1_000_000_000, nanosec % 1_000_000_000
    return msg("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)


def stamp_ns(stamp: Any) -> int:
    """Nanoseconds of a ``builtin_interfaces/msg/Time``."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
