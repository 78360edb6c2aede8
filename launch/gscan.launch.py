"""Start the gscan_ros stack: world simulator, parser, policy (and optionally the recorder).

    ros2 launch gscan_ros gscan.launch.py
    ros2 launch gscan_ros gscan.launch.py checkpoint:=/path/model.pt record:=true
    ros2 launch gscan_ros gscan.launch.py namespace:=robot1 params_file:=/path/my_params.yaml

Parameters come from `params_file` (default: share/gscan_ros/config/params.yaml, whose
`/**/<node>` keys match the nodes in any namespace). A non-empty `checkpoint` argument
overrides the parser's and the policy's, so both use the same model; empty keeps the
params file's. `gscan-ros bringup` runs the same nodes in one process where
`ros2 launch` is missing.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription

PACKAGE = "gscan_ros"


def stack(context):
    """The nodes, built once the arguments are known (the checkpoint override only when given)."""
    params_file = LaunchConfiguration("params_file").perform(context)
    namespace = LaunchConfiguration("namespace").perform(context)
    checkpoint = LaunchConfiguration("checkpoint").perform(context)
    model = [{"checkpoint": checkpoint}] if checkpoint else []
    return [
        Node(package=PACKAGE, executable="world_simulator_node", name="world_simulator_node",
             namespace=namespace, parameters=[params_file], output="screen"),
        Node(package=PACKAGE, executable="parser_node", name="parser_node",
             namespace=namespace, parameters=[params_file, *model], output="screen"),
        Node(package=PACKAGE, executable="policy_node", name="policy_node",
             namespace=namespace, parameters=[params_file, *model], output="screen"),
        Node(package=PACKAGE, executable="episode_recorder_node", name="episode_recorder_node",
             namespace=namespace, parameters=[params_file], output="screen",
             condition=IfCondition(LaunchConfiguration("record"))),
    ]


def generate_launch_description() -> LaunchDescription:
    default_params = os.path.join(get_package_share_directory(PACKAGE), "config", "params.yaml")
    return LaunchDescription([
        DeclareLaunchArgument("params_file", default_value=default_params,
                              description="node parameters (YAML, `/**/<node>: ros__parameters:` keys)"),
        DeclareLaunchArgument("namespace", default_value="", description="namespace of every node and topic"),
        DeclareLaunchArgument("checkpoint", default_value="",
                              description="policy checkpoint for parser and policy; empty: the params file's"),
        DeclareLaunchArgument("record", default_value="false", description="also run episode_recorder_node"),
        OpaqueFunction(function=stack),
    ])
