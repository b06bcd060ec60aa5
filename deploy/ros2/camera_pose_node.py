"""A ROS 2 node (rclpy) that publishes the camera pose agilegs pairs with each image.

For every colour image on ``/agilegs/image`` it looks up the transform from ``world_frame``
to the image's ``header.frame_id`` (the camera's optical frame) in TF at the image's stamp
and publishes it as a ``geometry_msgs/PoseStamped`` on ``/agilegs/camera_pose``, stamped
with the image's stamp and with ``header.frame_id`` = ``world_frame``. Open the agilegs
session with the same ``world_frame`` and with ``camera_frame`` = that optical frame.

    python3 camera_pose_node.py --ros-args -p world_frame:=map

An example for a robot whose arm (or localisation) publishes TF; it runs where ROS 2 is
installed (rclpy, tf2_ros), not in agilegs' own tests.
"""

import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.time import Time
from sensor_msgs.msg import Image
from tf2_ros import Buffer, TransformException, TransformListener


class CameraPose(Node):
    def __init__(self) -> None:
        super().__init__("agilegs_camera_pose")
        self.world = self.declare_parameter("world_frame", "map").value
        self.tf = Buffer()
        self.listener = TransformListener(self.tf, self)
        self.pub = self.create_publisher(PoseStamped, "/agilegs/camera_pose", 10)
        self.create_subscription(Image, "/agilegs/image", self.on_image, 10)

    def on_image(self, image: Image) -> None:
        try:  # no waiting in the callback: TF usually arrives before the image
            t = self.tf.lookup_transform(self.world, image.header.frame_id,
                                         Time.from_msg(image.header.stamp))
        except TransformException as exc:
            self.get_logger().warning(f"no camera pose for the image: {exc}")
            return
        msg = PoseStamped()
        msg.header.stamp = image.header.stamp
        msg.header.frame_id = self.world
        msg.pose.position.x = t.transform.translation.x
        msg.pose.position.y = t.transform.translation.y
        msg.pose.position.z = t.transform.translation.z
        msg.pose.orientation = t.transform.rotation
        self.pub.publish(msg)


def main() -> None:
    rclpy.init()
    node = CameraPose()
    try:
        rclpy.spin(node)
    finally:
        node.destroy_node()
        rclpy.shutdown()


if __name__ == "__main__":
    main()
