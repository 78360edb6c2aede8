"""Start the gscan_ros stack: world simulator, parser, policy (and optionally the recorder).

    ros2 launch gscan_ros gscan.launch.py
    ros2 launch gscan_ros gscan.launch.py checkpoint:=/path/model.pt max_steps:=60 seed:=7
    ros2 launch gscan_ros gscan.launch.py record:=true bag_dir:=/data/live_bag
    ros2 launch gscan_ros gscan.launch.py namespace:=robot1 params_file:=/path/my_params.yaml

Parameters come from `params_file` (default: share/gscan_ros/config/params.yaml, whose
`/**/<node>` keys match the nodes in any namespace). Each argument of `NODE_PARAMETERS`,
when given, overrides the parameter of that name of the nodes it lists; empty (the
default) keeps the params file's. `checkpoint` goes to the parser and the policy, so both
use the same model. `gscan-ros bringup` runs the same nodes in one process where
`ros2 launch` is missing.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

from launch import LaunchDescription

PACKAGE = "gscan_ros"

# Launch argument -> (the nodes whose parameter of that name it sets, the parameter's type, help).
NODE_PARAMETERS = {
    "checkpoint": (("parser_node", "policy_node"), str, "policy checkpoint for parser and policy"),
    "max_steps": (("policy_node",), int, "actions per episode before <eos> is forced"),
    "seed": (("world_simulator_node",), int, "first sampling seed of the world (no dataset)"),
    "grid_size": (("world_simulator_node",), int, "grid side of sampled worlds (no dataset)"),
    "bag_dir": (("episode_recorder_node",), str, "where the recorder writes its bag (with record:=true)"),
}


def node_parameters(context, node: str) -> list:
    """The params file, then the launch arguments given for `node` (typed, so `checkpoint:=7` stays a string)."""
    given = {name: ParameterValue(LaunchConfiguration(name), value_type=value_type)
             for name, (nodes, value_type, _) in NODE_PARAMETERS.items()
             if node in nodes and LaunchConfiguration(name).perform(context)}
    return [LaunchConfiguration("params_file").perform(context), *([given] if given else [])]


def stack(context):
    """The nodes, built once the arguments are known (overrides only for the arguments given)."""
    namespace = LaunchConfiguration("namespace").perform(context)

    def node(name: str, **kwargs) -> Node:
        return Node(package=PACKAGE, executable=name, name=name, namespace=namespace,
                    parameters=node_parameters(context, name), output="screen", **kwargs)

    return [
        node("world_simulator_node"),
        node("parser_node"),
        node("policy_node"),
        node("episode_recorder_node", condition=IfCondition(LaunchConfiguration("record"))),
    ]


def generate_launch_description() -> LaunchDescription:
    default_params = os.path.join(get_package_share_directory(PACKAGE), "config", "params.yaml")
    return LaunchDescription([
        DeclareLaunchArgument("params_file", default_value=default_params,
                              description="node parameters (YAML, `/**/<node>: ros__parameters:` keys)"),
        DeclareLaunchArgument("namespace", default_value="", description="namespace of every node and topic"),
        DeclareLaunchArgument("record", default_value="false", description="also run episode_recorder_node"),
        *(DeclareLaunchArgument(name, default_value="", description=f"{text}; empty: the params file's")
          for name, (_, _, text) in NODE_PARAMETERS.items()),
        OpaqueFunction(function=stack),
    ])
