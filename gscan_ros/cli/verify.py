"""`gscan-ros verify`: replay every example's target actions and re-plan it.

An example passes when its `target_commands` execute in the World without error and
equal what `gscan_ros.world.demonstrate` plans for its command and situation. A
recorded live episode (split `live`) holds the policy's actions, not the planner's, so it
is only replayed. Recorded episodes that did not end complete are counted by outcome. A bag
that lost data (truncated or corrupt MCAP, episodes dropped) fails verification too,
with one line per bag saying what was lost, unless `--allow-partial` accepts it. A
per-split bag dataset that is incomplete (its manifest names a split without its bag) or
lacks a split asked for is refused before anything is read, as dataset.txt is. Finding
no episode at all fails, and so does a bag whose episodes lie on more than one grid size
(a dataset has one; `train` refuses it).
"""
from __future__ import annotations

import argparse

from gscan_ros import episode_status as es
from gscan_ros.cli.args import existing_path, name_list, nonnegative_int, positive_int
from gscan_ros.data.bag_format import LIVE_SPLIT
from gscan_ros.errors import GscanError


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "verify",
        help="check a dataset's target actions against the world and the planner",
        description="Stream a dataset.txt (or a bag directory), replay each example's actions in the "
                    "World and compare them with the planner. Exit status 1 on any mismatch, and on a "
                    "bag that lost data (truncated, corrupt, episodes dropped) unless --allow-partial.",
    )
    p.add_argument("dataset", type=existing_path, metavar="DATASET",
                   help="dataset.txt, a directory holding it, or a bag directory")
    p.add_argument("--splits", type=name_list, metavar="S1,S2", help="comma-separated splits to check (default: all)")
    p.add_argument("--limit", type=positive_int, metavar="N", help="check at most N examples")
    p.add_argument("--show", type=nonnegative_int, default=5, metavar="K",
                   help="mismatches to print in full (default: 5)")
    p.add_argument("--allow-partial", action="store_true",
                   help="accept a bag that lost data (the loss is still printed; exit 0 unless a mismatch)")
    p.add_argument("--include-incomplete", action="store_true",
                   help="also check recorded episodes that ended cut, preempted or rejected (replay only)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _first_difference(a, b) -> int:
    return next((i for i, (x, y) in enumerate(zip(a, b)) if x != y), min(len(a), len(b)))


def _tokens(actions) -> str:
    return ",".join(a.token for a in actions)


def check_episode(episode, *, replan: bool = True) -> str | None:
    """None if the episode replays and (with `replan`) matches the planner, else a one-line reason."""
    from gscan_ros.world import World, demonstrate

    world = World(episode.situation)
    for t, action in enumerate(episode.actions):
        try:
            world.step(action)
        except GscanError as exc:
            return f"replay fails at step {t} ({action.token}): {exc}"
    if not replan:
        return None
    try:
        planned = demonstrate(episode.situation, episode.command)
    except GscanError as exc:
        return f"planner rejects the example: {exc}"
    if list(planned) == list(episode.actions):
        return None
    i = _first_difference(episode.actions, planned)
    return (f"differs at step {i} (dataset {len(episode.actions)} actions, planner {len(planned)})\n"
            f"      dataset: {_tokens(episode.actions)}\n"
            f"      planner: {_tokens(planned)}")


def run(args: argparse.Namespace) -> int:
    import itertools
    import sys

    from tqdm import tqdm

    splits = args.splits
    readers = _bag_readers(args.dataset, splits, args.include_incomplete)
    if readers is None and (args.allow_partial or args.include_incomplete):
        flags = " and ".join(f for f, on in (("--allow-partial", args.allow_partial),
                                             ("--include-incomplete", args.include_incomplete)) if on)
        raise GscanError(f"{flags}: for recorded bags; {args.dataset} is a dataset.txt")
    if readers is None:
        from gscan_ros.data.io import iter_episodes

        episodes = iter_episodes(args.dataset, splits)
    else:
        episodes = itertools.chain.from_iterable(readers)
    first = next(episodes, None)  # opens the file: a bad path fails before the progress bar
    episodes = itertools.chain([first] if first is not None else [], episodes)
    if args.limit is not None:
        episodes = itertools.islice(episodes, args.limit)
    checked = mismatches = live = 0
    for episode in tqdm(episodes, unit="ex", desc="verify", disable=args.quiet):
        checked += 1
        incomplete = episode.meta.get("outcome", es.COMPLETE) != es.COMPLETE
        recorded = episode.split == LIVE_SPLIT or incomplete
        live += recorded
        reason = check_episode(episode, replan=not recorded)
        if reason is None:
            continue
        mismatches += 1
        if mismatches <= args.show:
            tqdm.write(f"MISMATCH example {episode.example_id} of split {episode.split!r}: "
                       f"{episode.command!r}: {reason}")
    if not checked:
        from gscan_ros.errors import DatasetFormatError

        summaries = "; ".join(reader.report.summary() for reader in readers or [])
        raise DatasetFormatError(f"{args.dataset}: no episodes found" + (f" ({summaries})" if summaries else ""))
    print(f"verified {checked} examples: {mismatches} mismatch(es)"
          + (f" ({live} recorded episodes replayed, not re-planned)" if live else ""))
    from gscan_ros.data.bag_report import incomplete_line

    line = incomplete_line(readers or [], "checked", included=args.include_incomplete)
    if line:
        print(line)
    losses = [_loss(reader) for reader in readers or []]
    losses = [line for line in losses if line]
    for line in losses:
        if args.allow_partial:
            print(f"warning: lost data (accepted by --allow-partial): {line}", file=sys.stderr)
        else:
            print(f"gscan-ros verify: error: lost data: {line} (pass --allow-partial to accept it; "
                  f"`gscan-ros bag repair` rewrites what is left as a complete bag)", file=sys.stderr)
    mixed = [line for line in (reader.report.mixed_grid_sizes() for reader in readers or []) if line]
    for line in mixed:
        print(f"gscan-ros verify: error: {line} (`train` refuses it)", file=sys.stderr)
    return 1 if mismatches or mixed or (losses and not args.allow_partial) else 0


def _bag_readers(dataset, splits, include_incomplete: bool):
    """The readers of a bag or a directory of per-split bags (None for dataset.txt data);
    a split asked for and missing, or an incomplete dataset, is refused (`select_bags`)."""
    from gscan_ros.data.bag import iter_bag_episodes
    from gscan_ros.data.io import select_bags

    bags = select_bags(dataset, splits)
    if bags is None:
        return None
    return [iter_bag_episodes(bag, splits, log_losses=False, include_incomplete=include_incomplete) for bag in bags]


def _loss(reader) -> str | None:
    """One line on what a bag lost, or None. A reader that --limit stopped early is judged
    on what it read: damage seen so far and episodes cut by it."""
    report = reader.report
    if report.finished:
        return None if report.complete else report.summary()
    if report.damaged or report.incomplete_episodes:
        return (f"{report.bag_dir}: {report.state()} in the part read before --limit stopped: "
                f"{report.incomplete_episodes} episode(s) cut, {len(report.corrupt_regions)} damaged region(s)")
    return None
