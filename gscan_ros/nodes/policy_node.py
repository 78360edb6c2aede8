"""policy_node: follows the latest command graph in lock-step with the world simulator.

Episode protocol (docs/ros.md "Lock-step"):
- a new `command_graph` resets the model's module states and starts an episode; one
  still running is preempted (reported on `status`). A graph published before this
  node started (the latched copy a restarted policy receives) is not acted on: a
  command is an instruction for the moment it is given;
- the policy acts on the newest observation, publishes action t, and then acts only
  on an observation *published after* action t. "After" compares the observation's
  DDS source timestamp with the time action t was sent, so a reply that was already
  in flight, or a latched copy, is never mistaken for the result of action t;
- the episode ends with `<eos>`, either the model's or forced after `max_steps`.
Each step also publishes every word module's attention map on `attention/<word>`.
"""
from __future__ import annotations

import time

import numpy as np
from rcl_interfaces.msg import IntegerRange, ParameterDescriptor
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import String, UInt8MultiArray

from gscan_ros.errors import GscanError
from gscan_ros.language.graph import CommandGraph
from gscan_ros.model.runtime import configure_torch
from gscan_ros.nodes.common import (
    ACTION,
    ATTENTION_PREFIX,
    COMMAND_GRAPH,
    EVENT_QOS,
    LATCHED_QOS,
    OBSERVATION,
    VIEWER_QOS,
    StatusReporter,
    describe,
    guarded,
    run,
    topic_token,
)
from gscan_ros.world.types import Action
from msg_adapters import action_to_msg, attention_to_msg, msg_to_graph, msg_to_observation


class PolicyNode(Node):
    def __init__(self, policy=None, **kwargs) -> None:
        """`policy`: an already loaded Policy (bringup, tests); default: load `checkpoint`."""
        super().__init__("policy_node", **kwargs)
        checkpoint = self.declare_parameter(
            "checkpoint", "", describe("policy checkpoint (.pt); empty: the model shipped with gscan_ros")
        ).value
        self._max_steps = self.declare_parameter(
            "max_steps",
            120,
            ParameterDescriptor(
                description="actions per episode before <eos> is forced (read at each episode start)",
                integer_range=[IntegerRange(from_value=1, to_value=100_000, step=1)],
            ),
        )
        self._upsample = self.declare_parameter(
            "attention_upsample", 10, describe("pixels per grid cell in attention/<word> images")
        ).value
        torch_threads = self.declare_parameter(
            "torch_threads", 1, describe("CPU threads for the model; one is fastest for single-step inference")
        ).value
        self.status = StatusReporter(self)
        configure_torch(torch_threads)
        if policy is None:
            from gscan_ros.model.policy import Policy

            policy = Policy.from_checkpoint(checkpoint or None)
        self._policy = policy
        self._action_pub = self.create_publisher(String, ACTION, EVENT_QOS)
        self._attention_pubs: dict[str, object] = {}
        self._observation: np.ndarray | None = None
        self._observation_ns = 0  # DDS source timestamp of the newest observation
        self._sent_ns = -1  # when the last action left this node (-1: never)
        self._graph: CommandGraph | None = None  # the running episode's graph, None when idle
        self._steps = 0
        self._step_cap = 0
        self._started_ns = time.time_ns()
        self.create_subscription(String, COMMAND_GRAPH, self.on_graph, LATCHED_QOS)
        self.create_subscription(UInt8MultiArray, OBSERVATION, self.on_observation, LATCHED_QOS)
        self.get_logger().info(f"policy ready (parser {policy.parser_name})")

    @property
    def policy(self):
        """The loaded Policy (its parser and lexicon are the ones graphs must come from)."""
        return self._policy

    @guarded
    def on_graph(self, msg: String, info: dict) -> None:
        if info["source_timestamp"] < self._started_ns:
            self.get_logger().info("not following the latched command graph published before this node started")
            return
        if self._graph is not None:
            self.status.info(f"preempted {self._graph.command!r} after {self._steps} actions")
            self._graph = None
        try:
            graph = msg_to_graph(msg)
            self._policy.reset(graph)
        except GscanError as exc:
            self.status.reject(f"rejected command graph: {exc}")
            return
        self._graph, self._steps = graph, 0
        self._step_cap = self._max_steps.value
        self.status.info(f"following {graph.command!r}")
        if self._observation is not None and self._observation_ns > self._sent_ns:
            self._act()

    @guarded
    def on_observation(self, msg: UInt8MultiArray, info: dict) -> None:
        observation = msg_to_observation(msg)
        self._observation, self._observation_ns = observation, info["source_timestamp"]
        if self._graph is not None and self._observation_ns > self._sent_ns:
            self._act()

    def _act(self) -> None:
        if self._steps >= self._step_cap:
            action, attention = Action.EOS, {}
            self.status.info(f"{self._graph.command!r} stopped at max_steps={self._step_cap}")
        else:
            out = self._policy.step(self._observation)
            action, attention = out.action, out.attention
        self._sent_ns = time.time_ns()
        self._action_pub.publish(action_to_msg(action))
        self._publish_attention(attention)
        if action is Action.EOS:
            self.status.info(f"done with {self._graph.command!r} after {self._steps} actions")
            self._graph = None
        else:
            self._steps += 1

    def _publish_attention(self, attention: dict[str, np.ndarray]) -> None:
        for word, weights in attention.items():
            pub = self._attention_pubs.get(word)
            if pub is None:
                topic = f"{ATTENTION_PREFIX}/{topic_token(word)}"
                pub = self._attention_pubs[word] = self.create_publisher(Image, topic, VIEWER_QOS)
            pub.publish(attention_to_msg(weights, upsample=self._upsample))


def main(args: list[str] | None = None) -> int:
    return run(PolicyNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
