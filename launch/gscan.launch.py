"""Start the gscan_ros stack: world simulator, parser, policy (and optionally the recorder).

    ros2 launch gscan_ros gscan.launch.py
    ros2 launch gscan_ros gscan.launch.py checkpoint:=/path/model.pt record:=true

Parameters come from share/gscan_ros/config/params.yaml; the `checkpoint` argument
overrides the parser's and the policy's so both always use the same model.
`gscan-ros bringup` runs the same nodes in one process where `ros2 launch` is missing.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

PACKAGE = "gscan_ros"


def generate_launch_description() -> LaunchDescription:
    params = os.path.join(get_package_share_directory(PACKAGE), "config", "params.yaml")
    # value_type=str: an empty argument must stay "" (the shipped model), not become null.
    checkpoint = {"checkpoint": ParameterValue(LaunchConfiguration("checkpoint"), value_type=str)}
    return LaunchDescription([
        DeclareLaunchArgument("checkpoint", default_value="", description="policy checkpoint; empty: shipped model"),
        DeclareLaunchArgument("record", default_value="false", description="also run episode_recorder_node"),
        Node(package=PACKAGE, executable="world_simulator_node", name="world_simulator_node",
             parameters=[params], output="screen"),
        Node(package=PACKAGE, executable="parser_node", name="parser_node",
             parameters=[params, checkpoint], output="screen"),
        Node(package=PACKAGE, executable="policy_node", name="policy_node",
             parameters=[params, checkpoint], output="screen"),
        Node(package=PACKAGE, executable="episode_recorder_node", name="episode_recorder_node",
             parameters=[params], output="screen", condition=IfCondition(LaunchConfiguration("record"))),
    ])
