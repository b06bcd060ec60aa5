"""ROS 2 for agilegs, without a ROS install: messages as CDR (``rosbags``), the keys that
zenoh-bridge-ros2dds maps agilegs' topics and services to, the frame conventions, and
rosbag2 reading and writing (``pip install 'agilegs[ros2]'``).

* :mod:`~agilegs.client.ros2.messages`: the type store (ROS 2 Humble plus the
  ``agilegs_interfaces`` package shipped in ``agilegs_interfaces/``), CDR in and out.
* :mod:`~agilegs.client.ros2.keys`: topic and service names under a namespace, and their
  Zenoh keys.
* :mod:`~agilegs.client.ros2.frames`: poses (optical and REP-103 body frames), camera infos
  and images to agilegs' conventions and back.
* :mod:`~agilegs.client.ros2.bag`: posed frames from a bag (``read_bag``,
  ``observations_from_bag``) and bags from frames (``write_bag``).
* :mod:`~agilegs.client.ros2.robot`: a robot's side over Zenoh (CDR on the bridge's keys),
  for scripts and tests.

See ``docs/ros2.md``.
"""

from .bag import BagFrame, BagTopics, is_bag, observations_from_bag, read_bag, write_bag
from .frames import FieldError, axes_of_frame
from .keys import Namespace, name_to_key, normalize_namespace
from .messages import CdrError, deserialize, serialize, typestore

__all__ = [
    "BagFrame",
    "BagTopics",
    "CdrError",
    "FieldError",
    "Namespace",
    "axes_of_frame",
    "deserialize",
    "is_bag",
    "name_to_key",
    "normalize_namespace",
    "observations_from_bag",
    "read_bag",
    "serialize",
    "typestore",
    "write_bag",
]
