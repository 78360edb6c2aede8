"""`gscan-ros bag repair BAG --out NEW`: rewrite a damaged or unfinished bag as a complete one.

Everything the recovering reader gets out of BAG (every intact chunk around damage, every
complete episode before a truncation) is written to NEW as a fresh rosbag2 bag: a chunked,
zstd-compressed MCAP with its summary, indexes and footer, plus metadata.yaml, keeping
each message's channel, schema, sequence and times, so that third-party readers open the
result (tested with the `rosbags` library, which refuses a bag without an MCAP footer).
In an episode bag, bad messages and the reports of episodes that could not be read
(cut by damage, holding a bad message) are left out, so NEW reads back as the episodes
BAG gave, with nothing lost. A folder of .mcap files without metadata.yaml (a killed
`ros2 bag record`) is read in name order and gets one. BAG is only read.
"""
from __future__ import annotations

import argparse

from gscan_ros.cli.args import existing_path, output_dir
from gscan_ros.errors import GscanError


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "bag",
        help="repair rosbag2/MCAP bags",
        description="Tools for gscan_ros rosbag2/MCAP bags.",
    )
    actions = parser.add_subparsers(dest="bag_command", metavar="ACTION", required=True)
    repair = actions.add_parser(
        "repair",
        help="rewrite a damaged or unfinished bag as a complete, indexed one",
        description=__doc__.split("\n\n")[1],
    )
    repair.add_argument("bag", metavar="BAG", help="the damaged bag directory (read only)")
    repair.add_argument("--out", required=True, metavar="NEW",
                        help="directory for the repaired bag: new (its parents are made) or empty; "
                             "--overwrite replaces a bag there")
    repair.add_argument("--overwrite", action="store_true",
                        help="replace a previous bag at NEW (never anything that is not a bag)")
    repair.set_defaults(func=run_repair)


def _check(validate, text: str, name: str):
    """The `cli.args` validators, reported as `gscan-ros bag: error: argument NAME: ...` (exit 1)."""
    try:
        return validate(text)
    except argparse.ArgumentTypeError as exc:
        raise GscanError(f"argument {name}: {exc}") from None


def run_repair(args: argparse.Namespace) -> int:
    from gscan_ros.data.bag import repair_bag
    from gscan_ros.errors import DatasetFormatError
    from gscan_ros.outputs import claimed

    bag = _check(existing_path, args.bag, "BAG")
    out = _check(output_dir, args.out, "--out")
    try:
        with claimed(out):
            result = repair_bag(bag, out, overwrite=args.overwrite)
    except OSError as exc:  # unwritable destination, disk full ...
        raise DatasetFormatError(f"{out}: cannot write the repaired bag ({exc.strerror or exc})") from None
    source = result.source
    print(f"read {bag}: {source.state()}")
    print(f"kept: {result.kept()}, {result.messages} messages")
    if source.complete:
        print("lost: nothing")
    else:
        details = [f"{count} {what}" for count, what in (
            (len(source.missing_files), "missing storage file(s)"),
            (source.lost_chunks, "unreadable chunk(s)"),
            (len(source.corrupt_regions), "damaged region(s)"),
            (len(source.truncated_files), "file(s) without MCAP footer"),
            (source.unread_bytes, "torn trailing bytes"),
            (source.bad_messages, "bad message(s)"),
            (source.incomplete_episodes, "episode(s) that could not be read"),
            (result.dropped_messages, "readable message(s) left out"),
        ) if count]
        print(f"lost: {source.bound(source.episodes_exact)}{source.lost_episodes} episodes / "
              f"{source.bound(source.messages_exact)}{source.lost_messages} messages"
              + (f" ({', '.join(details)})" if details else ""))
        why = [source.reasons()] if source.drop_reasons else []
        if source.first_bad_message:
            why.append(f"the first bad message: {source.first_bad_message}")
        if why:
            print("why: " + "; ".join(why))
    print(f"wrote {result.info.path}: complete bag (MCAP summary, indexes and footer; metadata.yaml)")
    return 0
