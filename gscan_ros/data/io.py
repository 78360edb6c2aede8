"""One entry point for episodes on disk: a gSCAN dataset.txt or a rosbag2/MCAP bag."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Iterator

from gscan_ros.data.episode import Episode

BAG_METADATA = "metadata.yaml"


def is_bag(path: str | os.PathLike) -> bool:
    """A rosbag2 bag is a directory with metadata.yaml."""
    return (Path(path) / BAG_METADATA).is_file()


def split_bags(path: str | os.PathLike) -> dict[str, Path]:
    """Split name -> bag of a directory laid out as `generate --format mcap` writes it
    (`DIR/<split>/metadata.yaml`); empty for anything else."""
    root = Path(path)
    if not root.is_dir() or is_bag(root) or (root / "dataset.txt").exists():
        return {}
    return {sub.name: sub for sub in sorted(root.iterdir()) if is_bag(sub)}


def iter_episodes(path: str | os.PathLike, splits: Iterable[str] | None = None) -> Iterator[Episode]:
    """Episodes of `splits` (all if None) from dataset.txt (file or its directory), one bag,
    or a directory of per-split bags.

    Streams in file order; `example_id` is the example's index within its split.
    """
    wanted = None if splits is None else list(splits)
    if is_bag(path):
        from gscan_ros.data.bag import iter_bag_episodes

        yield from iter_bag_episodes(path, wanted)
        return
    bags = split_bags(path)
    if bags:
        from gscan_ros.data.bag import iter_bag_episodes

        for split, bag in bags.items():
            if wanted is None or split in wanted:
                yield from iter_bag_episodes(bag, wanted)
        return
    splits = wanted
    from gscan_ros.data.dataset import iter_examples

    for split, index, example in iter_examples(path, splits):
        yield example.to_episode(split, index)


def iter_test_episodes(path: str | os.PathLike, splits: list[str] | None = None) -> Iterator[Episode]:
    """The requested splits, or every evaluation split the dataset has (train/dev skipped
    without decoding them)."""
    from gscan_ros.data.splits import ALL_TEST_SPLITS

    if splits:
        yield from iter_episodes(path, splits)
    elif is_bag(path) or split_bags(path):
        yield from iter_episodes(path, ALL_TEST_SPLITS)
    else:
        from gscan_ros.data.dataset import Example, iter_raw_examples

        for split, index, raw in iter_raw_examples(path):
            if split in ALL_TEST_SPLITS:
                yield Example.from_json(raw).to_episode(split, index)


def select_test_episodes(path: str | os.PathLike, splits: list[str] | None, max_examples: int = 0,
                         seed: int = 0) -> list[Episode]:
    """`iter_test_episodes`, each split cut to a seeded subset of `max_examples` (0: all):
    the episodes `evaluate --max-examples` decodes and `explain --metrics` reads."""
    import numpy as np

    from gscan_ros.data.splits import ALL_TEST_SPLITS
    from gscan_ros.errors import DatasetFormatError

    by_split: dict[str, list[Episode]] = {}
    for ep in iter_test_episodes(path, splits):
        by_split.setdefault(ep.split, []).append(ep)
    if not by_split:
        raise DatasetFormatError(f"{str(path)!r} has none of the splits {list(splits or ALL_TEST_SPLITS)}")
    episodes: list[Episode] = []
    for eps in by_split.values():
        if max_examples and len(eps) > max_examples:
            pick = np.random.default_rng([seed, len(eps)]).choice(len(eps), max_examples, replace=False)
            eps = [eps[i] for i in sorted(pick)]
        episodes += eps
    return episodes
