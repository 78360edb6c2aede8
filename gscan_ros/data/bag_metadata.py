"""rosbag2 `metadata.yaml` of gscan_ros bags: writing it and reading it back as `BagInfo`.

rosbag2 (and the `rosbags` reader) open a bag through this file, so it must follow
the rosbag2 schema (version 9, as written by Jazzy). Our own facts ride in the
standard `custom_data` string map under `gscan_ros.*` keys: the episode format, the
episode count per split, and whether the writer finished (`status: closed`) or is
still recording / was killed (`status: recording`).

`ros2 bag record` writes metadata.yaml only when it closes the bag, so a killed
recorder leaves its .mcap files alone; such a folder is still read, from its files
in name order (each MCAP file holds its channels and schemas), with a warning.

A storage file that should be there and is not (listed in metadata.yaml, or a gap in the
`<name>_<n>.mcap` numbering of a folder without one) is lost data at its place in the
file order (`BagInfo.missing`): readers mark the loss there and read the other files.
"""
from __future__ import annotations

import json
import os
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from gscan_ros.data.bag_schema import YamlDumper, offered_qos
from gscan_ros.errors import DatasetFormatError, quoted, shortened
from gscan_ros.user_files import read_yaml
from msg_adapters import type_hash

METADATA_FILE = "metadata.yaml"
CACHE_DIR = ".cache"  # the decode-once episode cache beside a bag (bag_cache.py)
ROSBAG2_VERSION = 9
STORAGE_ID = "mcap"
EPISODE_FORMAT = "gscan_ros/episodes"
# 1: `/command` carried a JSON episode header, `<eos>` closed every episode.
# 2: the live topics as they are; the policy's `/episode_status` delimits episodes and
#    `/episode` carries what a bag adds (docs/bags.md). Bags without our metadata read as 2.
EPISODE_FORMAT_VERSION = 2
LEGACY_FORMAT_VERSION = 1
STATUS_RECORDING = "recording"
STATUS_CLOSED = "closed"
MAX_METADATA_BYTES = 16 << 20
"""Largest metadata.yaml: ~830 bytes per topic and ~200 per storage file, so 1,000 topics
and a week split every minute (10,080 files) are ~3 MB."""
MAX_SPLIT_NUMBER = 999_999
"""Highest `<name>_<n>.mcap` number taken for a rosbag2 split (a week split every second
is 604,800): a larger one (a date stamp) is a name, and no gap is inferred before it."""
_SPLIT_FILE = re.compile(r"(.+_)(0|[1-9]\d*)\.mcap")  # rosbag2 numbers without leading zeros


@dataclass(frozen=True)
class TopicInfo:
    name: str
    msg_type: str
    message_count: int


@dataclass(frozen=True)
class BagInfo:
    """What `metadata.yaml` says about a bag (counts are final only when `closed`)."""

    path: Path
    mcap_paths: tuple[Path, ...]  # every storage file in read order, the `missing` ones at their place
    version: int
    message_count: int
    start_ns: int
    duration_ns: int
    topics: dict[str, TopicInfo]  # by name: a name listed with two types keeps its first entry
    custom: dict[str, str] = field(default_factory=dict)
    counts_final: bool = True  # False: metadata.yaml is missing, or does not list every storage file
    warnings: tuple[str, ...] = ()  # what readers log: missing metadata or files, unlisted files, custom data ignored
    # Storage files that should be there but are absent (listed in metadata.yaml, or a gap in
    # the `_<n>` numbering of a folder without it): their data is lost (`McapScan` yields LOSS).
    missing: tuple[Path, ...] = ()
    entries: tuple[TopicInfo, ...] = ()  # every metadata.yaml topic entry in order (one per writer channel)

    @property
    def closed(self) -> bool:
        """False while recording, when the writer died before closing the bag, or when
        metadata.yaml does not account for every storage file (its counts are not final)."""
        return self.counts_final and self.custom.get("gscan_ros.status", STATUS_CLOSED) != STATUS_RECORDING

    @property
    def publish_ordered(self) -> bool:
        """Our writer stored every message in publish-time order (readers need not reorder)."""
        return self.custom.get("gscan_ros.publish_ordered") == "true"

    @property
    def format_version(self) -> int:
        """The episode format (2 for bags that are not ours: the live topics)."""
        return int(self.custom.get("gscan_ros.format_version", EPISODE_FORMAT_VERSION))

    @property
    def episodes(self) -> int | None:
        """Number of episodes that ended (every outcome), when our writer closed the bag."""
        if not self.closed or "gscan_ros.format" not in self.custom:
            return None
        if self.format_version == LEGACY_FORMAT_VERSION:  # one `/command` each
            command = self.topics.get("/command")
            return command.message_count if command else 0
        count = self.custom.get("gscan_ros.episodes")  # dropped when malformed (`_custom_data`)
        return None if count is None else int(count)

    @property
    def splits(self) -> dict[str, int]:
        """Episodes per split, as recorded by the writer ({} for foreign bags)."""
        return json.loads(self.custom.get("gscan_ros.splits", "{}"))


