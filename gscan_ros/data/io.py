"""One entry point for episodes on disk: a gSCAN dataset.txt, a rosbag2/MCAP bag, or a
directory of per-split bags (`generate --format mcap`).

A per-split bag dataset ends with its manifest (`manifest.json`, the episodes per split),
written after every bag is closed: a dataset whose manifest names a split without its
complete bag is refused by every reader (`bag_splits`). Every reader refuses a requested
split without examples, with the message dataset.txt gives (`splits.require_splits`), and,
once its bags are read, one whose bag lost every episode of it (`require_delivered`).
"""
from __future__ import annotations

import functools
import json
import logging
import os
from pathlib import Path
from typing import Callable, Iterable, Iterator, Mapping

from gscan_ros.data.bag_format import LIVE_SPLIT
from gscan_ros.data.episode import Episode
from gscan_ros.data.splits import require_splits
from gscan_ros.errors import DatasetFormatError

BAG_METADATA = "metadata.yaml"
DATASET_MANIFEST = "manifest.json"
MANIFEST_FORMAT = "gscan_ros/dataset"
MANIFEST_VERSION = 1
log = logging.getLogger(__name__)


def is_bag(path: str | os.PathLike) -> bool:
    """A rosbag2 bag is a directory with metadata.yaml, or with the .mcap files of a
    recorder killed before it wrote one (`bag_metadata.read_bag_info` reads both)."""
    path = Path(path)
    return (path / BAG_METADATA).is_file() or any(p.is_file() for p in path.glob("*.mcap"))


def split_bags(path: str | os.PathLike) -> dict[str, Path]:
    """Split name -> bag of a directory laid out as `generate --format mcap` writes it
    (`DIR/<split>/metadata.yaml`); empty for anything else."""
    root = Path(path)
    if not root.is_dir() or is_bag(root) or (root / "dataset.txt").exists():
        return {}
    return {sub.name: sub for sub in sorted(root.iterdir()) if is_bag(sub)}


def write_manifest(folder: str | os.PathLike, counts: Mapping[str, int], header: dict) -> Path:
    """Write the manifest of a per-split bag dataset: its last file, the mark that it is complete."""
    from gscan_ros.outputs import write_text

    record = {"format": MANIFEST_FORMAT, "version": MANIFEST_VERSION, "splits": dict(counts), "header": header}
    return write_text(Path(folder) / DATASET_MANIFEST, json.dumps(record, indent=1) + "\n")


def bag_splits(path: str | os.PathLike) -> dict[str, int] | None:
    """Episodes per split of the bag data at `path`, as their writers counted them; None for
    dataset.txt data and for a single bag without final counts (its writer has not closed
    it, or it is not ours).

    A per-split dataset is refused (DatasetFormatError, one line naming what is missing)
    when its manifest names a split whose bag is absent, unfinished or short, and, without
    a manifest (written by hand or by an older version), when a bag is unfinished."""
    from gscan_ros.data.bag_metadata import read_bag_info

    if is_bag(path):
        info = read_bag_info(path)
        return info.splits if info.closed and "gscan_ros.splits" in info.custom else None
    root = Path(path)
    manifest = _read_manifest(root)
    bags = split_bags(root)
    if manifest is None:
        if not bags:
            return None
        infos = {split: read_bag_info(bag) for split, bag in bags.items()}
        unfinished = [split for split, info in infos.items() if not info.closed]
        if unfinished:
            raise DatasetFormatError(f"{root} is incomplete: the bag(s) of {', '.join(unfinished)} were not "
                                     "finished by their writer (`gscan-ros bag repair` keeps what they hold)")
        return {split: info.splits.get(split, 0) for split, info in infos.items()}
    counts = manifest["splits"]
    problems = []
    for split, expected in counts.items():
        if not expected:
            continue
        if split not in bags:
            problems.append(f"{split} missing")
            continue
        info = read_bag_info(bags[split])
        if not info.closed:
            problems.append(f"{split} unfinished")
        elif info.splits.get(split) != expected:
            problems.append(f"{split} holds {info.splits.get(split, 0)} of {expected} episodes")
    if problems:
        raise DatasetFormatError(f"{root} is incomplete ({'; '.join(problems)}; its {DATASET_MANIFEST} lists "
                                 f"{', '.join(s for s, n in counts.items() if n)})")
    return counts


