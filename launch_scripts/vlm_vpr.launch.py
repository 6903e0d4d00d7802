"""ros2 launch vlm_vpr_ros vlm_vpr.launch.py map_dir:=/path/to/map [image:=/camera/image_raw]

For normal ROS 2 installs (``launch`` and ``launch_ros`` are not on PyPI; without them use
``launch_scripts/run_node.sh``). Installed to ``share/vlm_vpr_ros/launch/``. Arguments:

* ``map_dir`` (required): map folder written by ``vlm-vpr build-map``.
* ``params_file``: defaults to the installed ``vlm_vpr_params.yaml``.
* ``image``: camera topic (``image/compressed`` is remapped to ``<image>/compressed``).
* ``fix``: output topic of the NavSatFix (default ``fix`` in the launch namespace).
* ``pose``: output topic of the PoseWithCovarianceStamped (default ``pose``; e.g.
  ``/set_pose`` for robot_localization or ``/initialpose`` for Nav2 AMCL).
* ``namespace``: namespace of the node.
* ``use_sim_time``: follow ``/clock`` (``vlm-vpr replay --clock`` or a simulator).
* ``qos``, ``prior_provider``, ``fix_durability``, ``publish_debug``: override the params
  file when not empty.
* ``lifecycle``: run the managed variant (``vlm_vpr_lifecycle_node``); ``autostart`` then
  configures and activates it (set ``autostart:=false`` under a lifecycle manager).
* ``fastdds_profile``: a Fast DDS XML profile for the node's process, e.g. the installed
  ``fastdds_shm.xml`` (shared memory for full-size raw frames on one host).
"""

from launch import LaunchDescription
from launch.actions import (DeclareLaunchArgument, EmitEvent, OpaqueFunction,
                            RegisterEventHandler)
from launch.events import matches_action
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import LifecycleNode, Node
from launch_ros.event_handlers import OnStateTransition
from launch_ros.events.lifecycle import ChangeState
from launch_ros.substitutions import FindPackageShare
from lifecycle_msgs.msg import Transition

TRUE = ("true", "1", "yes", "on")


def _node(context, *args, **kwargs):
    get = lambda name: LaunchConfiguration(name).perform(context)  # noqa: E731
    overrides = {"map_dir": get("map_dir"), "use_sim_time": get("use_sim_time").lower() in TRUE}
    for name in ("qos", "prior_provider", "fix_durability"):
        if get(name):
            overrides[name] = get(name)
    if get("publish_debug"):
        overrides["publish_debug"] = get("publish_debug").lower() in TRUE
    image = get("image")
    common = dict(
        package="vlm_vpr_ros", name="vlm_vpr_node", namespace=get("namespace"),
        output="screen", parameters=[get("params_file"), overrides],
        remappings=[("image", image), ("image/compressed", image + "/compressed"),
                    ("fix", get("fix")), ("pose", get("pose"))])
    profile = get("fastdds_profile")
    if profile:
        common["additional_env"] = {"FASTDDS_DEFAULT_PROFILES_FILE": profile,
                                    "FASTRTPS_DEFAULT_PROFILES_FILE": profile}
    if get("lifecycle").lower() not in TRUE:
        return [Node(executable="vlm_vpr_node", **common)]
    node = LifecycleNode(executable="vlm_vpr_lifecycle_node", **common)
    actions = [node]
    if get("autostart").lower() in TRUE:
        actions += [
            RegisterEventHandler(OnStateTransition(
                target_lifecycle_node=node, goal_state="inactive",
                entities=[EmitEvent(event=ChangeState(
                    lifecycle_node_matcher=matches_action(node),
                    transition_id=Transition.TRANSITION_ACTIVATE))])),
            EmitEvent(event=ChangeState(lifecycle_node_matcher=matches_action(node),
                                        transition_id=Transition.TRANSITION_CONFIGURE)),
        ]
    return actions


def generate_launch_description() -> LaunchDescription:
    share = FindPackageShare("vlm_vpr_ros")
    return LaunchDescription([
        DeclareLaunchArgument("map_dir", description="map folder (vlm-vpr build-map)"),
        DeclareLaunchArgument("params_file",
                              default_value=PathJoinSubstitution([share, "launch",
                                                                  "vlm_vpr_params.yaml"]),
                              description="node parameters (YAML)"),
        DeclareLaunchArgument("image", default_value="/camera/image_raw",
                              description="sensor_msgs/Image topic of the camera"),
        DeclareLaunchArgument("fix", default_value="fix",
                              description="sensor_msgs/NavSatFix output topic"),
        DeclareLaunchArgument("pose", default_value="pose",
                              description="geometry_msgs/PoseWithCovarianceStamped output "
                                          "topic (/set_pose, /initialpose)"),
        DeclareLaunchArgument("namespace", default_value="", description="node namespace"),
        DeclareLaunchArgument("use_sim_time", default_value="false",
                              description="use /clock (bag replay with --clock, simulators)"),
        DeclareLaunchArgument("qos", default_value="",
                              description="image QoS: sensor_data, best_effort, reliable "
                                          "('' = the params file's)"),
        DeclareLaunchArgument("prior_provider", default_value="",
                              description="none, fixed, recorded, answers, openai "
                                          "('' = the params file's)"),
        DeclareLaunchArgument("fix_durability", default_value="",
                              description="volatile | transient_local ('' = the params "
                                          "file's)"),
        DeclareLaunchArgument("publish_debug", default_value="",
                              description="true: debug image and candidates ('' = the params "
                                          "file's)"),
        DeclareLaunchArgument("lifecycle", default_value="false",
                              description="run the managed (lifecycle) node"),
        DeclareLaunchArgument("autostart", default_value="true",
                              description="lifecycle: configure and activate at start"),
        DeclareLaunchArgument("fastdds_profile", default_value="",
                              description="Fast DDS XML profile for the node, e.g. "
                                          "<share>/launch/fastdds_shm.xml"),
        OpaqueFunction(function=_node),
    ])
