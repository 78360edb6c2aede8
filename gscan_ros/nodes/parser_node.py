"""parser_node: English command on `command` -> CommandGraph JSON on `command_graph` (latched).

A command the parser cannot handle (unknown word, empty, not in the gSCAN grammar)
is reported on `status` and as a REJECTED episode on `episode_status` (so a client
learns the fate of every command from one typed topic) and publishes no graph, so the
policy keeps its current episode. Commands longer than `max_command_chars` are rejected before parsing, so
megabyte strings cost no parser time. The subscription takes the serialized message,
so invalid UTF-8 and embedded NULs reach the language layer's `command_text` check
(the CLI's) instead of being replaced or cut off by rclpy.

A paraphrase ("Push the small blue cylinder") is parsed as the gSCAN command it means
(the language layer's `canonicalize`, inside every built-in parser); what was
understood — the canonical command and each rewrite, e.g. `large → big (WordNet
synonym in large.a.01)` — is logged and published on `status`, and the graph carries
the typed text (`typed`) for the episode recorder.
"""
from __future__ import annotations

import time

from actionlib_msgs.msg import GoalStatus
from rclpy.node import Node
from std_msgs.msg import String

from gscan_ros import interface
from gscan_ros.episode_status import REJECTED, EpisodeStatus
from gscan_ros.errors import CommandError, GscanError
from gscan_ros.language.canonical import canonicalize
from gscan_ros.language.parser import Parser
from gscan_ros.language.registry import BUILTIN_PARSERS, get_parser
from gscan_ros.language.synonyms import synonym_table
from gscan_ros.language.tokens import command_text
from gscan_ros.model.checkpoint import checkpoint_lexicon, read_checkpoint
from gscan_ros.model.policy import default_checkpoint_path
from gscan_ros.nodes.common import (
    COMMAND,
    COMMAND_GRAPH,
    COMMAND_REFUSAL,
    EPISODE_STATUS,
    StatusReporter,
    command_refusal,
    describe,
    guarded,
    qos_profile,
    quote,
    run,
    validated,
)
from msg_adapters import cdr_to_string_bytes, episode_status_to_cdr, graph_to_cdr


class ParserNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("parser_node", **kwargs)
        self.declare_parameter(
            "checkpoint", "", describe("policy checkpoint whose parser and word lexicon to use; empty: the shipped "
                                       "model (a change loads it; a bad one is refused)")
        )
        self.declare_parameter(
            "parser", "", describe("parse type; empty: the checkpoint's (the policy rejects graphs of another parser)",
                                   constraints=f"empty or one of: {', '.join(BUILTIN_PARSERS)}")
        )
        self.declare_parameter(
            "max_command_chars", 1000, describe("longer commands are rejected unparsed", int_range=(1, 1_000_000))
        )
        self.status = StatusReporter(self)
        self._parser, parser = self._load_parser({})  # a bad checkpoint is a start-up error (run() reports it)
        self._next_parser: Parser | None = None  # validated by the on-set callback, installed after the set
        try:
            synonym_table()  # built now, so the first paraphrase is not a second late
        except GscanError as exc:
            self.get_logger().warning(f"WordNet synonyms unavailable, only gSCAN words are understood: {exc}")
        self._graph_pub = self.create_publisher(String, COMMAND_GRAPH, qos_profile(interface.COMMAND_GRAPH))
        self._episode_pub = self.create_publisher(GoalStatus, EPISODE_STATUS, qos_profile(interface.EPISODE_STATUS))
        self._rejected = 0  # numbers the ids of rejected commands
        self.create_subscription(String, COMMAND, self.on_command, qos_profile(interface.COMMAND), raw=True)
        self.add_on_set_parameters_callback(validated(self._check_parameters))
        self.add_post_set_parameters_callback(self._apply_parameters)
        self.get_logger().info(f"parsing commands with the {parser} parser")

    def _load_parser(self, changes: dict) -> tuple[Parser, str]:
        """The parser that `checkpoint` and `parser` (with `changes` applied) name, and its name."""
        checkpoint = changes.get("checkpoint", self.get_parameter("checkpoint").value)
        name = changes.get("parser", self.get_parameter("parser").value)
        if name and name not in BUILTIN_PARSERS:
            raise CommandError(f"parser must be empty or one of {', '.join(BUILTIN_PARSERS)}, got {name!r}")
        ckpt = read_checkpoint(checkpoint or default_checkpoint_path())
        name = name or str(ckpt["parser"])
        return get_parser(name, checkpoint_lexicon(ckpt)), name

    def _check_parameters(self, changes: dict) -> None:
        """A new checkpoint or parser is loaded here, so a bad one is refused with the reason."""
        self._next_parser = None
        if "checkpoint" in changes or "parser" in changes:
            self._next_parser, _ = self._load_parser(changes)

    @guarded
    def _apply_parameters(self, parameters: list) -> None:
        if self._next_parser is not None:
            self._parser, self._next_parser = self._next_parser, None
            self.status.info(f"parsing commands with the {self._parser.name} parser "
                             f"of {self.get_parameter('checkpoint').value or 'the shipped model'}")

    @guarded
    def on_command(self, cdr: bytes) -> None:
        """`cdr`: the serialized std_msgs/String (see the module docstring)."""
        try:
            data = cdr_to_string_bytes(cdr)
        except GscanError as exc:  # no command to quote, but a command all the same: reported like one
            self._reject(f"{COMMAND_REFUSAL} (an unreadable std_msgs/String): {exc}")
            return
        limit = self.get_parameter("max_command_chars").value
        try:
            text = command_text(data)
            if len(text) > limit:
                raise CommandError(f"longer than max_command_chars={limit}")
            canonical = canonicalize(text)
            graph = self._parser.parse(text)
        except GscanError as exc:
            self._reject(f"{command_refusal(_shown(data))}: {exc}")
            return
        self._graph_pub.publish(graph_to_cdr(graph))
        if canonical.mappings:  # logged too
            self.status.info(f"{canonical.explain()} ({len(graph.nodes)} nodes)")
        else:
            self.get_logger().info(f"parsed {quote(text)} into {len(graph.nodes)} nodes")

    def _reject(self, line: str) -> None:
        """A command not parsed: on `status` for people, REJECTED on `episode_status` for programs."""
        self.status.reject(line)
        self._rejected += 1
        self._episode_pub.publish(episode_status_to_cdr(EpisodeStatus(
            f"{self.get_fully_qualified_name()}/{self._rejected}", time.time_ns(), REJECTED, line)))


def _shown(data: bytes) -> str:
    """A rejected command for a status line: its text, with undecodable bytes as \\xNN."""
    return data.decode("utf-8", "backslashreplace")


def main(args: list[str] | None = None) -> int:
    return run(ParserNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
