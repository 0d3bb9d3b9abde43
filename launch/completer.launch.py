"""Launch the gd_completion `completer` node with its parameters file (`params_file:=...` to override)."""
from __future__ import annotations

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription


def generate_launch_description() -> LaunchDescription:
    default_params = os.path.join(get_package_share_directory("gd_completion"), "config", "completer.yaml")
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
        ),
    ])
