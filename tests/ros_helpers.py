"""Test support for ROS: node processes, a probe node, parameters, an in-process stack.

Used by the node and end-to-end tests. The node-process rules for DDS on shared machines
(loopback, own domain, fast-discovery profile, process groups) live in
`gscan_ros.nodes.processes`, shared with the ROS benches; waits here are bounded and keyed
on messages or graph state (never fixed sleeps).

Importing this module sets ROS_AUTOMATIC_DISCOVERY_RANGE, FASTRTPS_DEFAULT_PROFILES_FILE
and ROS_LOG_DIR for the current process when unset (`join_local_graph`), so import it
before any rclpy.init.
"""
from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from gscan_ros.nodes.processes import (  # noqa: F401  (NodeProcess, VENV_BIN, ros_env: for the tests)
    VENV_BIN,
    NodeProcess,
    fresh_domain_id,
    join_local_graph,
    ros_env,
)

STARTUP_TIMEOUT = 90.0  # node processes import torch on 2 busy cores
TIMEOUT = 30.0

# This process joins the same DDS graph as the node processes it starts.
join_local_graph()


class Probe:
    """A node in the test process: records topics, publishes, and waits on graph state."""

    def __init__(self, domain_id: int, name: str = "test_probe", namespace: str = ""):
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = Node(name, namespace=namespace, context=self.context)
        self.namespace = self.node.get_namespace()  # relative topic names resolve in it
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.received: dict[str, list] = defaultdict(list)
        self.created_ns = time.time_ns()  # messages published before belong to earlier tests

    def record(self, topic: str, msg_type, qos, since_ns: int | None = None, *, raw: bool = False) -> list:
        """Subscribe and keep the messages of `topic` in `self.received[topic]` that were
        published at or after `since_ns` (source timestamp, ns), by default the probe's
        creation; `raw` keeps their CDR bytes, for msg_adapters to decode. In a shared domain
        a participant still shutting down from an earlier test can serve its older latched
        samples to a new subscription; they are not this test's."""
        kept = self.received[topic]
        since_ns = self.created_ns if since_ns is None else since_ns

        def keep_recent(msg, info) -> None:
            if info["source_timestamp"] >= since_ns:
                kept.append(msg)

        self.node.create_subscription(msg_type, topic, keep_recent, qos, raw=raw)
        return kept

    def spin_until(self, predicate: Callable[[], bool], timeout: float = TIMEOUT, what: str = "condition") -> None:
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")
            self.executor.spin_once(timeout_sec=0.02)

    def wait_for_endpoints(self, expected: dict[str, set[str]], timeout: float = STARTUP_TIMEOUT,
                           kind: str = "subscriptions") -> None:
        """Wait until each topic has an endpoint of `kind` from each named node."""
        info = self.node.get_subscriptions_info_by_topic if kind == "subscriptions" else (
            self.node.get_publishers_info_by_topic)

        def ready() -> bool:
            return all(nodes <= {i.node_name for i in info(topic)} for topic, nodes in expected.items())

        self.spin_until(ready, timeout, f"{kind} {expected}")

    def spin_in_background(self) -> None:
        """Spin the probe's executor (and every node added to it) in a thread until `close()`:
        a stack in this process, for a GscanCommander that spins itself in the test's thread."""
        import threading

        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name="probe-spin", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        """Spin until `close()` asks: the thread ends before the executor is shut down, as
        rclpy's shutdown from another thread can pull a guard condition from under a wait."""
        from rclpy.executors import ExternalShutdownException

        try:
            while not self._stop.is_set():
                self.executor.spin_once(timeout_sec=0.05)
        except ExternalShutdownException:
            pass

    def publish_when_matched(self, publisher, msg, subscribers: int = 1, timeout: float = TIMEOUT) -> None:
        self.spin_until(lambda: publisher.get_subscription_count() >= subscribers, timeout,
                        f"{subscribers} subscriber(s) on {publisher.topic_name}")
        publisher.publish(msg)

    def close(self) -> None:
        """Destroy every node spun here (the tests' nodes too) and the context: no participant
        lingers to serve its latched samples to the next test in the same domain."""
        nodes = [*self.executor.get_nodes(), self.node]
        if getattr(self, "_thread", None) is not None:
            self._stop.set()
            self._thread.join(timeout=10)
        self.executor.shutdown()
        for node in dict.fromkeys(nodes):
            node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def parameters(**values) -> list:
    """rclpy parameter overrides for constructing a node in-process."""
    from rclpy.parameter import Parameter

    return [Parameter(name, value=value) for name, value in values.items()]


def source_info(t_ns: int | None = None) -> dict:
    """The MessageInfo a subscription callback gets, for calling node callbacks directly."""
    return {"source_timestamp": time.time_ns() if t_ns is None else t_ns}


