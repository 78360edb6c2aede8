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
