"""`gscan-ros verify`: replay every example's target actions and re-plan it.

An example passes when its `target_commands` execute in the World without error and
equal what `gscan_ros.world.demonstrate` plans for its command and situation.
"""
from __future__ import annotations

import argparse


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "verify",
        help="check a dataset's target actions against the world and the planner",
        description="Stream a dataset.txt (or a bag directory), replay each example's actions in the "
                    "World and compare them with the planner. Exit status 1 on any mismatch.",
    )
    p.add_argument("dataset", metavar="DATASET", help="dataset.txt, a directory holding it, or a bag directory")
    p.add_argument("--splits", help="comma-separated splits to check (default: all)")
    p.add_argument("--limit", type=int, metavar="N", help="check at most N examples")
    p.add_argument("--show", type=int, default=5, metavar="K", help="mismatches to print in full (default: 5)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _first_difference(a, b) -> int:
    return next((i for i, (x, y) in enumerate(zip(a, b)) if x != y), min(len(a), len(b)))


def _tokens(actions) -> str:
    return ",".join(a.token for a in actions)


def check_episode(episode) -> str | None:
    """None if the episode replays and matches the planner, else a one-line reason."""
    from gscan_ros.errors import GscanError
    from gscan_ros.world import World, demonstrate

    world = World(episode.situation)
    for t, action in enumerate(episode.actions):
        try:
            world.step(action)
        except GscanError as exc:
            return f"replay fails at step {t} ({action.token}): {exc}"
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

    from tqdm import tqdm

    from gscan_ros.data.io import iter_episodes

    splits = args.splits.split(",") if args.splits else None
    episodes = iter_episodes(args.dataset, splits)
    first = next(episodes, None)  # opens the file: a bad path fails before the progress bar
    episodes = itertools.chain([first] if first is not None else [], episodes)
    if args.limit is not None:
        episodes = itertools.islice(episodes, args.limit)
    checked = mismatches = 0
    for episode in tqdm(episodes, unit="ex", desc="verify", disable=args.quiet):
        checked += 1
        reason = check_episode(episode)
        if reason is None:
            continue
        mismatches += 1
        if mismatches <= args.show:
            tqdm.write(f"MISMATCH example {episode.example_id} of split {episode.split!r}: "
                       f"{episode.command!r}: {reason}")
    print(f"verified {checked} examples: {mismatches} mismatch(es)")
    return 1 if mismatches else 0