class ScriptedPolicy:
    """A stand-in for Policy in policy_node: plays `script` (its last action repeats);
    records resets and the observations it saw."""

    parser_name = "semantic"
    grid_size = 6
    observation_shape = (6, 6, 16)

    def __init__(self, script, on_step=None):
        self.script, self.resets, self.seen, self._t = list(script), [], [], 0
        self.on_step = on_step  # called with the step number before each step (e.g. to reset the world)

    def require_observation(self, shape, what):
        from gscan_ros.model.policy import Policy

        Policy.require_observation(self, shape, what)  # the real rule, on this stand-in's grid

    def require_grid(self, grid_size, what):
        from gscan_ros.model.policy import require_grid

        require_grid(grid_size, self.grid_size, what)

    def reset(self, graph):
        from gscan_ros.errors import GraphError

        if graph.parser != self.parser_name:
            raise GraphError(f"graph comes from the {graph.parser!r} parser")
        self.resets.append(graph.command)
        self._t = 0

    def step(self, observation):
        import numpy as np

        from gscan_ros.model.policy import StepOutput

        if self.on_step is not None:
            self.on_step(self._t)
        self.seen.append(np.array(observation))
        action = self.script[min(self._t, len(self.script) - 1)]
        self._t += 1
        eye = np.eye(6, dtype=np.float32)
        return StepOutput(action, {"red": eye, "while spinning": eye[::-1].copy()})


def in_process_stack(probe: Probe, checkpoint: Path, script, *, max_steps: int | None = None,
                     bag_dir: Path | None = None, on_step=None, seed: int = 3, names: dict[str, str] | None = None):
    """A stack in the probe's context, spun in the background: world_simulator_node (`seed`,
    no images), parser_node (`checkpoint`), policy_node playing `script` (ScriptedPolicy)
    and, with `bag_dir`, episode_recorder_node. `max_steps` None keeps policy_node's default
    (`gscan_ros.model.policy.MAX_STEPS`); `names` renames nodes as `--ros-args -r
    __node:=NAME` does (keys world, parser, policy_node, recorder). Returns the nodes by
    name (and `policy`)."""
    from types import SimpleNamespace

    from gscan_ros.nodes.episode_recorder_node import EpisodeRecorderNode
    from gscan_ros.nodes.parser_node import ParserNode
    from gscan_ros.nodes.policy_node import PolicyNode
    from gscan_ros.nodes.world_simulator_node import WorldSimulatorNode

    context = probe.context
    policy = ScriptedPolicy(script, on_step)
    names = names or {}

    def rename(key: str) -> dict:
        return {"cli_args": ["--ros-args", "-r", f"__node:={names[key]}"]} if key in names else {}

    stack = SimpleNamespace(
        policy=policy,
        world=WorldSimulatorNode(context=context, parameter_overrides=parameters(seed=seed, publish_images=False),
                                 **rename("world")),
        parser=ParserNode(context=context, parameter_overrides=parameters(checkpoint=str(checkpoint)),
                          **rename("parser")),
        policy_node=PolicyNode(policy, context=context, parameter_overrides=parameters(
            **({} if max_steps is None else {"max_steps": max_steps})), **rename("policy_node")),
        recorder=None,
    )
    if bag_dir is not None:
        stack.recorder = EpisodeRecorderNode(context=context, parameter_overrides=parameters(bag_dir=str(bag_dir)),
                                             **rename("recorder"))
    for node in (stack.world, stack.parser, stack.policy_node, stack.recorder):
        if node is not None:
            probe.executor.add_node(node)
    probe.spin_in_background()
    return stack


class AllTopicsRecorder:
    """What `ros2 bag record -a` does, written with the third-party `rosbags` library (no
    gscan_ros code): every topic of the graph, discovered as it appears, subscribed with
    the QoS its publishers offer (reliable, transient local when they all are), stored as
    rosbag2 (metadata.yaml version 9, MCAP, CDR) at each message's DDS source timestamp,
    which is the publish time Jazzy's recorder stores. Call `discover()` while the graph
    forms and `close()` to finish the bag."""

    def __init__(self, node: Node, path: Path):
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        self.node = node
        self.typestore = get_typestore(Stores.ROS2_JAZZY)
        self.writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        self.writer.open()
        self.connections: dict[str, object] = {}
        self.messages = 0

    def discover(self) -> None:
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        for topic, types in self.node.get_topic_names_and_types():
            if topic in self.connections or topic in ("/rosout", "/parameter_events"):
                continue
            offered = self.node.get_publishers_info_by_topic(topic)
            if not offered:
                continue
            latched = all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in offered)
            qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
            if any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in offered):
                qos.reliability = ReliabilityPolicy.BEST_EFFORT
            msg_type = types[0]
            connection = self.connections[topic] = self.writer.add_connection(topic, msg_type,
                                                                             typestore=self.typestore)
            package, _, name = msg_type.split("/")
            msg_class = getattr(__import__(f"{package}.msg", fromlist=[name]), name)
            self.node.create_subscription(msg_class, topic, self._sink(connection), qos, raw=True)

    def _sink(self, connection):
        def write(data: bytes, info: dict) -> None:
            self.writer.write(connection, info["source_timestamp"], data)
            self.messages += 1

        return write

    def close(self) -> None:
        self.writer.close()
