"""launch/gscan.launch.py and config/params.yaml agree with the node executables and parameters.

`launch` has no wheels here, so the launch file is checked statically (it is imported
and built only where launch_ros is installed).
"""
import ast
import importlib.util
from pathlib import Path

import pytest
import yaml

from gscan_ros.nodes.harness import Probe, fresh_domain_id

from ros_helpers import parameters, tiny_checkpoint

REPO = Path(__file__).resolve().parents[1]
LAUNCH = REPO / "launch" / "gscan.launch.py"
PARAMS = REPO / "config" / "params.yaml"
NODES = ("world_simulator_node", "parser_node", "policy_node", "episode_recorder_node")


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


def test_launch_file_builds_where_launch_ros_exists():
    if importlib.util.find_spec("launch_ros") is None:
        pytest.skip("launch_ros is not installed (no wheels); checked statically above")
    spec = importlib.util.spec_from_file_location("gscan_launch", LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert len(module.generate_launch_description().entities) >= len(NODES)


def declared(node) -> set[str]:
    return set(node.list_parameters([], 0).names)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return tiny_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt")


def test_params_yaml_sets_exactly_the_declared_parameters_with_their_types(checkpoint, tmp_path):
    from rclpy.node import Node

    from gscan_ros.nodes.episode_recorder_node import EpisodeRecorderNode
    from gscan_ros.nodes.parser_node import ParserNode
    from gscan_ros.nodes.policy_node import PolicyNode
    from gscan_ros.nodes.world_simulator_node import WorldSimulatorNode

    classes = dict(zip(NODES, (WorldSimulatorNode, ParserNode, PolicyNode, EpisodeRecorderNode)))
    config = yaml.safe_load(PARAMS.read_text())
    assert sorted(config) == sorted(NODES)
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
