"""`gscan-ros demo`: bring the stack up, give it commands, show and save the episodes.

Runs `gscan-ros bringup`'s nodes in this process with a recorder. For each of
`--episodes` situations (the next one after a `reset_world` call) it sends the command
that the situation was generated with (so it is satisfiable) or `--command`, prints the
parse, the actions and whether they match the planner's demonstration, and writes one
bag with every episode and an animated GIF per episode with the word modules'
attention maps.
"""
from __future__ import annotations

import argparse
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from gscan_ros.cli.args import float_in, positive_int
from gscan_ros.cli.bringup import Stack, StackOptions, add_stack_arguments
from gscan_ros.errors import GscanError

DEFAULT_OUT_ROOT = Path("out/demo")
MAX_TIMEOUT_S = 86_400.0  # threading waits overflow on huge timeouts


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="run the ROS stack on one command and show the episode",
                              description=__doc__.splitlines()[0])
    add_stack_arguments(p)
    p.add_argument("--command", dest="command_text", default=None,
                   help="command to send (default: the situation's generated one)")
    p.add_argument("--out", type=Path, default=None,
                   help=f"output directory, new or empty (default: a new {DEFAULT_OUT_ROOT}/<date>_<time>)")
    p.add_argument("--overwrite", action="store_true", help="replace the bag and GIFs of an earlier demo in --out")
    p.add_argument("--episodes", type=positive_int, default=3,
                   help="episodes to run, each after a reset_world (default: 3)")
    p.add_argument("--timeout", type=float_in(0, MAX_TIMEOUT_S, low_open=True), default=120.0,
                   help="seconds to wait for each episode (default: 120)")
    p.set_defaults(func=run)


@dataclass
class EpisodeResult:
    actions: list = field(default_factory=list)  # Action, last one <eos>
    attention: dict = field(default_factory=dict)  # word -> [mono8 Image per step]
    status: list = field(default_factory=list)


def _operator_node(words: list[str]):
    """A node that sends commands, resets the world and collects episodes (defined lazily: needs rclpy)."""
    from rclpy.node import Node
    from sensor_msgs.msg import Image
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    from gscan_ros.nodes import common
    from msg_adapters import msg_to_action

    class DemoOperator(Node):
        def __init__(self) -> None:
            super().__init__("demo_operator")
            self.result = EpisodeResult()
            self.done = threading.Event()
            self.recorded = 0  # episodes the recorder reported
            self.command_pub = self.create_publisher(String, common.COMMAND, common.EVENT_QOS)
            self.reset_client = self.create_client(Trigger, common.RESET_WORLD)
            self.create_subscription(String, common.ACTION, self.on_action, common.EVENT_QOS)
            self.create_subscription(String, common.STATUS, self.on_status, common.EVENT_QOS)
            for word in words:
                topic = f"{common.ATTENTION_PREFIX}/{common.topic_token(word)}"
                self.create_subscription(Image, topic, self._attention_sink(word), common.EVENT_QOS)

        def _attention_sink(self, word: str):
            return lambda msg: self.result.attention.setdefault(word, []).append(msg)

        def start_episode(self) -> EpisodeResult:
            self.result = EpisodeResult()
            self.done.clear()
            return self.result

        def reset_world(self, timeout: float) -> None:
            if not self.reset_client.wait_for_service(timeout_sec=timeout):
                raise GscanError("reset_world service not available")
            future = self.reset_client.call_async(Trigger.Request())
            deadline = time.monotonic() + timeout
            while not future.done():
                if time.monotonic() > deadline:
                    raise GscanError(f"reset_world did not answer within {timeout:.0f} s")
                time.sleep(0.005)
            if not future.result().success:
                raise GscanError(f"reset_world failed: {future.result().message}")

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
                self.recorded += 1

    return DemoOperator


