"""`gscan-ros bringup`: the gscan_ros nodes in one process, for machines without `ros2 launch`.

The same node classes and parameters as `launch/gscan.launch.py`, spun by one
SingleThreadedExecutor (`gscan_ros.nodes.stack`). Talk to it like to the launched stack,
e.g. with `ros2 topic pub /command std_msgs/msg/String "{data: 'walk to a red circle'}" --once`.
"""
from __future__ import annotations

import argparse

from gscan_ros.cli.args import (
    existing_file,
    existing_path,
    fill_defaults,
    int_in,
    nonnegative_int,
    output_dir,
    positive_int,
    refuse_unused,
)
from gscan_ros.errors import GscanError
from gscan_ros.nodes.stack import StackOptions  # rclpy and torch are imported only when a stack starts
from gscan_ros.world.types import GRID_SIZE, SUPPORTED_GRID_SIZES


def add_stack_arguments(parser: argparse.ArgumentParser) -> None:
    """Options shared by `bringup` and `demo`."""
    parser.add_argument("--checkpoint", type=existing_file, default=None,
                        help="policy checkpoint (default: the shipped model)")
    parser.add_argument("--parser", default="", help="parse type; the policy takes only its checkpoint's "
                        "(the default)")
    source = parser.add_argument_group("situations (a dataset split, else random sampling)")
    source.add_argument("--dataset", type=existing_path, default=None, help="dataset.txt, its directory, or a bag")
    source.add_argument("--split", default=None, help="dataset split, with --dataset (default: test)")
    source.add_argument("--index", type=nonnegative_int, default=None,
                        help="first example of the split, with --dataset (default: 0)")
    source.add_argument("--seed", type=nonnegative_int, default=None,
                        help="first sampling seed, without --dataset (default: 0)")
    source.add_argument("--grid-size", type=int_in(SUPPORTED_GRID_SIZES[0], SUPPORTED_GRID_SIZES[-1]),
                        default=None, help="grid side of sampled worlds, without --dataset (default: the model's)")
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


SOURCE_DEFAULTS = {"split": "test", "index": 0, "seed": 0}


def resolve_stack_arguments(args: argparse.Namespace) -> dict:
    """Refuse, before any node starts, what the stack would take and then fail on: situation
    options the chosen source does not use (--split and --index name a dataset's examples;
    --seed and --grid-size sample worlds without one), a checkpoint that cannot be read, a
    --parser whose graphs its policy rejects, a --grid-size its model does not read. Sampled
    worlds take the model's grid size unless told; the other defaults are filled in. The
    checkpoint dict is returned (its parser and lexicon parse the demo's commands)."""
    from gscan_ros.language.registry import BUILTIN_PARSERS
    from gscan_ros.model.checkpoint import read_checkpoint
    from gscan_ros.model.policy import default_checkpoint_path

    if args.dataset is not None:
        refuse_unused(args, ("seed", "grid_size"), "(--dataset serves its own examples)")
    else:
        refuse_unused(args, ("split", "index"), "(without --dataset, worlds are sampled)")
    if args.parser and args.parser not in BUILTIN_PARSERS:
        raise GscanError(f"--parser {args.parser!r}: not one of {', '.join(BUILTIN_PARSERS)}")
    ckpt = read_checkpoint(args.checkpoint or default_checkpoint_path())
    model = f"the {'shipped' if args.checkpoint is None else 'checkpoint'}'s model"
    if args.parser and args.parser != ckpt["parser"]:
        raise GscanError(f"--parser {args.parser}: {model} reads {ckpt['parser']} parses, so the policy would "
                         f"reject every command (leave --parser out)")
    grid = int(ckpt["model_config"].get("grid_size", GRID_SIZE))
    if args.grid_size is not None and args.grid_size != grid:
        raise GscanError(f"--grid-size {args.grid_size}: {model} reads {grid}x{grid} worlds")
    fill_defaults(args, {**SOURCE_DEFAULTS, "grid_size": grid})
    return ckpt


def stack_options(args: argparse.Namespace, **overrides) -> StackOptions:
    """The StackOptions the parsed arguments name (fields missing from `args` keep their defaults)."""
    fields = {name: getattr(args, name) for name in StackOptions.__dataclass_fields__ if hasattr(args, name)}
    return StackOptions(**{**fields, **overrides})


def run(args: argparse.Namespace) -> int:
    import contextlib

    from gscan_ros.nodes.stack import Stack
    from gscan_ros.outputs import claimed

    if args.overwrite and args.record is None:
        raise GscanError("--overwrite replaces a bag at --record BAG_DIR; no --record given")
    resolve_stack_arguments(args)
    if args.record is not None:
        from gscan_ros.data.bag_metadata import replaceable_bag

        replaceable_bag(args.record, args.overwrite)  # refused here with this command's flag, before any node
    with claimed(args.record) if args.record else contextlib.nullcontext(), Stack(stack_options(args)) as stack:
        names = ", ".join(n.get_name() for n in stack.nodes)
        print(f"gscan-ros bringup: running {names}; Ctrl-C stops")
        stack.spin()
    return 0
