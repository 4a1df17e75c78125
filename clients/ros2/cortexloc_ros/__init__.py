"""cortexloc's ROS 2 node (`cortexloc_node`, console script `cortexloc-ros`): camera frames, camera_info and
odometry in; places, loop closures, diagnostics and RViz markers out, through the typed client
(`cortexloc_client`). See clients/ros2/README.md and the repository's README, "With ROS 2"."""

__version__ = "0.1.0"
