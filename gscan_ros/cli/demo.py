"""`gscan-ros demo`: bring the stack up, give it one command, show and save the episode.

Runs `gscan-ros bringup`'s nodes in this process with a recorder, sends the command
that the first situation was generated with (so it is satisfiable) or `--command`,
prints the parse, the actions and whether they match the planner's demonstration,
and writes the bag and an animated GIF with the word modules' attention maps.
"""
from __future__ import annotations

import argparse
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from gscan_ros.cli.bringup import Stack, StackOptions, add_stack_arguments
from gscan_ros.errors import GscanError

DEFAULT_OUT = Path("out/demo")


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="run the ROS stack on one command and show the episode",
                              description=__doc__.splitlines()[0])
    add_stack_arguments(p)
    p.add_argument("--command", dest="command_text", default=None,
                   help="command to send (default: the situation's generated one)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"output directory (default: {DEFAULT_OUT})")
    p.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for the episode")
    p.set_defaults(func=run)


@dataclass
class EpisodeResult:
    actions: list = field(default_factory=list)  # Action, last one <eos>
    attention: dict = field(default_factory=dict)  # word -> [mono8 Image per step]
    status: list = field(default_factory=list)


def _operator_node(words: list[str]):
    """A node that sends the command and collects the episode (defined lazily: needs rclpy)."""
    from rclpy.node import Node
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    from gscan_ros.nodes import common
    from msg_adapters import msg_to_action

    class DemoOperator(Node):
        def __init__(self) -> None:
            super().__init__("demo_operator")
            self.result = EpisodeResult()
            self.done = threading.Event()
            self.recorded = threading.Event()
            self.command_pub = self.create_publisher(String, common.COMMAND, common.EVENT_QOS)
            self.create_subscription(String, common.ACTION, self.on_action, common.EVENT_QOS)
            self.create_subscription(String, common.STATUS, self.on_status, common.EVENT_QOS)
            for word in words:
                maps = self.result.attention.setdefault(word, [])
                topic = f"{common.ATTENTION_PREFIX}/{common.topic_token(word)}"
                self.create_subscription(Image, topic, maps.append, common.EVENT_QOS)

        def on_action(self, msg: String) -> None:
            try:
                action = msg_to_action(msg)
            except GscanError:
                return  # not the policy's; the world simulator reports it
            self.result.actions.append(action)
            if action.token == "<eos>":
                self.done.set()

        def on_status(self, msg: String) -> None:
            self.result.status.append(msg.data)
            if msg.data.startswith("episode_recorder_node: recorded episode"):
                self.recorded.set()

    return DemoOperator


def run(args: argparse.Namespace) -> int:
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    from std_msgs.msg import String

    from gscan_ros.nodes.episode_recorder_node import EpisodeRecorderNode
    from gscan_ros.data.sources import episode_source
    from gscan_ros.nodes.policy_node import PolicyNode

    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    options = StackOptions.from_args(args, record=out / "bag", record_images=True)
    dataset = str(args.dataset) if args.dataset else ""
    episode = episode_source(dataset, args.split, args.index, args.seed).next()  # the world's first situation
    command = args.command_text or episode.command

    with Stack(options) as stack:
        graph = stack.node(PolicyNode).policy.parse(command)  # CommandError for a bad --command
        words = list(dict.fromkeys(node.word for node in graph.nodes))
        operator = _operator_node(words)()
        stack.add(operator)
        stack.start()
        _wait(lambda: stack.node(EpisodeRecorderNode).ready, "episode_recorder_node to receive the world state")
        _wait(lambda: operator.command_pub.get_subscription_count() > 0, "parser_node to subscribe to 'command'")
        operator.command_pub.publish(String(data=command))
        if not operator.done.wait(args.timeout):
            raise GscanError(f"no <eos> within {args.timeout:.0f} s; status: {operator.result.status[-3:]}")
        operator.recorded.wait(args.timeout)
        result = operator.result
    _report(graph.command, graph, episode, result, out)  # the command as gSCAN tokens
    return 0


def _wait(condition, what: str, timeout: float = 30.0) -> None:
    """Poll a condition that the stack's executor thread makes true (bounded)."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise GscanError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(0.005)


def _report(command: str, graph, episode, result: EpisodeResult, out: Path) -> None:
    from gscan_ros.world import demonstrate
    from gscan_ros.world.render import render_frames, save_gif
    from msg_adapters import msg_to_attention

    actions = result.actions
    moves = [a.token for a in actions[:-1]]
    try:
        gold = [a.token for a in demonstrate(episode.situation, command)]
    except GscanError as exc:
        gold, why = None, str(exc)
    print(f"command:  {command}")
    print(f"parse ({graph.parser}):")
    print("  " + graph.pretty().replace("\n", "\n  "))
    print(f"actions:  {', '.join(moves) or '(none)'}  [{len(moves)} actions, then <eos>]")
    if gold is None:
        print(f"planner:  no demonstration ({why})")
    else:
        print(f"planner:  {', '.join(gold)}  [{len(gold)} actions]")
        print(f"match:    {'yes, exact match' if moves == gold else 'no'}")

    steps = len(actions)
    attention = [
        {word: msg_to_attention(maps[t]) for word, maps in result.attention.items() if t < len(maps)}
        for t in range(steps)
    ]
    gif = save_gif(render_frames(episode.situation, actions, attention=attention), out / "episode.gif")
    print(f"bag:      {out / 'bag'}")
    print(f"gif:      {gif}")
    print(f"output:   {out.resolve()}")