def mcap_file_name(bag_dir: Path) -> str:
    """`<name>_0.mcap`, the first (and our only) storage file of a rosbag2 bag."""
    return f"{bag_dir.name}_0.mcap"


def bagfile_information(
    bag_dir: Path,
    *,
    topics: list[tuple[str, str, int]],
    start_ns: int | None,
    end_ns: int | None,
    custom: dict[str, str],
) -> dict:
    """The `rosbag2_bagfile_information` of a bag of one MCAP file, as rosbag2 writes it;
    `topics` = (name, type, message count) per channel, in the order they were registered."""
    total = sum(count for _, _, count in topics)
    start = start_ns if start_ns is not None else 0
    duration = (end_ns - start_ns) if (start_ns is not None and end_ns is not None) else 0
    file_name = mcap_file_name(bag_dir)
    info = {
        "version": ROSBAG2_VERSION,
        "storage_identifier": STORAGE_ID,
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": total,
        "topics_with_message_count": [
            {
                "topic_metadata": {
                    "name": topic,
                    "type": msg_type,
                    "serialization_format": "cdr",
                    "offered_qos_profiles": [offered_qos(topic)],
                    "type_description_hash": type_hash(msg_type),
                },
                "message_count": count,
            }
            for topic, msg_type, count in topics
        ],
        # Chunks are zstd-compressed inside the MCAP file; no rosbag2-level compression.
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [file_name],
        "files": [
            {
                "path": file_name,
                "starting_time": {"nanoseconds_since_epoch": start},
                "duration": {"nanoseconds": duration},
                "message_count": total,
            }
        ],
        "custom_data": custom,
        "ros_distro": "jazzy",
    }
    return info


def serialized_information(info: dict) -> str:
    """`info` as rosbag2's MCAP storage embeds it in the file (the `rosbag2` metadata record)."""
    return yaml.dump(info, Dumper=YamlDumper, sort_keys=False)


def write_metadata(bag_dir: Path, info: dict) -> None:
    """Write `metadata.yaml` holding `info` atomically (tmp + rename)."""
    text = yaml.dump({"rosbag2_bagfile_information": info}, Dumper=YamlDumper, sort_keys=False)
    tmp = bag_dir / f".{METADATA_FILE}.tmp"
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, bag_dir / METADATA_FILE)


