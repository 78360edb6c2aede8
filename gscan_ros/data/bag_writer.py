"""Writing gscan_ros bags: generated datasets (`write_bag`, `BagWriter.write_episode`) and
live recordings (`BagWriter.write_message` of every message as received), one format:
the live topics (docs/bags.md).

MCAP profile `ros2`, CDR messages and `ros2msg` schemas with full dependency text (both
from msg_adapters), zstd chunks, and a rosbag2 `metadata.yaml`.
"""
from __future__ import annotations

import json
import os
from collections import Counter
from pathlib import Path
from typing import Iterable, Mapping

import yaml
from mcap.well_known import MessageEncoding, Profile, SchemaEncoding
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from gscan_ros import episode_status as es
from gscan_ros.data.bag_format import ACTION_DELAY_NS, EPISODE_PERIOD_NS, PROLOGUE_NS, STEP_NS, episode_record
from gscan_ros.data.bag_metadata import (
    EPISODE_FORMAT,
    EPISODE_FORMAT_VERSION,
    STATUS_CLOSED,
    STATUS_RECORDING,
    BagInfo,
    bagfile_information,
    mcap_file_name,
    read_bag_info,
    remove_bag_files,
    replaceable_bag,
    serialized_information,
    write_metadata,
)
from gscan_ros.data.bag_schema import (
    ACTION,
    COMMAND,
    COMMAND_GRAPH,
    EPISODE,
    EPISODE_STATUS,
    OBSERVATION,
    SITUATION,
    TOPICS,
    WORLD_IMAGE,
    TopicSpec,
    YamlDumper,
    offered_qos,
)
from gscan_ros.data.episode import Episode
from gscan_ros.errors import GraphError
from gscan_ros.language.graph import CommandGraph
from gscan_ros.world.types import Action
from msg_adapters import (
    action_to_cdr,
    episode_status_to_cdr,
    graph_to_cdr,
    grid_header,
    image_to_cdr,
    message_definition,
    observation_to_cdr,
    situation_to_cdr,
    text_to_cdr,
    type_hash,
)

DEFAULT_CHUNK_SIZE = 1 << 20