def select_bags(path: str | os.PathLike, splits: Iterable[str] | None = None) -> list[Path] | None:
    """The bags to read for `splits` (all if None) of the bag data at `path`, after
    `bag_splits` and `require_splits` accepted them; None for dataset.txt data."""
    wanted = None if splits is None else list(splits)
    counts = bag_splits(path)
    if counts is not None and wanted is not None:
        require_splits(wanted, counts, path)
    if is_bag(path):
        return [Path(path)]
    if counts is None:
        return None
    return [bag for split, bag in split_bags(path).items() if wanted is None or split in wanted]


def is_manifest(path: str | os.PathLike) -> bool:
    """Whether the file at `path` is a per-split bag dataset's manifest (`write_manifest`)."""
    try:
        _manifest_record(Path(path))
    except DatasetFormatError:
        return False
    return True


def _read_manifest(root: Path) -> dict | None:
    path = root / DATASET_MANIFEST
    return _manifest_record(path) if path.is_file() else None


def _manifest_record(path: Path) -> dict:
    from gscan_ros.user_files import read_json

    record = read_json(path, str(path), DatasetFormatError)
    counts = record.get("splits") if isinstance(record, dict) else None
    valid = (isinstance(counts, dict) and record.get("format") == MANIFEST_FORMAT
             and all(isinstance(n, int) and not isinstance(n, bool) for n in counts.values()))
    if not valid:
        raise DatasetFormatError(f"{path} is not a gscan_ros dataset manifest (format {MANIFEST_FORMAT})")
    return record


def iter_episodes(path: str | os.PathLike, splits: Iterable[str] | None = None) -> Iterator[Episode]:
    """Episodes of `splits` (all if None) from dataset.txt (file or its directory), one bag,
    or a directory of per-split bags.

    Streams in file order; `example_id` is the example's index within its split.
    """
    for load in iter_episode_loaders(path, splits):
        yield load()


def iter_episode_loaders(path: str | os.PathLike,
                         splits: Iterable[str] | None = None) -> Iterator[Callable[[], Episode]]:
    """`iter_episodes`, each episode made only when its item is called: a reader that skips
    examples does not decode them, and a malformed example (a DatasetFormatError from its
    call) leaves the stream going on to the next one."""
    wanted = None if splits is None else list(splits)
    bags = select_bags(path, wanted)
    if bags is not None:
        from gscan_ros.data.bag import iter_bag_episodes

        readers, delivered = [], set()
        for bag in bags:
            readers.append(iter_bag_episodes(bag, wanted, log_losses=False))  # reported below, once
            for episode in readers[-1]:
                delivered.add(episode.split)
                yield functools.partial(_itself, episode)
        require_delivered(path, wanted, delivered, readers)
        for reader in readers:
            if not reader.report.complete:
                log.warning(reader.report.summary())
        return
    from gscan_ros.data.dataset import dataset_file, decode_example, iter_raw_examples

    _require_dataset_txt(path)

    file = dataset_file(path)

    def load(split: str, index: int, raw: dict) -> Episode:
        return decode_example(split, index, raw, file).to_episode(split, index)

    for split, index, raw in iter_raw_examples(path, wanted):
        yield functools.partial(load, split, index, raw)


def require_delivered(path: str | os.PathLike, wanted: list[str] | None, delivered: Iterable[str],
                      readers: list) -> None:
    """Refuse, once `readers` (bag readers of the data at `path`) are read to their end, a
    split asked for, or when none was one a damaged bag counts, that gave no episode: a bag
    that lost all of a split reads as empty while its metadata and the manifest still count
    it, and the split would drop out of a result without a word."""
    damaged = [reader for reader in readers if not reader.report.complete]
    expected = wanted if wanted is not None else [
        split for reader in damaged for split, count in reader.info.splits.items() if count]
    delivered = set(delivered)
    missing = [split for split in dict.fromkeys(expected) if split not in delivered]
    if not missing:
        return
    why = "; ".join(reader.report.summary() for reader in damaged) or "its bags hold none that ended complete"
    raise DatasetFormatError(f"no episodes of split(s) {', '.join(missing)} could be read from {path} ({why})")


