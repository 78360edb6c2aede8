"""Episodes as rosbag2 bags: a directory with `metadata.yaml` and `<name>_0.mcap` (docs/bags.md).

The public bag API, gathered from the modules that implement it:

- `bag_format`: the episode conventions (format 2: the live topics; format 1: `/command` headers);
- `episode_assembly`: the rule that cuts the live topics into episodes;
- `bag_writer`: `BagWriter`, `write_bag` (generated datasets and live recordings);
- `bag_reader`: `BagEpisodeReader`, `iter_bag_episodes` (Episodes back, with a `BagReadReport`);
- `bag_scan`: `McapScan`, the record-by-record MCAP reader that recovers around damage;
- `bag_repair`: `repair_bag` (a damaged or unfinished bag rewritten as a complete one);
- `bag_metadata` / `bag_schema`: metadata.yaml (`BagInfo`) and topics, QoS and schemas.

The topics are the live stack's (`gscan_ros.interface`), so a recorded run and a
generated dataset are one format.
"""
from __future__ import annotations

from gscan_ros.data.bag_format import (
    ACTION_DELAY_NS,
    EPISODE_PERIOD_NS,
    LIVE_SPLIT,
    READER_META_KEYS,
    STEP_NS,
    GraphCache,
    episode_from_header,
    legacy_header,
)
from gscan_ros.data.bag_metadata import BagInfo, read_bag_info
from gscan_ros.data.bag_reader import BagEpisodeReader, RecordedEpisode, iter_bag_episodes
from gscan_ros.data.bag_repair import RepairResult, repair_bag
from gscan_ros.data.bag_report import BagReadReport
from gscan_ros.data.bag_scan import McapScan
from gscan_ros.data.bag_writer import DEFAULT_CHUNK_SIZE, BagWriter, write_bag

__all__ = [
    "ACTION_DELAY_NS",
    "DEFAULT_CHUNK_SIZE",
    "EPISODE_PERIOD_NS",
    "LIVE_SPLIT",
    "READER_META_KEYS",
    "STEP_NS",
    "BagEpisodeReader",
    "BagInfo",
    "BagReadReport",
    "BagWriter",
    "GraphCache",
    "McapScan",
    "RecordedEpisode",
    "RepairResult",
    "episode_from_header",
    "legacy_header",
    "iter_bag_episodes",
    "read_bag_info",
    "repair_bag",
    "write_bag",
]
