"""`gscan-ros replay BAG`: re-run recorded episodes closed-loop and score them against the bag.

Each complete episode of the bag is restarted from its recorded initial situation and
command; the policy acts, the one World executes, and the produced action sequence
is compared with the recorded one (exact match, overall and per split). Recorded
episodes that did not end complete (cut, preempted, rejected) are counted and left out
unless --include-incomplete. BAG may also be a folder of per-split bags (`generate
--format mcap`): the bags of --splits, or all of them, are replayed.
"""
from __future__ import annotations

import argparse
import itertools

from gscan_ros.cli.args import existing_file, existing_path, positive_int
from gscan_ros.errors import DatasetFormatError


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "replay",
        help="re-run a bag's episodes closed-loop and compare with the recorded actions",
        description=__doc__.split("\n\n")[1],
    )
    parser.add_argument("bag", type=existing_path, help="rosbag2 directory (metadata.yaml + MCAP), or a folder of "
                                                         "per-split bags")
    parser.add_argument("--checkpoint", type=existing_file, default=None,
                        help="model checkpoint (default: the shipped model)")
    parser.add_argument("--max-episodes", type=positive_int, default=None, help="replay only the first N episodes")
    parser.add_argument("--splits", nargs="+", default=None, metavar="SPLIT", help="only episodes of these splits")
    parser.add_argument("--batch-size", type=positive_int, default=64, help="episodes decoded together")
    parser.add_argument("--include-incomplete", action="store_true",
                        help="also replay recorded episodes that ended cut, preempted or rejected (their "
                             "actions are what was done before the stop: a model that goes on past a cut "
                             "at the recording's max_steps, or a preemption, does not match them)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gscan_ros.data.bag import iter_bag_episodes
    from gscan_ros.data.io import require_delivered, select_bags
    from gscan_ros.model.policy import Policy
    from gscan_ros.training.evaluate import evaluate_episodes
    from gscan_ros.training.failures import failure_label

    bags = select_bags(args.bag, args.splits)  # a split none of the bags holds (or a typo) is named
    if bags is None:
        raise DatasetFormatError(f"{args.bag}: not a rosbag2 bag (no metadata.yaml or .mcap files) "
                                 "nor a folder of per-split bags (<split>/metadata.yaml)")
    readers = [iter_bag_episodes(bag, args.splits, log_losses=False, include_incomplete=args.include_incomplete)
               for bag in bags]
    episodes = list(itertools.islice(itertools.chain.from_iterable(readers), args.max_episodes))
    if not episodes:
        summaries = "; ".join(reader.report.summary() for reader in readers)
        raise DatasetFormatError(f"{args.bag}: no complete episodes to replay ({summaries})")
    if all(reader.report.finished for reader in readers):  # not cut short by --max-episodes
        require_delivered(args.bag, args.splits, {episode.split for episode in episodes}, readers)
    policy = Policy.from_checkpoint(args.checkpoint)
    result = evaluate_episodes(policy, episodes, batch_size=args.batch_size)
    matched = sum(p.exact_match for p in result.predictions)
    model = args.checkpoint or "the shipped model"
    print(f"replayed {len(episodes)} episodes of {args.bag} with {model} (parser {policy.parser_name})")
    print(f"exact match: {result.exact_match:.2f}% ({matched}/{len(episodes)})")
    for split, stats in result.summary().items():
        failed = ", ".join(f"{n} {failure_label(kind)}" for kind, n in stats["failures"].items() if n)
        print(f"  {split:<16} {stats['exact_match']:6.2f}%  of {stats['examples']} episodes"
              + (f"  (failed: {failed})" if failed else ""))
    if args.max_episodes is None:
        from gscan_ros.data.bag_report import incomplete_line

        line = incomplete_line(readers, "replayed", included=args.include_incomplete)
        if line:
            print(line)
    for reader in readers:
        if reader.report.finished and not reader.report.complete:
            print(f"warning: {reader.report.summary()}")
    return 0