def read_bag_info(bag_dir: str | os.PathLike) -> BagInfo:
    """Parse and check `metadata.yaml`; any problem is one DatasetFormatError naming the file.

    A folder of .mcap files without metadata.yaml (a killed `ros2 bag record`) reads from
    its files in name order, and .mcap files that metadata.yaml does not list are read
    after those it lists; either way the counts are not final (`closed` is False) and
    `warnings` says so. A storage file metadata.yaml lists, or one missing from the
    `<name>_<n>.mcap` numbering of a folder without it, that is absent stays in
    `mcap_paths` at its place and is named in `missing` and `warnings`: its data is lost,
    the rest reads (refused only when no file metadata.yaml lists is there). Malformed
    `gscan_ros.*` custom data, advisory only, is ignored with a warning."""
    bag_dir = Path(bag_dir)
    path = bag_dir / METADATA_FILE
    on_disk = sorted((p for p in bag_dir.glob("*.mcap") if p.is_file()), key=_storage_order)
    if not path.is_file():
        if not on_disk:
            raise DatasetFormatError(f"{bag_dir}: not a rosbag2 bag (no {METADATA_FILE} and no .mcap files)")
        gaps = _numbering_gaps(bag_dir, on_disk)
        lost = (f"; {_names(gaps)} missing from their numbering (lost data, marked where it was)"
                if gaps else "")
        return BagInfo(bag_dir, tuple(sorted((*on_disk, *gaps), key=_storage_order)), 0, 0, 0, 0, {},
                       counts_final=False, missing=gaps, warnings=(
            f"{bag_dir}: no {METADATA_FILE} (its recorder did not close the bag): reading its "
            f"{len(on_disk)} .mcap file(s) in name order{lost}; `gscan-ros bag repair {bag_dir} --out NEW` "
            f"writes a complete bag with one",))
    try:
        document = read_yaml(path, str(path), DatasetFormatError, MAX_METADATA_BYTES)
        if not isinstance(document, dict) or not isinstance(document.get("rosbag2_bagfile_information"), dict):
            raise DatasetFormatError(f"{path}: not rosbag2 metadata (no rosbag2_bagfile_information mapping)")
        info = document["rosbag2_bagfile_information"]
        storage = info["storage_identifier"]
        if storage != STORAGE_ID:
            raise DatasetFormatError(f"{path}: storage {quoted(storage)} is not supported (only {STORAGE_ID!r})")
        mode = info.get("compression_mode")
        if mode not in (None, "", "none", "NONE"):
            raise DatasetFormatError(
                f"{path}: rosbag2 compression_mode {quoted(mode)} is not supported; MCAP's own chunk compression "
                f"is (record with `--storage-preset-profile zstd_fast`, or rewrite the bag uncompressed with "
                f"`ros2 bag convert`)")
        files = info["relative_file_paths"]
        if not isinstance(files, list) or not all(isinstance(p, str) for p in files):
            raise DatasetFormatError(f"{path}: relative_file_paths must be a list of file names, got {quoted(files)}")
        mcap_paths = tuple(bag_dir / Path(p).name for p in files)
        topics, entries = {}, []
        for t in info["topics_with_message_count"] or []:
            name, msg_type = t["topic_metadata"]["name"], t["topic_metadata"]["type"]
            if not (isinstance(name, str) and isinstance(msg_type, str)):  # a type decides how a topic is read
                raise DatasetFormatError(f"{path}: a topic's name and type must be text, got {quoted(name)} "
                                         f"of type {quoted(msg_type)}")
            entries.append(TopicInfo(name, msg_type, int(t["message_count"])))
            topics.setdefault(name, entries[-1])
        version = int(info["version"])
        message_count = int(info["message_count"])
        start_ns = int(info["starting_time"]["nanoseconds_since_epoch"])
        duration_ns = int(info["duration"]["nanoseconds"])
    except KeyError as exc:
        raise DatasetFormatError(f"{path}: missing rosbag2 key {exc}") from None
    except (TypeError, ValueError, AttributeError) as exc:
        raise DatasetFormatError(f"{path}: malformed rosbag2 metadata ({shortened(str(exc))})") from None
    if not mcap_paths:
        raise DatasetFormatError(f"{path}: relative_file_paths is empty")
    missing = tuple(p for p in mcap_paths if not p.is_file())
    if len(missing) == len(mcap_paths):  # nothing to recover
        raise DatasetFormatError(f"{path}: storage file {shortened(missing[0].name)} is missing" if len(missing) == 1
                                 else f"{path}: all {len(missing)} storage files are missing ({_names(missing)})")
    custom, warnings = _custom_data(info.get("custom_data"), path)
    fmt = custom.get("gscan_ros.format_version", str(EPISODE_FORMAT_VERSION))
    if fmt not in {str(v) for v in range(EPISODE_FORMAT_VERSION + 1)}:
        what = "is newer than supported" if fmt.isdigit() and fmt.isascii() else "is not a version number"
        raise DatasetFormatError(
            f"{path}: episode format version {quoted(fmt)} {what} (the newest is {EPISODE_FORMAT_VERSION})"
        )
    if missing:
        warnings.append(f"{path} lists {len(missing)} storage file(s) that are missing ({_names(missing)}): "
                        f"their data is lost (marked where it was); reading the other files; "
                        f"`gscan-ros bag repair {bag_dir} --out NEW` writes a complete bag of what is left")
    unlisted = [p for p in on_disk if p not in mcap_paths]
    if unlisted:
        names = ", ".join(p.name for p in unlisted[:3]) + (", ..." if len(unlisted) > 3 else "")
        warnings.append(f"{path} does not list {len(unlisted)} .mcap file(s) of the folder ({names}): reading "
                        f"them after the ones it lists; `gscan-ros bag repair {bag_dir} --out NEW` writes a bag "
                        f"whose {METADATA_FILE} lists everything")
    return BagInfo(bag_dir, mcap_paths + tuple(unlisted), version, message_count, start_ns, duration_ns, topics,
                   custom, counts_final=not unlisted, warnings=tuple(warnings), missing=missing,
                   entries=tuple(entries))


def _storage_order(path: Path) -> tuple[str, int]:
    """rosbag2's order of split files: `<name>_<n>.mcap` by n (so `_10` follows `_9`)."""
    match = re.fullmatch(r"(.*?)(\d+)\.mcap", path.name)
    return (match.group(1), int(match.group(2))) if match else (path.stem, -1)