def refuse_bag_file(path: str | os.PathLike) -> None:
    """A bag is read from its folder (metadata.yaml and every storage file); one of its .mcap
    files passed alone would be read as a dataset.txt."""
    root = Path(path)
    if root.is_file() and root.suffix == ".mcap":
        raise DatasetFormatError(f"{root}: a storage file of a bag; pass the bag's folder ({root.parent}), "
                                 f"which every reader takes")


def _require_dataset_txt(path: str | os.PathLike) -> None:
    """dataset.txt is what is left to read at `path`: a folder without it holds no dataset
    any reader knows, and the error says what was looked for."""
    from gscan_ros.data.dataset import DATASET_FILE

    root = Path(path)
    refuse_bag_file(root)
    if root.is_dir() and not (root / DATASET_FILE).exists():
        raise DatasetFormatError(f"{root}: no dataset here (looked for {DATASET_FILE}, a rosbag2 bag: "
                                 f"{BAG_METADATA} or .mcap files, and per-split bags: <split>/{BAG_METADATA})")


def _itself(episode: Episode) -> Episode:
    return episode


def iter_test_episodes(path: str | os.PathLike, splits: list[str] | None = None) -> Iterator[Episode]:
    """The requested splits, or every evaluation split the dataset has (train/dev skipped
    without decoding them)."""
    from gscan_ros.data.splits import ALL_TEST_SPLITS

    if splits:
        yield from iter_episodes(path, splits)
        return
    counts = bag_splits(path)
    if counts is not None:
        present = [split for split in ALL_TEST_SPLITS if counts.get(split)]
        if present:
            yield from iter_episodes(path, present)
    elif is_bag(path):  # a bag still being written: whatever test episodes it holds so far
        from gscan_ros.data.bag import iter_bag_episodes

        yield from iter_bag_episodes(path, ALL_TEST_SPLITS)
    else:
        from gscan_ros.data.dataset import dataset_file, decode_example, iter_raw_examples

        _require_dataset_txt(path)
        for split, index, raw in iter_raw_examples(path):
            if split in ALL_TEST_SPLITS:
                yield decode_example(split, index, raw, dataset_file(path)).to_episode(split, index)


def select_test_episodes(path: str | os.PathLike, splits: list[str] | None, max_examples: int = 0,
                         seed: int = 0) -> list[Episode]:
    """`iter_test_episodes`, each split cut to a seeded subset of `max_examples` (0: all):
    the episodes `evaluate --max-examples` decodes and `explain --metrics` reads."""
    import numpy as np

    from gscan_ros.data.splits import ALL_TEST_SPLITS

    by_split: dict[str, list[Episode]] = {}
    for ep in iter_test_episodes(path, splits):
        by_split.setdefault(ep.split, []).append(ep)
    if not by_split:
        bags = select_bags(path) is not None
        counts = bag_splits(path) if bags else None  # None for a bag that does not count its splits
        has = f" (it has: {', '.join(s for s, n in counts.items() if n) or 'none'})" if counts else ""
        recorded = bags and (counts is None or LIVE_SPLIT in counts)
        raise DatasetFormatError(f"{str(path)!r} has none of the splits {list(splits or ALL_TEST_SPLITS)}{has}"
                                 + (f"; a recording's episodes are in split {LIVE_SPLIT} (--splits {LIVE_SPLIT})"
                                    if recorded else ""))
    episodes: list[Episode] = []
    for eps in by_split.values():
        if max_examples and len(eps) > max_examples:
            pick = np.random.default_rng([seed, len(eps)]).choice(len(eps), max_examples, replace=False)
            eps = [eps[i] for i in sorted(pick)]
        episodes += eps
    return episodes
