"""`gscan-ros bringup`: the gscan_ros nodes in one process, for machines without `ros2 launch`.

The same node classes and parameters as `launch/gscan.launch.py`, spun by one
MultiThreadedExecutor. Talk to it like to the launched stack, e.g. with
`ros2 topic pub /command std_msgs/msg/String "{data: 'walk to a red circle'}" --once`.
"""
from __future__ import annotations

import argparse
import threading
from dataclasses import dataclass
from pathlib import Path

from gscan_ros.cli.args import int_in, nonnegative_int, positive_int
from gscan_ros.world.types import GRID_SIZE, SUPPORTED_GRID_SIZES

DEFAULT_MAX_STEPS = 120


def add_stack_arguments(parser: argparse.ArgumentParser) -> None:
    """Options shared by `bringup` and `demo`."""
    parser.add_argument("--checkpoint", type=Path, default=None, help="policy checkpoint (default: the shipped model)")
    parser.add_argument("--parser", default="", help="parse type (default: the checkpoint's)")
    source = parser.add_argument_group("situations (a dataset split, else random sampling)")
    source.add_argument("--dataset", type=Path, default=None, help="dataset.txt, its directory, or a bag")
    source.add_argument("--split", default="test", help="dataset split (default: test)")
    source.add_argument("--index", type=nonnegative_int, default=0, help="first example of the split (default: 0)")
    source.add_argument("--seed", type=nonnegative_int, default=0,
                        help="first sampling seed without --dataset (default: 0)")
    source.add_argument("--grid-size", type=int_in(SUPPORTED_GRID_SIZES[0], SUPPORTED_GRID_SIZES[-1]),
                        default=GRID_SIZE, help=f"grid side of sampled worlds without --dataset (default: {GRID_SIZE})")
    parser.add_argument("--max-steps", type=positive_int, default=DEFAULT_MAX_STEPS, help="action cap per episode")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "bringup",
        help="run the ROS 2 nodes in one process",
        description=__doc__.splitlines()[0],
    )
    add_stack_arguments(p)
    p.add_argument("--record", type=Path, default=None, metavar="BAG_DIR",
                   help="also record episodes to this bag (a new directory, or an empty one)")
    p.add_argument("--overwrite", action="store_true",
                   help="with --record: replace a bag already at BAG_DIR (only the bag's own files)")
    p.set_defaults(func=run)


@dataclass(frozen=True)
class StackOptions:
    checkpoint: Path | None = None
    parser: str = ""
    dataset: Path | None = None
    split: str = "test"
    index: int = 0
    seed: int = 0
    grid_size: int = GRID_SIZE
    max_steps: int = DEFAULT_MAX_STEPS
    record: Path | None = None
    record_images: bool = False
    overwrite: bool = False

    @classmethod
    def from_args(cls, args: argparse.Namespace, **overrides) -> "StackOptions":
        fields = {name: getattr(args, name) for name in cls.__dataclass_fields__ if hasattr(args, name)}
        return cls(**{**fields, **overrides})


class Stack:
    """The nodes of one stack in one rclpy context, spun by a MultiThreadedExecutor.

    Use as a context manager; `spin()` blocks (Ctrl-C returns), `start()` spins in a
    background thread (the demo). Leaving the context destroys the nodes, which closes
    the recorder's bag.
    """

    def __init__(self, options: StackOptions):
        self.options = options
        self.nodes = []
        self._thread: threading.Thread | None = None

    def __enter__(self) -> "Stack":
        import rclpy
        from rclpy.executors import MultiThreadedExecutor

        rclpy.init()
        try:
            self.nodes = self._build()
        except BaseException:
            self._destroy()
            raise
        self.executor = MultiThreadedExecutor()
        for node in self.nodes:
            self.executor.add_node(node)
        return self

    def _build(self) -> list:
        from gscan_ros.model.policy import Policy
        from gscan_ros.nodes.parser_node import ParserNode
        from gscan_ros.nodes.policy_node import PolicyNode
        from gscan_ros.nodes.world_simulator_node import WorldSimulatorNode

        o = self.options
        checkpoint = str(o.checkpoint) if o.checkpoint else ""
        nodes = [
            WorldSimulatorNode(parameter_overrides=_params(
                dataset=str(o.dataset) if o.dataset else "", split=o.split, index=o.index, seed=o.seed,
                grid_size=o.grid_size,
            )),
            ParserNode(parameter_overrides=_params(checkpoint=checkpoint, parser=o.parser)),
            PolicyNode(Policy.from_checkpoint(o.checkpoint), parameter_overrides=_params(max_steps=o.max_steps)),
        ]
        self.nodes = nodes  # so a failure below still destroys what was built
        if o.record is not None:
            from gscan_ros.nodes.episode_recorder_node import EpisodeRecorderNode

            nodes.append(EpisodeRecorderNode(parameter_overrides=_params(
                bag_dir=str(o.record), include_images=o.record_images, overwrite=o.overwrite,
            )))
        return nodes

    def add(self, node) -> None:
        """Spin one more node (e.g. the demo's operator) with the stack; destroyed with it."""
        self.nodes.append(node)
        self.executor.add_node(node)

    def node(self, cls):
        """The stack's node of class `cls`."""
        return next(n for n in self.nodes if isinstance(n, cls))

    def spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            self.executor.spin()
        except (KeyboardInterrupt, ExternalShutdownException):
            pass

    def start(self) -> None:
        self._thread = threading.Thread(target=self.spin, name="gscan-stack", daemon=True)
        self._thread.start()

    def __exit__(self, *exc_info) -> None:
        import rclpy

        if hasattr(self, "executor"):
            self.executor.shutdown()
        if self._thread is not None:
            self._thread.join(timeout=10)
        self._destroy()
        rclpy.try_shutdown()

    def _destroy(self) -> None:
        for node in reversed(self.nodes):
            node.destroy_node()
        self.nodes = []


def _params(**values):
    from rclpy.parameter import Parameter

    return [Parameter(name, value=value) for name, value in values.items()]


def run(args: argparse.Namespace) -> int:
    options = StackOptions.from_args(args)
    with Stack(options) as stack:
        names = ", ".join(n.get_name() for n in stack.nodes)
        print(f"gscan-ros bringup: running {names}; Ctrl-C stops")
        stack.spin()
    return 0