def run(args: argparse.Namespace) -> int:
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    from std_msgs.msg import String

    from gscan_ros.data.sources import episode_source
    from gscan_ros.nodes.episode_recorder_node import EpisodeRecorderNode
    from gscan_ros.nodes.policy_node import PolicyNode

    out = args.out or DEFAULT_OUT_ROOT / time.strftime("%Y%m%d_%H%M%S")
    if out.exists() and not out.is_dir():
        raise GscanError(f"--out {out} is a file, not a directory")
    if out.exists() and any(out.iterdir()) and not args.overwrite:
        raise GscanError(f"--out {out} is not empty; pass --overwrite to replace an earlier demo there")
    out.mkdir(parents=True, exist_ok=True)
    options = StackOptions.from_args(args, record=out / "bag", record_images=True)
    dataset = str(args.dataset) if args.dataset else ""
    source = episode_source(dataset, args.split, args.index, args.seed, args.grid_size)  # the world node's sequence
    episodes = [source.next() for _ in range(args.episodes)]

    matched = 0
    with Stack(options) as stack:
        policy = stack.node(PolicyNode).policy
        graphs = [policy.parse(args.command_text or e.command) for e in episodes]  # CommandError for --command
        words = list(dict.fromkeys(node.word for g in graphs for node in g.nodes))
        operator = _operator_node(words)()
        stack.add(operator)
        stack.start()
        _wait(lambda: stack.node(EpisodeRecorderNode).ready, "episode_recorder_node to receive the world state")
        _wait(lambda: operator.command_pub.get_subscription_count() > 0, "parser_node to subscribe to 'command'")
        for i, (episode, graph) in enumerate(zip(episodes, graphs), start=1):
            if i > 1:
                operator.reset_world(args.timeout)
            result = operator.start_episode()
            operator.command_pub.publish(String(data=graph.typed or graph.command))  # as typed: parser_node maps it
            if not operator.done.wait(args.timeout):
                raise GscanError(f"no <eos> within {args.timeout:.0f} s; status: {result.status[-3:]}")
            _wait(lambda: operator.recorded >= i, f"the recorder to store episode {i}", args.timeout)
            print(f"--- episode {i} of {len(episodes)}")
            matched += _report(graph, episode, result, out / f"episode_{i}.gif")
    print(f"matched the planner in {matched} of {len(episodes)} episodes")
    print(f"bag:      {out / 'bag'}")
    print(f"output:   {out.resolve()}")
    return 0


def _wait(condition, what: str, timeout: float = 30.0) -> None:
    """Poll a condition that the stack's executor thread makes true (bounded)."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise GscanError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(0.005)


def _report(graph, episode, result: EpisodeResult, gif_path: Path) -> bool:
    """Print one episode, write its GIF; True when the actions equal the planner's."""
    from gscan_ros.world import demonstrate
    from gscan_ros.world.render import render_frames, save_gif
    from msg_adapters import msg_to_attention

    actions = result.actions
    moves = [a.token for a in actions[:-1]]
    try:
        gold = [a.token for a in demonstrate(episode.situation, graph.command)]
    except GscanError as exc:
        gold, why = None, str(exc)
    if graph.typed is not None:
        from gscan_ros.language import canonicalize

        print(f"typed:    {graph.typed}")
        for mapping in canonicalize(graph.typed).mappings:
            print(f"          {mapping}")
    print(f"command:  {graph.command}")
    print(f"parse ({graph.parser}):")
    print("  " + graph.pretty().replace("\n", "\n  "))
    print(f"actions:  {', '.join(moves) or '(none)'}  [{len(moves)} actions, then <eos>]")
    if gold is None:
        print(f"planner:  no demonstration ({why})")
    else:
        print(f"planner:  {', '.join(gold)}  [{len(gold)} actions]")
        print(f"match:    {'yes, exact match' if moves == gold else 'no'}")
    attention = [
        {word: msg_to_attention(maps[t], grid_size=episode.situation.grid_size)
         for word, maps in result.attention.items() if t < len(maps)}
        for t in range(len(actions))
    ]
    gif = save_gif(render_frames(episode.situation, actions, attention=attention), gif_path)
    print(f"gif:      {gif}")
    return moves == gold
