"""ros2 launch vlm_vpr_ros vlm_vpr.launch.py map_dir:=/path/to/map [image:=/camera/image_raw]

For normal ROS 2 installs (``launch`` and ``launch_ros`` are not on PyPI; without them use
``launch_scripts/run_node.sh``). Arguments:

* ``map_dir`` (required): map folder written by ``vlm-vpr build-map``.
* ``params_file``: defaults to the installed ``launch_scripts/vlm_vpr_params.yaml``.
* ``image``: camera topic (``image/compressed`` is remapped to ``<image>/compressed``).
* ``fix``: output topic of the NavSatFix (default ``fix`` in the launch namespace).
* ``namespace``: namespace of the node.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def generate_launch_description() -> LaunchDescription:
    default_params = PathJoinSubstitution(
        [FindPackageShare("vlm_vpr_ros"), "launch_scripts", "vlm_vpr_params.yaml"])
    image = LaunchConfiguration("image")
    return LaunchDescription([
        DeclareLaunchArgument("map_dir", description="map folder (vlm-vpr build-map)"),
        DeclareLaunchArgument("params_file", default_value=default_params,
                              description="node parameters (YAML)"),
        DeclareLaunchArgument("image", default_value="/camera/image_raw",
                              description="sensor_msgs/Image topic of the camera"),
        DeclareLaunchArgument("fix", default_value="fix",
                              description="sensor_msgs/NavSatFix output topic"),
        DeclareLaunchArgument("namespace", default_value="", description="node namespace"),
        Node(
            package="vlm_vpr_ros",
            executable="vlm_vpr_node",
            name="vlm_vpr_node",
            namespace=LaunchConfiguration("namespace"),
            output="screen",
            parameters=[LaunchConfiguration("params_file"),
                        {"map_dir": LaunchConfiguration("map_dir")}],
            remappings=[
                ("image", image),
                ("image/compressed", [image, "/compressed"]),
                ("fix", LaunchConfiguration("fix")),
            ],
        ),
    ])
