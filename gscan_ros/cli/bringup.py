"""`gscan-ros bringup`: the gscan_ros nodes in one process, for machines without `ros2 launch`.

The same node classes and parameters as `launch/gscan.launch.py`, spun by one
MultiThreadedExecutor (`gscan_ros.nodes.stack`). Talk to it like to the launched stack,
e.g. with `ros2 topic pub /command std_msgs/msg/String "{data: 'walk to a red circle'}" --once`.
"""
from __future__ import annotations

import argparse

from gscan_ros.cli.args import existing_file, existing_path, int_in, nonnegative_int, output_dir, positive_int
from gscan_ros.nodes.stack import StackOptions  # rclpy and torch are imported only when a stack starts
from gscan_ros.world.types import GRID_SIZE, SUPPORTED_GRID_SIZES


def add_stack_arguments(parser: argparse.ArgumentParser) -> None:
    """Options shared by `bringup` and `demo`."""
    parser.add_argument("--checkpoint", type=existing_file, default=None,
                        help="policy checkpoint (default: the shipped model)")
    parser.add_argument("--parser", default="", help="parse type (default: the checkpoint's)")
    source = parser.add_argument_group("situations (a dataset split, else random sampling)")
    source.add_argument("--dataset", type=existing_path, default=None, help="dataset.txt, its directory, or a bag")
    source.add_argument("--split", default="test", help="dataset split (default: test)")
    source.add_argument("--index", type=nonnegative_int, default=0, help="first example of the split (default: 0)")
    source.add_argument("--seed", type=nonnegative_int, default=0,
                        help="first sampling seed without --dataset (default: 0)")
    source.add_argument("--grid-size", type=int_in(SUPPORTED_GRID_SIZES[0], SUPPORTED_GRID_SIZES[-1]),
                        default=GRID_SIZE, help=f"grid side of sampled worlds without --dataset (default: {GRID_SIZE})")
    parser.add_argument("--max-steps", type=positive_int, default=None,
                        help="action cap per episode (default: policy_node's, gscan_ros.model.policy.MAX_STEPS)")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "bringup",
        help="run the ROS 2 nodes in one process",
        description=__doc__.splitlines()[0],
    )
    add_stack_arguments(p)
    p.add_argument("--record", type=output_dir, default=None, metavar="BAG_DIR",
                   help="also record episodes to this bag (a new directory, or an empty one)")
    p.add_argument("--overwrite", action="store_true",
                   help="with --record: replace a bag already at BAG_DIR (only the bag's own files)")
    p.set_defaults(func=run)


def stack_options(args: argparse.Namespace, **overrides) -> StackOptions:
    """The StackOptions the parsed arguments name (fields missing from `args` keep their defaults)."""
    fields = {name: getattr(args, name) for name in StackOptions.__dataclass_fields__ if hasattr(args, name)}
    return StackOptions(**{**fields, **overrides})


def run(args: argparse.Namespace) -> int:
    import contextlib

    from gscan_ros.nodes.stack import Stack
    from gscan_ros.outputs import claimed

    with claimed(args.record) if args.record else contextlib.nullcontext(), Stack(stack_options(args)) as stack:
        names = ", ".join(n.get_name() for n in stack.nodes)
        print(f"gscan-ros bringup: running {names}; Ctrl-C stops")
        stack.spin()
    return 0