def _numbering_gaps(bag_dir: Path, on_disk: list[Path]) -> tuple[Path, ...]:
    """The split files absent from the numbering of the files on disk: for each `<name>_`,
    every `<name>_<n>.mcap` from n = 0 (rosbag2's first) up to the highest one there."""
    numbers: dict[str, set[int]] = {}
    for path in on_disk:
        match = _SPLIT_FILE.fullmatch(path.name)
        if match and int(match.group(2)) <= MAX_SPLIT_NUMBER:
            numbers.setdefault(match.group(1), set()).add(int(match.group(2)))
    return tuple(sorted((bag_dir / f"{name}{n}.mcap" for name, present in numbers.items()
                         for n in range(max(present)) if n not in present), key=_storage_order))


def _names(paths) -> str:
    """'a_5.mcap, a_6.mcap, a_7.mcap, ...' (the first three)."""
    return ", ".join(shortened(p.name) for p in paths[:3]) + (", ..." if len(paths) > 3 else "")


def _custom_data(custom, path: Path) -> tuple[dict[str, str], list[str]]:
    """metadata.yaml `custom_data` as a string map, and warnings for what was ignored: it
    is advisory (the counts our writers add), so a malformed value costs the value, not the bag."""
    if custom is None:
        return {}, []
    if not isinstance(custom, dict):
        return {}, [f"{path}: custom_data is not a map ({quoted(custom)}); ignoring it"]
    warnings = []
    for key in [k for k, v in custom.items() if isinstance(v, (dict, list))]:  # a string map: never walked
        warnings.append(f"{path}: custom_data {shortened(str(key))} is not a string; ignoring it")
        del custom[key]
    custom = {str(k): str(v) for k, v in custom.items()}
    for key, (valid, expected) in _COUNTS.items():
        if key in custom and not valid(custom[key]):
            warnings.append(f"{path}: custom_data {key} is not {expected} ({quoted(custom.pop(key))}); "
                            "ignoring it")
    return custom, warnings


def _is_count(text: str) -> bool:
    return text.isascii() and text.isdigit()


def _is_split_counts(text: str) -> bool:
    try:
        splits = json.loads(text)
    except ValueError:
        return False
    return isinstance(splits, dict) and all(
        isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in splits.values())


# The custom data our writers count episodes in: key -> (check, what it must be).
_COUNTS = {
    "gscan_ros.episodes": (_is_count, "a count"),
    "gscan_ros.splits": (_is_split_counts, "a JSON map of split names to counts"),
}


def bag_owned_files(bag_dir: str | os.PathLike) -> list[Path]:
    """The files a bag writer owns in `bag_dir` (metadata.yaml, *.mcap, the cache): the
    only ones an `--overwrite` may replace."""
    bag_dir = Path(bag_dir)
    own = (bag_dir / METADATA_FILE, *sorted(bag_dir.glob("*.mcap")), bag_dir / CACHE_DIR)
    return [p for p in own if p.exists() or p.is_symlink()]


def replaceable_bag(bag_dir: str | os.PathLike, overwrite: bool, *, flag: str = "--overwrite") -> list[Path]:
    """What must go before a new bag is written at `bag_dir`: the one overwrite rule of
    every bag writer (BagWriter, `bag repair`). Nothing there, or an empty folder: [].
    Anything else is refused without `overwrite`; with it, only a folder that holds nothing
    but a bag's own files (`bag_owned_files`) is replaced: a symbolic link, a file, or a
    folder holding anything else is refused. A refusal is one DatasetFormatError line;
    `flag` is how the caller's user allows the replacement."""
    bag_dir = Path(bag_dir)
    if bag_dir.is_symlink() or (bag_dir.exists() and not bag_dir.is_dir()):
        kind = "a symbolic link" if bag_dir.is_symlink() else "not a directory"
        raise DatasetFormatError(f"{bag_dir}: exists and is {kind} (refusing to overwrite)")
    if not bag_dir.exists() or not any(bag_dir.iterdir()):
        return []
    if not overwrite:
        raise DatasetFormatError(f"{bag_dir}: exists and is not empty (pass {flag} to replace a bag there)")
    own = bag_owned_files(bag_dir)
    foreign = sorted(p.name for p in bag_dir.iterdir() if p not in own)
    if foreign:
        names = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
        raise DatasetFormatError(f"{bag_dir}: not a bag (holds {names}); refusing to overwrite")
    return own


def remove_bag_files(paths: list[Path]) -> None:
    """Delete what `replaceable_bag` allowed (a link is removed, never followed)."""
    for path in paths:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()
