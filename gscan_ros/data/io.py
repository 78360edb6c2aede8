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


def iter_episodes(path: str | os.PathLike, splits: Iterable[str] | None = None) -> Iterator[Episode]:
    """Episodes of `splits` (all if None) from dataset.txt (file or its directory) or a bag.

    Streams in file order; `example_id` is the example's index within its split.
    """
    if is_bag(path):
        from gscan_ros.data.bag import iter_bag_episodes

        yield from iter_bag_episodes(path, splits)
        return
    from gscan_ros.data.dataset import iter_examples

    for split, index, example in iter_examples(path, splits):
        yield example.to_episode(split, index)
