"""launch/gscan.launch.py and config/params.yaml agree with the node executables and parameters.

`launch` has no wheels here, so the launch file is checked statically (it is imported
and built only where launch_ros is installed).
"""
import ast
import importlib.util
from pathlib import Path

import pytest
import yaml

from ros_helpers import Probe, fresh_domain_id, parameters

REPO = Path(__file__).resolve().parents[1]
LAUNCH = REPO / "launch" / "gscan.launch.py"
PARAMS = REPO / "config" / "params.yaml"
NODES = ("world_simulator_node", "parser_node", "policy_node", "episode_recorder_node")

pytestmark = pytest.mark.e2e  # every node of the stack, built in a probe's context


def launch_node_kwargs() -> list[dict]:
    """Keyword arguments of every `Node(...)` call in the launch file that are (named) constants."""
    tree = ast.parse(LAUNCH.read_text())
    constants = {t.id: n.value.value for n in tree.body if isinstance(n, ast.Assign)
                 and isinstance(n.value, ast.Constant) for t in n.targets}

    def value(node):
        if isinstance(node, ast.Constant):
            return node.value
        return constants.get(getattr(node, "id", None))

    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", None) == "Node"]
    return [{k.arg: value(k.value) for k in c.keywords} for c in calls]


def test_launch_file_starts_every_executable_of_the_package():
    kwargs = launch_node_kwargs()
    assert sorted(k["executable"] for k in kwargs) == sorted(NODES)
    assert all(k["package"] == "gscan_ros" and k["name"] == k["executable"] for k in kwargs)
    setup = (REPO / "setup.py").read_text()
    for node in NODES:
        assert f'"{node}"' in setup
        assert (REPO / "scripts" / node).is_file()


def launch_arguments() -> set[str]:
    """Names of the launch file's DeclareLaunchArgument(...) calls."""
    tree = ast.parse(LAUNCH.read_text())
    return {c.args[0].value for c in ast.walk(tree) if isinstance(c, ast.Call)
            and getattr(c.func, "id", None) == "DeclareLaunchArgument"}


def test_launch_file_takes_a_params_file_a_namespace_a_checkpoint_and_record():
    assert launch_arguments() == {"params_file", "namespace", "checkpoint", "record"}
    assert all("namespace" in k and "parameters" in k for k in launch_node_kwargs())


def test_launch_file_builds_where_launch_ros_exists():
    if importlib.util.find_spec("launch_ros") is None:
        pytest.skip("launch_ros is not installed (no wheels); checked statically above")
    spec = importlib.util.spec_from_file_location("gscan_launch", LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert len(module.generate_launch_description().entities) == len(launch_arguments()) + 1  # + the nodes


def declared(node) -> set[str]:
    return set(node.list_parameters([], 0).names)


def test_params_yaml_sets_exactly_the_declared_parameters_with_their_types(checkpoint, tmp_path):
    from rclpy.node import Node

    from gscan_ros.nodes.episode_recorder_node import EpisodeRecorderNode
    from gscan_ros.nodes.parser_node import ParserNode
    from gscan_ros.nodes.policy_node import PolicyNode
    from gscan_ros.nodes.world_simulator_node import WorldSimulatorNode

    classes = dict(zip(NODES, (WorldSimulatorNode, ParserNode, PolicyNode, EpisodeRecorderNode)))
    config = {key.removeprefix("/**/"): value for key, value in yaml.safe_load(PARAMS.read_text()).items()}
    assert sorted(config) == sorted(NODES)  # keyed `/**/<node>`: any namespace
    paths = {"checkpoint": str(checkpoint), "bag_dir": str(tmp_path / "bag")}
    probe = Probe(fresh_domain_id())
    try:
        builtin = declared(Node("plain", context=probe.context))  # use_sim_time, ...
        for name, cls in classes.items():
            values = dict(config[name]["ros__parameters"])
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
    from gscan_ros.data.bag_schema import msg_type_name
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
                    assert msg_type_name(endpoint.msg_type) == entry.type, where
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
    # Every entry is used (attention maps appear with the policy's first step: test_nodes_policy).
    assert seen == {e.name for e in interface.ENDPOINTS} - {interface.ATTENTION.name, interface.SIZE_ORDERING.name}
