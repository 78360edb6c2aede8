"""rosbag2 `metadata.yaml` of gscan_ros bags: writing it and reading it back as `BagInfo`.

rosbag2 (and the `rosbags` reader) open a bag through this file, so it must follow
the rosbag2 schema (version 9, as written by Jazzy). Our own facts ride in the
standard `custom_data` string map under `gscan_ros.*` keys: the episode format, the
episode count per split, and whether the writer finished (`status: closed`) or is
still recording / was killed (`status: recording`).
"""
from __future__ import annotations

import json
import os
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


@dataclass(frozen=True)
class TopicInfo:
    name: str
    msg_type: str
    message_count: int


@dataclass(frozen=True)
class BagInfo:
    """What `metadata.yaml` says about a bag (counts are final only when `closed`)."""

    path: Path
    mcap_paths: tuple[Path, ...]
    version: int
    message_count: int
    start_ns: int
    duration_ns: int
    topics: dict[str, TopicInfo]
    custom: dict[str, str] = field(default_factory=dict)

    @property
    def closed(self) -> bool:
        """False while recording or when the writer died before closing the bag."""
        return self.custom.get("gscan_ros.status", STATUS_CLOSED) != STATUS_RECORDING

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
        return int(self.custom.get("gscan_ros.episodes", "0"))

    @property
    def splits(self) -> dict[str, int]:
        """Episodes per split, as recorded by the writer ({} for foreign bags)."""
        return json.loads(self.custom.get("gscan_ros.splits", "{}"))


def mcap_file_name(bag_dir: Path) -> str:
    """`<name>_0.mcap`, the first (and our only) storage file of a rosbag2 bag."""
    return f"{bag_dir.name}_0.mcap"


def write_metadata(
    bag_dir: Path,
    *,
    topic_types: dict[str, str],
    counts: dict[str, int],
    start_ns: int | None,
    end_ns: int | None,
    custom: dict[str, str],
) -> str:
    """Write `metadata.yaml` atomically (tmp + rename); returns the bagfile-information YAML."""
    total = sum(counts.values())
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
                "message_count": counts.get(topic, 0),
            }
            for topic, msg_type in topic_types.items()
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
    text = yaml.dump({"rosbag2_bagfile_information": info}, Dumper=YamlDumper, sort_keys=False)
    tmp = bag_dir / f".{METADATA_FILE}.tmp"
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, bag_dir / METADATA_FILE)
    return yaml.dump(info, Dumper=YamlDumper, sort_keys=False)


def read_bag_info(bag_dir: str | os.PathLike) -> BagInfo:
    """Parse and check `metadata.yaml`; any problem is one DatasetFormatError naming the file."""
    bag_dir = Path(bag_dir)
    path = bag_dir / METADATA_FILE
    if not path.is_file():
        raise DatasetFormatError(f"{bag_dir}: not a rosbag2 bag (no {METADATA_FILE})")
    try:
        info = read_yaml(path, str(path), DatasetFormatError)["rosbag2_bagfile_information"]
        storage = info["storage_identifier"]
        if storage != STORAGE_ID:
            raise DatasetFormatError(f"{path}: storage {quoted(storage)} is not supported (only {STORAGE_ID!r})")
        if info.get("compression_mode") not in (None, "", "none", "NONE"):
            raise DatasetFormatError(f"{path}: rosbag2 file compression is not supported (MCAP chunks are)")
        mcap_paths = tuple(bag_dir / Path(p).name for p in info["relative_file_paths"])
        topics = {
            t["topic_metadata"]["name"]: TopicInfo(
                t["topic_metadata"]["name"], t["topic_metadata"]["type"], int(t["message_count"])
            )
            for t in info["topics_with_message_count"] or []
        }
        bag = BagInfo(
            path=bag_dir,
            mcap_paths=mcap_paths,
            version=int(info["version"]),
            message_count=int(info["message_count"]),
            start_ns=int(info["starting_time"]["nanoseconds_since_epoch"]),
            duration_ns=int(info["duration"]["nanoseconds"]),
            topics=topics,
            custom={str(k): str(v) for k, v in (info.get("custom_data") or {}).items()},
        )
    except KeyError as exc:
        raise DatasetFormatError(f"{path}: missing rosbag2 key {exc}") from None
    except (TypeError, ValueError, AttributeError) as exc:
        raise DatasetFormatError(f"{path}: malformed rosbag2 metadata ({shortened(str(exc))})") from None
    if not mcap_paths:
        raise DatasetFormatError(f"{path}: relative_file_paths is empty")
    for mcap_path in mcap_paths:
        if not mcap_path.is_file():
            raise DatasetFormatError(f"{path}: storage file {shortened(mcap_path.name)} is missing")
    fmt = bag.custom.get("gscan_ros.format_version", str(EPISODE_FORMAT_VERSION))
    if fmt not in {str(version) for version in range(EPISODE_FORMAT_VERSION + 1)}:
        raise DatasetFormatError(
            f"{path}: episode format version {shortened(fmt)} is newer than supported ({EPISODE_FORMAT_VERSION})"
        )
    return bag


def bag_owned_files(bag_dir: str | os.PathLike) -> list[Path]:
    """The files a bag writer owns in `bag_dir` (metadata.yaml, *.mcap, the cache): the
    only ones an `--overwrite` may replace."""
    bag_dir = Path(bag_dir)
    own = (bag_dir / METADATA_FILE, *sorted(bag_dir.glob("*.mcap")), bag_dir / CACHE_DIR)
    return [p for p in own if p.exists()]
