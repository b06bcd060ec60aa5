"""The ROS 2 transport: agilegs' topics and services as CDR on the Zenoh keys that
zenoh-bridge-ros2dds maps ROS 2 names to (:mod:`.adapter`), the messages <-> operation bodies
(:mod:`.convert`) and the frames paired from their topics (:mod:`.assembler`). The message
types, keys and frame conventions are :mod:`agilegs.client.ros2`'s. See ``docs/ros2.md``.
"""