class BagWriter:
    """Incremental bag writer for generated datasets and live recorders.

    Use as a context manager (or `open()` / `close()`). `write_episode` writes a whole
    demonstration as the live stack would publish it, with synthetic times; a recorder
    writes each message as it came (`write_message`) and counts the episodes that end
    (`count_episode`). Both count episodes per split (metadata.yaml `gscan_ros.splits`).
    Completed chunks are flushed to the file as they fill, so a killed writer leaves a
    readable prefix; `metadata.yaml` exists from `open()` on (status `recording`) and
    gets the final counts at `close()`.
    """

    def __init__(
        self,
        bag_dir: str | os.PathLike,
        *,
        include_images: bool = False,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        overwrite: bool = False,
        overwrite_flag: str = "--overwrite",
    ):
        self.bag_dir = Path(bag_dir)
        self.mcap_path = self.bag_dir / mcap_file_name(self.bag_dir)
        self.include_images = include_images
        self._chunk_size = chunk_size
        self._overwrite = overwrite
        self._overwrite_flag = overwrite_flag  # how the user allows it, for the refusal's message
        self._file = None
        self._mcap: McapWriter | None = None
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}  # (topic, type) -> channel id
        self._channel_topics: dict[int, tuple[str, str]] = {}  # channel id -> (topic, type), registration order
        self._counts: Counter[int] = Counter()  # messages per channel id
        self._splits: Counter[str] = Counter()
        self._start_ns: int | None = None
        self._end_ns: int | None = None
        self.episodes_written = 0
        self._publish_ordered = True  # every message so far in publish-time order (readers skip reordering)
        self._last_publish_ns = 0
        self.custom_data: dict[str, str] = {}  # extra metadata.yaml custom_data (`bag repair`'s notes)
        # The episode format the messages follow: `bag repair` copies a format-1 bag as format 1.
        self.format_version = EPISODE_FORMAT_VERSION

    # -- lifecycle -------------------------------------------------------------------
    def open(self) -> "BagWriter":
        self._prepare_dir()
        self._file = open(self.mcap_path, "wb")
        self._mcap = McapWriter(self._file, chunk_size=self._chunk_size, compression=CompressionType.ZSTD)
        self._mcap.start(profile=Profile.ROS2, library="gscan_ros")
        self._file.flush()
        self._write_metadata(STATUS_RECORDING)
        return self

    def close(self) -> None:
        """Finish the MCAP summary, then write the final `metadata.yaml`: a finish that
        fails (a full disk) leaves the bag `recording`, as a killed writer's."""
        if self._mcap is None:
            return
        info = self._information(STATUS_CLOSED)
        try:
            # rosbag2's MCAP storage also embeds the bag metadata in the file.
            self._mcap.add_metadata("rosbag2", {"serialized_metadata": serialized_information(info)})
            self._mcap.finish()
        finally:
            self._file.close()
            self._mcap = self._file = None
        write_metadata(self.bag_dir, info)

    def abandon(self) -> None:
        """Stop without finishing: what was written stays an unfinished bag (status
        `recording`, no MCAP summary), as a killed writer's, which every reader reports
        as incomplete; a bag cut short must never read as a closed, whole one."""
        if self._mcap is None:
            return
        try:
            self.flush()
        finally:
            self._file.close()
            self._mcap = self._file = None

    def __enter__(self) -> "BagWriter":
        return self.open()

    def __exit__(self, exc_type, *exc_info) -> None:
        if exc_type is None:
            self.close()
        else:  # an error or an interrupt (KeyboardInterrupt) cut the writing short
            self.abandon()

    def flush(self) -> None:
        """Write the chunk in progress and refresh metadata.yaml (a recorder's episode end)."""
        self._require_open()
        self._mcap.flush()
        self._write_metadata(STATUS_RECORDING)

    # -- writing -----------------------------------------------------------------------
    def write_message(self, topic: str, msg_type: str, data: bytes, t_ns: int, publish_ns: int | None = None) -> None:
        """Append one serialized message of `msg_type` ("pkg/msg/Type", CDR `data` as
        msg_adapters makes it) on `topic`, received at `t_ns` (the log time) and published
        at `publish_ns` (the DDS source timestamp; default `t_ns`)."""
        self._write(topic, msg_type, data, t_ns, publish_ns)
        self._file.flush()  # cheap when empty; pushes out a chunk the MCAP writer just closed

    def write_episode(
        self,
        episode: Episode,
        *,
        graph: CommandGraph | None = None,
        include_images: bool | None = None,
        t0_ns: int | None = None,
    ) -> int:
        """Write one demonstration as the live stack publishes it; returns its last time.

        At t0: `/episode` (what the dataset knows of it), the world's `/situation` and
        `/observation` 0, the `/command`, its `/command_graph` (optional) and the policy's
        ACTIVE report; then action t at +(t+1) ms and the world's reply half a millisecond
        later; `<eos>` and the SUCCEEDED report close it (docs/bags.md "Episodes").
        """
        images = self.include_images if include_images is None else include_images
        if t0_ns is None:
            t0_ns = self.episodes_written * EPISODE_PERIOD_NS
            if self._end_ns is not None:
                t0_ns = max(t0_ns, self._end_ns + STEP_NS)
        episode_id = str(self.episodes_written)
        prologue = iter(range(t0_ns, t0_ns + STEP_NS, PROLOGUE_NS))
        record = episode_record(episode, episode_id, self.episodes_written)
        self._write_topic(EPISODE, text_to_cdr(json.dumps(record, separators=(",", ":"))), next(prologue))
        self._write_topic(SITUATION, situation_to_cdr(episode.situation), next(prologue))
        world = None
        if images:
            from gscan_ros.world.world import World

            world = World(episode.situation)
        states = iter(episode.states())
        self._write_state(next(states), world, next(prologue))
        self._write_topic(COMMAND, text_to_cdr(episode.command), next(prologue))
        if graph is not None:
            self._write_topic(COMMAND_GRAPH, graph_to_cdr(graph), next(prologue))
        start_ns = next(prologue)
        self._write_topic(EPISODE_STATUS, episode_status_to_cdr(es.EpisodeStatus(episode_id, start_ns, es.ACTIVE)),
                          start_ns)
        t_ns = start_ns
        for t, action in enumerate((*episode.actions, Action.EOS)):
            t_ns = t0_ns + (t + 1) * STEP_NS
            self._write_topic(ACTION, action_to_cdr(action), t_ns)
            if action is not Action.EOS:
                if world is not None:
                    world.step(action)
                self._write_state(next(states), world, t_ns + ACTION_DELAY_NS)
        self._write_topic(EPISODE_STATUS, episode_status_to_cdr(es.EpisodeStatus(episode_id, start_ns, es.COMPLETE)),
                          t_ns + ACTION_DELAY_NS)
        self.count_episode(episode.split)
        self._file.flush()
        return self._end_ns

    def _write_state(self, state, world, t_ns: int) -> None:
        """The world's state at `t_ns`, stamped with that time as the live world stamps it."""
        self._write_topic(OBSERVATION, observation_to_cdr(state, header=grid_header(t_ns)), t_ns)
        if world is not None:
            from gscan_ros.world.render import render

            self._write_topic(WORLD_IMAGE, image_to_cdr(render(world), header=grid_header(t_ns)), t_ns)

    def count_episode(self, split: str | None) -> None:
        """One more episode written (of `split`, when known): numbering and metadata counts."""
        self.episodes_written += 1
        if split is not None:
            self._splits[split] += 1

    # -- internals ---------------------------------------------------------------------
    def _prepare_dir(self) -> None:
        """Make way for the bag (`replaceable_bag`: with `overwrite`, only an old bag's own
        files go) and create its directory."""
        remove_bag_files(replaceable_bag(self.bag_dir, self._overwrite, flag=self._overwrite_flag))
        self.bag_dir.mkdir(parents=True, exist_ok=True)

    def _require_open(self) -> None:
        if self._mcap is None:
            raise RuntimeError(f"bag writer for {self.bag_dir} is not open")

    def _write_topic(self, topic: TopicSpec, data: bytes, t_ns: int) -> None:
        self._write(topic.name, topic.msg_type, data, t_ns)

    def _write(self, topic: str, msg_type: str, data: bytes, t_ns: int, publish_ns: int | None = None) -> None:
        self._require_open()
        self.add_record(self.channel(topic, msg_type), data, t_ns, t_ns if publish_ns is None else publish_ns, 0)

    @property
    def last_publish_ns(self) -> int:
        """The latest publish time written so far (0: none): a message that must come last goes after it."""
        return self._last_publish_ns

    # -- channels and records (`bag repair` copies another bag's through these) ------------
    def channel(self, topic: str, msg_type: str, **kwargs) -> int:
        """The channel of `topic` carrying `msg_type`, registered on first use (`register_channel`
        with `kwargs`): a topic of two types (merged recordings) keeps a channel for each."""
        channel_id = self._channels.get((topic, msg_type))
        return self.register_channel(topic, msg_type, **kwargs) if channel_id is None else channel_id

    def add_record(self, channel_id: int, data: bytes, log_time: int, publish_time: int, sequence: int) -> None:
        """Append serialized message bytes on a registered channel, times and sequence as given."""
        self._mcap.add_message(channel_id, log_time=log_time, publish_time=publish_time, data=data, sequence=sequence)
        self._publish_ordered &= publish_time >= self._last_publish_ns
        self._last_publish_ns = max(self._last_publish_ns, publish_time)
        self._counts[channel_id] += 1
        self._start_ns = log_time if self._start_ns is None else min(self._start_ns, log_time)
        self._end_ns = log_time if self._end_ns is None else max(self._end_ns, log_time)

    def register_channel(
        self,
        topic: str,
        msg_type: str,
        *,
        schema: tuple[str, bytes] | None = None,
        message_encoding: str = MessageEncoding.CDR,
        metadata: Mapping[str, str] | None = None,
    ) -> int:
        """Add `topic`'s channel (and its type's schema); `schema` = (encoding, text) and
        `metadata` keep a copied channel's own (`bag repair`), else ours are generated.
        A channel of ours must have the interface table's type; a copied one keeps its
        own (another node's topic of the same name, which readers leave aside)."""
        spec = TOPICS.get(topic)
        if schema is None and spec is not None and not spec.carries(msg_type):
            raise TypeError(f"topic {topic} carries {spec.msg_type}, got a {msg_type}")
        schema_id = self._schemas.get(msg_type)
        if schema_id is None:
            if schema is None:
                schema = (SchemaEncoding.ROS2, message_definition(msg_type).encode())
            encoding, text = schema
            schema_id = self._mcap.register_schema(msg_type, encoding, text)
            self._schemas[msg_type] = schema_id
        if metadata is None:
            # rosbag2's MCAP storage keeps the offered QoS and type hash per channel.
            metadata = {
                "offered_qos_profiles": yaml.dump([offered_qos(topic)], Dumper=YamlDumper, sort_keys=False),
                "topic_type_hash": type_hash(msg_type),
            }
        channel_id = self._mcap.register_channel(topic, message_encoding, schema_id, metadata=dict(metadata))
        self._channels[(topic, msg_type)] = channel_id
        self._channel_topics[channel_id] = (topic, msg_type)
        return channel_id

    def _write_metadata(self, status: str) -> None:
        write_metadata(self.bag_dir, self._information(status))

    def _information(self, status: str) -> dict:
        return bagfile_information(
            self.bag_dir,
            topics=[(topic, msg_type, self._counts[channel_id])
                    for channel_id, (topic, msg_type) in self._channel_topics.items()],
            start_ns=self._start_ns,
            end_ns=self._end_ns,
            custom={
                **self.custom_data,
                "gscan_ros.format": EPISODE_FORMAT,
                "gscan_ros.format_version": str(self.format_version),
                "gscan_ros.status": status,
                "gscan_ros.splits": json.dumps(dict(sorted(self._splits.items()))),
                "gscan_ros.episodes": str(self.episodes_written),
                "gscan_ros.publish_ordered": "true" if self._publish_ordered else "false",
            },
        )


def write_bag(
    bag_dir: str | os.PathLike,
    episodes: Iterable[Episode],
    *,
    graphs: Mapping[str, CommandGraph] | None = None,
    include_images: bool = False,
    overwrite: bool = False,
) -> BagInfo:
    """Write `episodes` as one bag; `graphs` maps a command to its CommandGraph (optional)."""
    with BagWriter(bag_dir, include_images=include_images, overwrite=overwrite) as writer:
        for episode in episodes:
            graph = None
            if graphs is not None:
                graph = graphs.get(episode.command)
                if graph is None:
                    raise GraphError(f"no command graph given for command {episode.command!r}")
            writer.write_episode(episode, graph=graph)
    return read_bag_info(bag_dir)
