"""ROS 2 launch example: a RealSense camera, its frames' poses and zenoh-bridge-ros2dds,
so that an agilegs server (``agilegs serve --ros2 /bot1/agilegs``) serves this robot.

    ros2 launch agilegs_robot.launch.py world_frame:=map

* ``realsense2_camera`` (4.x) with depth aligned to colour, its colour image, camera info and
  aligned depth remapped to ``/agilegs/image``, ``/agilegs/camera_info`` and
  ``/agilegs/depth`` (CHANGE: the topic names of your camera driver);
* ``camera_pose_node.py`` (beside this file): the camera pose from TF on
  ``/agilegs/camera_pose``, stamped like each image;
* ``zenoh-bridge-ros2dds`` with ``zenoh-bridge-ros2dds.json5`` (beside this file: the robot's
  namespace ``/bot1``, the agilegs topics only, long service timeouts).

Your robot node then publishes the candidate poses on ``/agilegs/candidates`` and calls
``/agilegs/create_session`` (or ``open_session``) and ``/agilegs/select``
(``agilegs_interfaces``, built with colcon); the decision arrives on ``/agilegs/decision``.
An example, not run by agilegs' own tests (they need no ROS install).
"""

import os

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

HERE = os.path.dirname(os.path.abspath(__file__))


def generate_launch_description() -> LaunchDescription:
    world = LaunchConfiguration("world_frame")
    return LaunchDescription([
        DeclareLaunchArgument("world_frame", default_value="map",
                              description="the frame the camera poses are given in"),
        DeclareLaunchArgument("bridge_config",
                              default_value=os.path.join(HERE, "zenoh-bridge-ros2dds.json5")),
        Node(
            package="realsense2_camera", executable="realsense2_camera_node",
            namespace="camera", name="camera", output="screen",
            parameters=[{"align_depth.enable": True, "enable_sync": True}],
            remappings=[
                ("/camera/camera/color/image_raw", "/agilegs/image"),
                ("/camera/camera/color/camera_info", "/agilegs/camera_info"),
                ("/camera/camera/aligned_depth_to_color/image_raw", "/agilegs/depth"),
            ],
        ),
        ExecuteProcess(
            cmd=["python3", os.path.join(HERE, "camera_pose_node.py"), "--ros-args", "-p",
                 ["world_frame:=", world]],
            output="screen",
        ),
        ExecuteProcess(
            cmd=["zenoh-bridge-ros2dds", "-c", LaunchConfiguration("bridge_config")],
            output="screen",
        ),
    ])
