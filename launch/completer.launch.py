"""Launch the gd_completion `completer` node (`ros2 launch gd_completion completer.launch.py --show-args`).

Arguments: `namespace` (the node's namespace; a params file's `completer:` section still applies), `use_sim_time`,
`params_file` (the completer's ros__parameters; a missing file ends the launch with an error instead of a node on
its defaults), `cloud_topic`, `boxes_topic`, `output_topic` (remappings of the node's topic names points,
detections, completed_vehicles: they rename the topics the parameters of the same name leave at their defaults),
`log_level`.

The node gets the Fast DDS large-message profile (config/fastdds_large_messages.xml) unless the environment
already names one: without it most 2 MB clouds are lost between processes. Publishers of large clouds need it
too (`gd-completion play` sets it for itself)."""
from __future__ import annotations

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.launch_context import LaunchContext
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from gd_completion.fastdds import PROFILE_NAME, PROFILE_VARIABLES
from gd_completion.ros.launch_params import (
    NODE_NAME,
    TOPIC_ARGUMENTS,
    checked_params_file,
    params_file_for_namespace,
    topic_remappings,
)
from launch import LaunchDescription


def _completer(context: LaunchContext, share: str) -> list[Node]:
    """The node, from the arguments' values (the params file checked here, at launch time)."""
    def value(name: str) -> str:
        return LaunchConfiguration(name).perform(context)

    namespace = value("namespace")
    pushed = context.launch_configurations.get("ros_namespace", "")  # a PushRosNamespace around this launch file
    full_namespace = namespace if namespace.startswith("/") else f"{pushed.rstrip('/')}/{namespace}"
    params_file = params_file_for_namespace(checked_params_file(value("params_file")), full_namespace)
    environment = context.environment
    profile_env = {} if any(environment.get(name) for name in PROFILE_VARIABLES) else \
        {PROFILE_VARIABLES[0]: os.path.join(share, "config", PROFILE_NAME)}
    return [Node(
        package="gd_completion",
        executable="completer",
        name=NODE_NAME,
        namespace=namespace,
        output="screen",
        emulate_tty=True,
        parameters=[str(params_file), {"use_sim_time": value("use_sim_time").lower() == "true"}],
        remappings=topic_remappings({name: value(name) for name in TOPIC_ARGUMENTS}),
        arguments=["--ros-args", "--log-level", value("log_level")],
        additional_env=profile_env,
    )]


def generate_launch_description() -> LaunchDescription:
    share = get_package_share_directory("gd_completion")
    return LaunchDescription([
        DeclareLaunchArgument("namespace", default_value="", description="Namespace of the node (default: none)"),
        DeclareLaunchArgument("use_sim_time", default_value="false", choices=["true", "false"],
                              description="Follow /clock (e.g. `gd-completion play --clock`) instead of the system "
                                          "clock; overrides the params file's use_sim_time"),
        DeclareLaunchArgument("params_file", default_value=os.path.join(share, "config", "completer.yaml"),
                              description="YAML file with the completer's ros__parameters (must exist)"),
        DeclareLaunchArgument("cloud_topic", default_value="points",
                              description="Input PointCloud2 topic: remaps the node's `points`"),
        DeclareLaunchArgument("boxes_topic", default_value="detections",
                              description="Input boxes topic: remaps the node's `detections`"),
        DeclareLaunchArgument("output_topic", default_value="completed_vehicles",
                              description="Output PointCloud2 topic: remaps the node's `completed_vehicles`"),
        DeclareLaunchArgument("log_level", default_value="info", description="Logging level of the node"),
        OpaqueFunction(function=_completer, args=[share]),
    ])
