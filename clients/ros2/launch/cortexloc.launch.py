"""Launch cortexloc_node with the package's parameters (full ROS 2 installs: `ros2 launch cortexloc_ros
cortexloc.launch.py`). Not run in CI: pip-installed ROS 2 has no `launch` / `launch_ros`.

    ros2 launch cortexloc_ros cortexloc.launch.py params:=/path/to/my_params.yaml namespace:=robot1

The API key comes from the environment (CORTEXLOC_API_KEY, or the variable `api_key_env` names) or from
`api_key_file`, never from a launch argument.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription


def generate_launch_description() -> LaunchDescription:
    default_params = os.path.join(get_package_share_directory("cortexloc_ros"), "config", "params.yaml")
    return LaunchDescription([
        DeclareLaunchArgument("params", default_value=default_params,
                              description="parameters YAML (/**: ros__parameters: ...)"),
        DeclareLaunchArgument("namespace", default_value="", description="the node's namespace"),
        Node(package="cortexloc_ros", executable="cortexloc_node", name="cortexloc_node",
             namespace=LaunchConfiguration("namespace"), parameters=[LaunchConfiguration("params")],
             output="screen", emulate_tty=True),
    ])
