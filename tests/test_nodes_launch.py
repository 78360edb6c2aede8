"""launch/gscan.launch.py and config/params.yaml agree with the node executables and parameters.

`launch` and `launch_ros` have no wheels here, so the launch file is run against a stub
of the launch API that records what it builds (`launched`); it is imported and built for
real only where launch_ros is installed.
"""
import importlib.util
import json
import os
import re
import subprocess
import sys
import types
from pathlib import Path
from typing import NamedTuple

import pytest
import yaml

from ros_helpers import Probe, fresh_domain_id, parameters

REPO = Path(__file__).resolve().parents[1]
LAUNCH = REPO / "launch" / "gscan.launch.py"
PARAMS = REPO / "config" / "params.yaml"
FOXGLOVE_LAYOUT = REPO / "config" / "foxglove_layout.json"
NODES = ("world_simulator_node", "parser_node", "policy_node", "episode_recorder_node")
# Launch argument -> the nodes whose parameter of the same name it sets (their declare_parameter calls).
NODE_ARGUMENTS = {
    "checkpoint": {"parser_node", "policy_node"},
    "max_steps": {"policy_node"},
    "seed": {"world_simulator_node"},
    "grid_size": {"world_simulator_node"},
    "bag_dir": {"episode_recorder_node"},
}
ARGUMENTS = {"params_file", "namespace", "record", *NODE_ARGUMENTS}
PARAMS_FILE = "/share/gscan_ros/config/params.yaml"  # the stub's share directory

pytestmark = pytest.mark.e2e  # every node of the stack, built in a probe's context


class Built:
    """What a stubbed launch class was constructed with."""

    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


class LaunchConfiguration(Built):
    def perform(self, context: dict) -> str:
        return context[self.args[0]]


def launch_api_stub() -> dict[str, types.ModuleType]:
    """The modules the launch file imports, with classes that only record their arguments."""
    classes = {name: type(name, (Built,), {}) for name in (
        "LaunchDescription", "DeclareLaunchArgument", "OpaqueFunction", "IfCondition", "Node", "ParameterValue")}
    classes["LaunchConfiguration"] = LaunchConfiguration
    classes["get_package_share_directory"] = lambda package: f"/share/{package}"
    names = {
        "launch": ["LaunchDescription"],
        "launch.actions": ["DeclareLaunchArgument", "OpaqueFunction"],
        "launch.conditions": ["IfCondition"],
        "launch.substitutions": ["LaunchConfiguration"],
        "launch_ros": [],
        "launch_ros.actions": ["Node"],
        "launch_ros.parameter_descriptions": ["ParameterValue"],
        "ament_index_python": [],
        "ament_index_python.packages": ["get_package_share_directory"],
    }
    modules = {}
    for module, members in names.items():
        modules[module] = types.ModuleType(module)
        for member in members:
            setattr(modules[module], member, classes[member])
    return modules


class Launched(NamedTuple):
    arguments: dict[str, Built]  # DeclareLaunchArgument by name
    nodes: dict[str, Built]  # Node by name
    context: dict[str, str]  # every argument's value


