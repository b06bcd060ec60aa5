"""Where agilegs' ROS 2 topics and services travel on Zenoh: the names zenoh-bridge-ros2dds
gives them.

The bridge (``zenoh-plugin-ros2dds``, ``ros2_utils.rs``: ``ros2_name_to_key_expr``) maps a
ROS 2 topic or service name to a key expression by dropping its leading ``/`` and, when the
bridge runs with a ``namespace``, putting that namespace (without its ``/``) in front:
``/agilegs/candidates`` is the key ``agilegs/candidates``, and behind a bridge with
``namespace: "/bot1"`` the key ``bot1/agilegs/candidates``. agilegs serves one or more
*namespaces*, each the ROS name prefix as the keys carry it (bridge namespace + the topics'
own namespace, e.g. ``/bot1/agilegs``); under a namespace ``NS``:

====================  ========================================  ==========================
name                  type                                      direction
====================  ========================================  ==========================
``NS/camera_info``    ``sensor_msgs/msg/CameraInfo``            robot -> agilegs
``NS/candidates``     ``geometry_msgs/msg/PoseArray``           robot -> agilegs (the pool)
``NS/image``          ``sensor_msgs/msg/Image`` (colour)        robot -> agilegs
``NS/depth``          ``sensor_msgs/msg/Image`` (16UC1, 32FC1)  robot -> agilegs
``NS/camera_pose``    ``geometry_msgs/msg/PoseStamped``         robot -> agilegs
``NS/decision``       ``geometry_msgs/msg/PoseStamped``         agilegs -> robot
``NS/shortlist``      ``geometry_msgs/msg/PoseArray``           agilegs -> robot
``NS/errors``         ``agilegs_interfaces/msg/Status``         agilegs -> robot
``NS/create_session`` ``agilegs_interfaces/srv/CreateSession``  service
``NS/open_session``   ``agilegs_interfaces/srv/OpenSession``    service
``NS/select``         ``agilegs_interfaces/srv/Select``         service
====================  ========================================  ==========================
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from . import messages as m

__all__ = [
    "INPUT_TOPICS",
    "OUTPUT_TOPICS",
    "SERVICES",
    "Namespace",
    "name_to_key",
    "normalize_namespace",
]

INPUT_TOPICS: dict[str, str] = {
    "camera_info": m.CAMERA_INFO,
    "candidates": m.POSE_ARRAY,
    "image": m.IMAGE,
    "depth": m.IMAGE,
    "camera_pose": m.POSE_STAMPED,
}
"""The topics agilegs subscribes to under a namespace, and their types."""
OUTPUT_TOPICS: dict[str, str] = {
    "decision": m.POSE_STAMPED,
    "shortlist": m.POSE_ARRAY,
    "errors": m.STATUS,
}
"""The topics agilegs publishes under a namespace, and their types."""
SERVICES: dict[str, str] = {
    "create_session": m.CREATE_SESSION,
    "open_session": m.OPEN_SESSION,
    "select": m.SELECT,
}
"""The services agilegs answers under a namespace, and their types."""

_TOKEN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def normalize_namespace(namespace: str) -> str:
    """``namespace`` as a fully qualified ROS name (``/a/b``: a leading ``/``, none at the
    end); ValueError unless every token is a valid ROS name token (letters, digits and
    ``_``, not starting with a digit)."""
    text = str(namespace).strip()
    tokens = [t for t in text.strip("/").split("/")]
    if not text.strip("/") or any(not _TOKEN.match(t) for t in tokens):
        raise ValueError(f"ROS 2 namespace {namespace!r}: each /-separated token must match "
                         f"{_TOKEN.pattern}")
    return "/" + "/".join(tokens)


def name_to_key(ros_name: str, bridge_namespace: str = "/") -> str:
    """The Zenoh key zenoh-bridge-ros2dds uses for the fully qualified ROS name
    ``ros_name`` when it runs with ``bridge_namespace`` (``/``: none)."""
    name = normalize_namespace(ros_name)[1:]
    if bridge_namespace.strip() in ("", "/"):
        return name
    return f"{normalize_namespace(bridge_namespace)[1:]}/{name}"


@dataclass(frozen=True)
class Namespace:
    """The keys of one agilegs namespace (``name``: a fully qualified ROS name)."""

    name: str

    def __post_init__(self) -> None:
        object.__setattr__(self, "name", normalize_namespace(self.name))

    @property
    def prefix(self) -> str:
        """The key prefix: the namespace without its leading ``/``."""
        return self.name[1:]

    def key(self, leaf: str) -> str:
        """The key of the topic or service ``leaf`` (``candidates``, ``select``, ...)."""
        if leaf not in INPUT_TOPICS and leaf not in OUTPUT_TOPICS and leaf not in SERVICES:
            raise ValueError(f"{leaf!r} is no agilegs ROS 2 topic or service")
        return f"{self.prefix}/{leaf}"

    def leaf(self, key: str) -> str | None:
        """The topic or service name of ``key`` under this namespace (None if not one)."""
        head, _, leaf = str(key).rpartition("/")
        return leaf if head == self.prefix else None
