"""Launch the gd_completion `completer` node with its parameters file (`params_file:=...` to override).

The node gets the Fast DDS large-message profile (config/fastdds_large_messages.xml) unless the environment
already names one: without it most 2 MB clouds are lost between processes. Publishers of large clouds need it
too (`gd-completion play` sets it for itself)."""
from __future__ import annotations

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument
from launch.substitutions import EnvironmentVariable, LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription


def generate_launch_description() -> LaunchDescription:
    share = get_package_share_directory("gd_completion")
    default_params = os.path.join(share, "config", "completer.yaml")
    profile = os.path.join(share, "config", "fastdds_large_messages.xml")
    return LaunchDescription([
        DeclareLaunchArgument("params_file", default_value=default_params,
                              description="YAML file with the completer's ros__parameters"),
        DeclareLaunchArgument("log_level", default_value="info", description="Logging level of the node"),
        Node(
            package="gd_completion",
            executable="completer",
            name="completer",
            output="screen",
            emulate_tty=True,
            parameters=[LaunchConfiguration("params_file")],
            arguments=["--ros-args", "--log-level", LaunchConfiguration("log_level")],
            additional_env={"FASTRTPS_DEFAULT_PROFILES_FILE": EnvironmentVariable("FASTRTPS_DEFAULT_PROFILES_FILE",
                                                                                  default_value=profile)},
        ),
    ])