def launched(monkeypatch, **arguments: str) -> Launched:
    """Run the launch file against the stub with `arguments` given, the others at their defaults."""
    for name, module in launch_api_stub().items():
        monkeypatch.setitem(sys.modules, name, module)
    spec = importlib.util.spec_from_file_location("gscan_launch_stubbed", LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    entities = module.generate_launch_description().args[0]
    declared = {e.args[0]: e for e in entities if type(e).__name__ == "DeclareLaunchArgument"}
    assert set(arguments) <= set(declared), f"not launch arguments: {set(arguments) - set(declared)}"
    context = {name: e.kwargs["default_value"] for name, e in declared.items()} | arguments
    [opaque] = [e for e in entities if type(e).__name__ == "OpaqueFunction"]
    nodes = opaque.kwargs["function"](context)
    return Launched(declared, {n.kwargs["name"]: n for n in nodes}, context)


def overrides(node: Built, context: dict[str, str]) -> dict[str, tuple[str, type]]:
    """Parameters a node gets after the params file: name -> (value, declared type)."""
    params_file, *given = node.kwargs["parameters"]
    assert params_file == PARAMS_FILE
    return {name: (value.args[0].perform(context), value.kwargs["value_type"])
            for entry in given for name, value in entry.items()}


def params_yaml() -> dict[str, dict]:
    """config/params.yaml: node -> its ros__parameters (the keys are `/**/<node>`)."""
    return {key.removeprefix("/**/"): value["ros__parameters"]
            for key, value in yaml.safe_load(PARAMS.read_text()).items()}


def test_launch_file_starts_every_executable_of_the_package(monkeypatch):
    nodes = launched(monkeypatch).nodes
    assert sorted(nodes) == sorted(NODES)
    assert all(n.kwargs["package"] == "gscan_ros" and n.kwargs["executable"] == name for name, n in nodes.items())
    assert nodes["episode_recorder_node"].kwargs["condition"].args[0].args[0] == "record"
    setup = (REPO / "setup.py").read_text()
    for node in NODES:
        assert f'"{node}"' in setup
        assert (REPO / "scripts" / node).is_file()


def test_launch_file_takes_its_arguments_and_puts_every_node_in_the_namespace(monkeypatch):
    run = launched(monkeypatch, namespace="robot1")
    assert set(run.arguments) == ARGUMENTS
    assert {n.kwargs["namespace"] for n in run.nodes.values()} == {"robot1"}


def test_by_default_every_node_keeps_the_params_file_values(monkeypatch):
    run = launched(monkeypatch)
    assert all(run.context[name] == "" for name in NODE_ARGUMENTS)
    assert all(n.kwargs["parameters"] == [PARAMS_FILE] for n in run.nodes.values())


@pytest.mark.parametrize("argument", sorted(NODE_ARGUMENTS))
def test_each_argument_sets_the_parameter_of_its_nodes_only(monkeypatch, argument):
    """Typed as the node declares it (params.yaml, checked against the nodes below): a
    checkpoint named "7" stays a string, a seed of 7 is an integer."""
    config = params_yaml()
    run = launched(monkeypatch, **{argument: "7"})
    for name, node in run.nodes.items():
        wanted = {argument: ("7", type(config[name][argument]))} if name in NODE_ARGUMENTS[argument] else {}
        assert overrides(node, run.context) == wanted, name


def test_launch_file_builds_where_launch_ros_exists():
    if importlib.util.find_spec("launch_ros") is None:
        pytest.skip("launch_ros is not installed (no wheels); run against a stub above")
    spec = importlib.util.spec_from_file_location("gscan_launch", LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert len(module.generate_launch_description().entities) == len(ARGUMENTS) + 1  # + the nodes


def changed_values(before, after, key=None):
    """(key, before, after) for every value that differs between two JSON documents of the same shape."""
    if isinstance(before, dict):
        assert before.keys() == after.keys()
        for name in before:
            yield from changed_values(before[name], after[name], name)
    elif isinstance(before, list):
        assert len(before) == len(after)
        for item_before, item_after in zip(before, after):
            yield from changed_values(item_before, item_after, key)
    elif before != after:
        yield key, before, after


def test_documented_command_moves_the_foxglove_layout_into_a_namespace(tmp_path):
    """Foxglove panels take absolute topic names, so docs/ros.md gives a command that
    writes a copy of the layout with every topic under the launch namespace."""
    [command] = [line for line in (REPO / "docs" / "ros.md").read_text().splitlines()
                 if line.startswith("sed ") and "$LAYOUT" in line]
    env = dict(os.environ, NS="fleet/robot1", LAYOUT=str(FOXGLOVE_LAYOUT))
    subprocess.run(["bash", "-c", command], cwd=tmp_path, env=env, check=True, timeout=30)
    [written] = tmp_path.iterdir()
    text = FOXGLOVE_LAYOUT.read_text()
    changed = list(changed_values(json.loads(text), json.loads(written.read_text())))
    assert len(changed) == len(re.findall(r'"(?:imageTopic|topicPath)": "/', text)) > 0  # every topic, nothing else
    assert all(key in ("imageTopic", "topicPath") and after == f"/fleet/robot1{before}"
               for key, before, after in changed)


def declared(node) -> set[str]:
    return set(node.list_parameters([], 0).names)


def test_params_yaml_sets_exactly_the_declared_parameters_with_their_types(checkpoint, tmp_path):
    from rclpy.node import Node

    from gscan_ros.nodes.episode_recorder_node import EpisodeRecorderNode
    from gscan_ros.nodes.parser_node import ParserNode
    from gscan_ros.nodes.policy_node import PolicyNode
    from gscan_ros.nodes.world_simulator_node import WorldSimulatorNode

    classes = dict(zip(NODES, (WorldSimulatorNode, ParserNode, PolicyNode, EpisodeRecorderNode)))
    config = params_yaml()
    assert sorted(config) == sorted(NODES)  # keyed `/**/<node>`: any namespace
    paths = {"checkpoint": str(checkpoint), "bag_dir": str(tmp_path / "bag")}
    probe = Probe(fresh_domain_id())
    try:
        builtin = declared(Node("plain", context=probe.context))  # use_sim_time, ...
        for name, cls in classes.items():
            values = dict(config[name])
            values.update({k: v for k, v in paths.items() if k in values})
            # A value of another type than the declared default is refused by rclpy.
            node = cls(context=probe.context, parameter_overrides=parameters(**values))
            assert declared(node) - builtin == set(values), name
            for key, value in values.items():
                assert node.get_parameter(key).value == value, (name, key)
            node.destroy_node()
    finally:
        probe.close()


def test_every_node_offers_and_asks_the_qos_of_the_interface_table(checkpoint, tmp_path):
    """Publishers offer the table's type and QoS; subscribers ask for its type, reliability
    and durability (their own depth); the service has its type (gscan_ros.interface)."""
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    from gscan_ros import interface
    from gscan_ros.nodes.episode_recorder_node import EpisodeRecorderNode
    from gscan_ros.nodes.parser_node import ParserNode
    from gscan_ros.nodes.policy_node import PolicyNode
    from gscan_ros.nodes.world_simulator_node import WorldSimulatorNode

    reliability = {interface.RELIABLE: ReliabilityPolicy.RELIABLE, interface.BEST_EFFORT: ReliabilityPolicy.BEST_EFFORT}
    durability = {interface.VOLATILE: DurabilityPolicy.VOLATILE,
                  interface.TRANSIENT_LOCAL: DurabilityPolicy.TRANSIENT_LOCAL}
    builtin = {"/rosout", "/parameter_events"}
    probe = Probe(fresh_domain_id())
    seen = set()
    try:
        nodes = [
            WorldSimulatorNode(context=probe.context, parameter_overrides=parameters(publish_images=False)),
            ParserNode(context=probe.context, parameter_overrides=parameters(checkpoint=str(checkpoint))),
            PolicyNode(context=probe.context, parameter_overrides=parameters(checkpoint=str(checkpoint))),
            EpisodeRecorderNode(context=probe.context, parameter_overrides=parameters(
                bag_dir=str(tmp_path / "bag"), include_images=True)),
        ]
        for node in nodes:
            for kind, endpoints in (("publisher", node.publishers), ("subscription", node.subscriptions)):
                for endpoint in endpoints:
                    if endpoint.topic_name in builtin:
                        continue
                    entry = interface.endpoint_of(endpoint.topic_name)
                    where = (node.get_name(), kind, endpoint.topic_name)
                    assert entry is not None, where
                    msg_class = endpoint.msg_type  # a generated rosidl class, e.g. std_msgs.msg.String
                    assert f"{msg_class.__module__.split('.')[0]}/msg/{msg_class.__name__}" == entry.type, where
                    qos = endpoint.qos_profile
                    assert qos.reliability == reliability[entry.qos.reliability], where
                    assert qos.durability == durability[entry.qos.durability], where
                    if kind == "publisher":
                        assert qos.depth == entry.qos.depth, where
                    seen.add(entry.name)
            for service in node.services:
                if service.srv_name.endswith(interface.RESET_WORLD.name):
                    assert f"std_srvs/srv/{service.srv_type.__name__}" == interface.RESET_WORLD.type
                    seen.add(interface.RESET_WORLD.name)
    finally:
        probe.close()
    # Every entry is used (attention maps appear with the policy's first step: test_nodes_policy;
    # `episode` records are written into bags by the bag writers, not published).
    assert seen == {e.name for e in interface.ENDPOINTS} - {interface.ATTENTION.name, interface.SIZE_ORDERING.name,
                                                              interface.EPISODE.name}


def test_every_node_reports_its_health_on_diagnostics(checkpoint, tmp_path):
    """One DiagnosticStatus per node on the absolute `/diagnostics`, named by its fully qualified name."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

    from gscan_ros import interface
    from gscan_ros.nodes.common import qos_profile
    from gscan_ros.nodes.episode_recorder_node import EpisodeRecorderNode
    from gscan_ros.nodes.parser_node import ParserNode
    from gscan_ros.nodes.policy_node import PolicyNode
    from gscan_ros.nodes.world_simulator_node import WorldSimulatorNode

    probe = Probe(fresh_domain_id())
    try:
        arrays = probe.record("/diagnostics", DiagnosticArray, qos_profile(interface.DIAGNOSTICS, depth=100))
        for node in (
            WorldSimulatorNode(context=probe.context, parameter_overrides=parameters(publish_images=False)),
            ParserNode(context=probe.context, parameter_overrides=parameters(checkpoint=str(checkpoint))),
            PolicyNode(context=probe.context, parameter_overrides=parameters(checkpoint=str(checkpoint))),
            EpisodeRecorderNode(context=probe.context, parameter_overrides=parameters(bag_dir=str(tmp_path / "bag"))),
        ):
            probe.executor.add_node(node)
        names = {"/world_simulator_node", "/parser_node", "/policy_node", "/episode_recorder_node"}
        statuses = {}

        def all_reported():
            statuses.update((s.name, s) for a in arrays for s in a.status)
            return names <= statuses.keys()

        probe.spin_until(all_reported, what="a DiagnosticStatus of every node")
        assert all(statuses[n].level == DiagnosticStatus.OK and statuses[n].hardware_id == "gscan_ros" for n in names)
        assert {v.key for v in statuses["/policy_node"].values} == {"rejected inputs", "internal errors", "episodes"}
    finally:
        probe.close()
