"""cortexloc_ros: an ament_python package (`colcon build` in a ROS 2 workspace) that pip also installs.

pip: `pip install ./clients/python './clients/ros2[kilted]'` (the ROS 2 Kilted wheels come with the extra;
in a ROS 2 install from apt, leave the extra out: rclpy and the messages are the install's).
"""

from setuptools import setup

PACKAGE = "cortexloc_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    description="ROS 2 node for the cortexloc visual place-recognition service",
    license="Apache-2.0",
    python_requires=">=3.10",
    packages=[PACKAGE],
    package_data={PACKAGE: ["data/*.npz", "data/*.md", "py.typed"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", ["config/params.yaml", "config/fastdds_udp_localhost.xml"]),
        (f"share/{PACKAGE}/launch", ["launch/cortexloc.launch.py"]),
    ],
    install_requires=["setuptools", "numpy>=1.21", "cortexloc-client"],
    extras_require={
        # ROS 2 Kilted's wheels (Python 3.11); exact versions in the repository's constraints.txt.
        "kilted": ["ros-rclpy>=9,<10", "ros-rmw-fastrtps-cpp", "ros-sensor-msgs", "ros-std-msgs",
                   "ros-nav-msgs", "ros-geometry-msgs", "ros-diagnostic-msgs", "ros-visualization-msgs"],
    },
    entry_points={"console_scripts": [
        "cortexloc-ros = cortexloc_ros.node:run",
        "cortexloc_node = cortexloc_ros.node:run",  # `ros2 run cortexloc_ros cortexloc_node` (colcon)
        "cortexloc-ros-demo = cortexloc_ros.demo:run",
    ]},
)
