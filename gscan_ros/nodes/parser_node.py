"""parser_node: English command on `command` -> CommandGraph JSON on `command_graph` (latched).

A command the parser cannot handle (unknown word, empty, not in the gSCAN grammar)
is reported on `status` and publishes nothing, so the policy keeps its current
episode. Commands longer than `max_command_chars` are rejected before parsing, so
megabyte strings cost no parser time.
"""
from __future__ import annotations

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from std_msgs.msg import String

from gscan_ros.errors import GscanError
from gscan_ros.language.registry import get_parser
from gscan_ros.model.checkpoint import checkpoint_lexicon, read_checkpoint
from gscan_ros.model.policy import default_checkpoint_path
from gscan_ros.nodes.common import (
    COMMAND,
    COMMAND_GRAPH,
    EVENT_QOS,
    LATCHED_QOS,
    StatusReporter,
    describe,
    guarded,
    quote,
    run,
)
from msg_adapters import graph_to_msg

PARSERS = ("semantic", "constituency", "dependency")


class ParserNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("parser_node", **kwargs)
        checkpoint = self.declare_parameter(
            "checkpoint",
            "",
            describe("policy checkpoint whose parser and word lexicon to use; empty: the shipped model"),
        ).value
        parser = self.declare_parameter(
            "parser",
            "",
            ParameterDescriptor(
                description="parse type; empty: the checkpoint's (the policy rejects graphs of another parser)",
                additional_constraints=f"empty or one of: {', '.join(PARSERS)}",
                read_only=True,
            ),
        ).value
        self._max_chars = self.declare_parameter(
            "max_command_chars", 1000, describe("longer commands are rejected unparsed", read_only=False)
        )
        self.status = StatusReporter(self)
        ckpt = read_checkpoint(checkpoint or default_checkpoint_path())
        parser = parser or str(ckpt["parser"])
        self._parser = get_parser(parser, checkpoint_lexicon(ckpt))
        self._graph_pub = self.create_publisher(String, COMMAND_GRAPH, LATCHED_QOS)
        self.create_subscription(String, COMMAND, self.on_command, EVENT_QOS)
        self.get_logger().info(f"parsing commands with the {parser} parser")

    @guarded
    def on_command(self, msg: String) -> None:
        limit = self._max_chars.value
        if len(msg.data) > limit:
            self.status.reject(f"rejected command {quote(msg.data)}: longer than max_command_chars={limit}")
            return
        try:
            graph = self._parser.parse(msg.data)
        except GscanError as exc:
            self.status.reject(f"rejected command {quote(msg.data)}: {exc}")
            return
        self._graph_pub.publish(graph_to_msg(graph))
        self.get_logger().info(f"parsed {quote(msg.data)} into {len(graph.nodes)} nodes")


def main(args: list[str] | None = None) -> int:
    return run(ParserNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
