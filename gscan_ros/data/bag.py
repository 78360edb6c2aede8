"""Episodes as rosbag2 bags: a directory with `metadata.yaml` and `<name>_0.mcap`.

MCAP profile `ros2`, CDR messages (rclpy serialization via msg_adapters), `ros2msg` schemas with full
dependency text, zstd chunks. The topics are the live stack's (DESIGN.md), so a
recorded run and a generated dataset are one format. Episode convention (docs/bags.md):

- a `/command` message starts an episode; its String data is a JSON header
  `{"version": 1, "episode_id", "split", "example_id", "command", "situation": <gSCAN
  situation JSON>, "meta"}`;
- optionally one `/command_graph` (CommandGraph JSON);
- then for t = 0..T: `/observation` t (+ `/world_image` t), then `/action` t, where the
  last action is `<eos>`, which closes the episode.

An episode without its `<eos>` (writer killed, file truncated) is incomplete: the
reader drops it and counts it in `BagReadReport`. Generated data gets synthetic
times (episode i at i s, step t at +(t+1) ms, the action half a millisecond after
its observation); live recordings pass real times to `BagWriter.write_message`.
"""
from __future__ import annotations

import json
import logging
import os
import shutil
import struct
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator, Mapping

import numpy as np
import yaml
import zstandard
from mcap.exceptions import McapError
from mcap.records import Channel, Header, Message
from mcap.stream_reader import StreamReader
from mcap.well_known import MessageEncoding, Profile, SchemaEncoding
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from std_msgs.msg import String, UInt8MultiArray

from gscan_ros.data.bag_metadata import (
    EPISODE_FORMAT,
    EPISODE_FORMAT_VERSION,
    METADATA_FILE,
    STATUS_CLOSED,
    STATUS_RECORDING,
    BagInfo,
    mcap_file_name,
    read_bag_info,
    write_metadata,
)
from gscan_ros.data.bag_schema import (
    ACTION,
    COMMAND,
    COMMAND_GRAPH,
    OBSERVATION,
    TOPICS,
    VOLATILE_QOS,
    WORLD_IMAGE,
    YamlDumper,
    message_definition,
    msg_type_name,
    type_hash,
)
from gscan_ros.data.episode import Episode
from gscan_ros.errors import DatasetFormatError, GraphError, GscanError
from gscan_ros.language.graph import CommandGraph
from gscan_ros.world.types import Action, Situation
from msg_adapters import (
    action_to_msg,
    cdr_to_msg,
    graph_to_msg,
    image_to_msg,
    msg_to_action,
    msg_to_cdr,
    msg_to_observation,
    observation_to_msg,
)

__all__ = [
    "BagEpisodeReader",
    "BagInfo",
    "BagReadReport",
    "BagWriter",
    "RecordedEpisode",
    "iter_bag_episodes",
    "read_bag_info",
    "write_bag",
]

log = logging.getLogger(__name__)

EPISODE_PERIOD_NS = 1_000_000_000  # generated episode i starts at i seconds
STEP_NS = 1_000_000  # step t of an episode at +(t+1) ms
ACTION_DELAY_NS = STEP_NS // 2  # an action follows its observation
DEFAULT_CHUNK_SIZE = 1 << 20
EPISODE_TOPICS = frozenset(t.name for t in (COMMAND, COMMAND_GRAPH, OBSERVATION, ACTION, WORLD_IMAGE))
# Episode.meta keys the reader adds (not stored in the header, so re-writing is clean).
READER_META_KEYS = frozenset({"episode_id", "command_graph"})


def episode_header(episode: Episode, episode_id: int) -> dict:
    """The JSON header a `/command` message carries (see module docstring)."""
    return {
        "version": EPISODE_FORMAT_VERSION,
        "episode_id": episode_id,
        "split": episode.split,
        "example_id": episode.example_id,
        "command": episode.command,
        "situation": episode.situation.to_json(),
        "meta": {k: v for k, v in episode.meta.items() if k not in READER_META_KEYS},
    }


def episode_from_header(header: dict, actions: Iterable[Action], where: str) -> Episode:
    """Rebuild an Episode from its `/command` header and recorded actions (EOS excluded)."""
    try:
        episode_id = header["episode_id"]
        return Episode(
            command=header["command"],
            situation=Situation.from_json(header["situation"]),
            actions=tuple(actions),
            split=header["split"],
            example_id=header.get("example_id"),
            meta={**(header.get("meta") or {}), "episode_id": episode_id},
        )
    except KeyError as exc:
        raise DatasetFormatError(f"{where}: episode header lacks field {exc}") from None
    except GscanError as exc:
        raise DatasetFormatError(f"{where}: episode {header.get('episode_id')}: {exc}") from None


class GraphCache:
    """Parses each distinct CommandGraph JSON once (a bag repeats the same few hundred)."""

    def __init__(self) -> None:
        self._graphs: dict[str, CommandGraph] = {}

    def attach(self, episode: Episode, graph_json: str | None, where: str) -> None:
        """Put the parsed graph into `episode.meta["command_graph"]` (no-op without one)."""
        if not graph_json:
            return
        graph = self._graphs.get(graph_json)
        if graph is None:
            try:
                graph = self._graphs[graph_json] = CommandGraph.from_json(graph_json)
            except GscanError as exc:
                raise DatasetFormatError(f"{where}: command_graph: {exc}") from None
        episode.meta["command_graph"] = graph


class BagWriter:
    """Incremental bag writer for generated datasets and live recorders.

    Use as a context manager (or `open()` / `close()`). `write_episode` writes a whole
    demonstration; a live recorder calls `write_message(topic, msg, t_ns)` as messages
    arrive and `flush()` at each episode end. Completed chunks are flushed to the file
    as they fill, so a killed writer leaves a readable prefix; `metadata.yaml` exists
    from `open()` on (status `recording`) and gets the final counts at `close()`.
    """

    def __init__(
        self,
        bag_dir: str | os.PathLike,
        *,
        include_images: bool = False,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        overwrite: bool = False,
    ):
        self.bag_dir = Path(bag_dir)
        self.mcap_path = self.bag_dir / mcap_file_name(self.bag_dir)
        self.include_images = include_images
        self._chunk_size = chunk_size
        self._overwrite = overwrite
        self._file = None
        self._mcap: McapWriter | None = None
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._topic_types: dict[str, str] = {}
        self._counts: Counter[str] = Counter()
        self._splits: Counter[str] = Counter()
        self._start_ns: int | None = None
        self._end_ns: int | None = None
        self.episodes_written = 0

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
        """Finish the MCAP summary and write the final `metadata.yaml`."""
        if self._mcap is None:
            return
        info_yaml = self._write_metadata(STATUS_CLOSED)
        # rosbag2's MCAP storage also embeds the bag metadata in the file.
        self._mcap.add_metadata("rosbag2", {"serialized_metadata": info_yaml})
        self._mcap.finish()
        self._file.close()
        self._mcap = self._file = None

    def __enter__(self) -> "BagWriter":
        return self.open()

    def __exit__(self, *exc_info) -> None:
        self.close()

    def flush(self) -> None:
        """Write the chunk in progress and refresh metadata.yaml (a recorder's episode end)."""
        self._require_open()
        self._mcap.flush()
        self._write_metadata(STATUS_RECORDING)

    # -- writing -----------------------------------------------------------------------
    def write_message(self, topic: str, msg, t_ns: int) -> None:
        """Append one ROS message (any rosidl type) on `topic` at log time `t_ns`."""
        self._write(topic, msg, t_ns)
        self._file.flush()  # cheap when empty; pushes out a chunk the MCAP writer just closed

    def write_episode(
        self,
        episode: Episode,
        *,
        graph: CommandGraph | None = None,
        include_images: bool | None = None,
        t0_ns: int | None = None,
    ) -> int:
        """Write one episode (header, graph, observation/action steps, `<eos>`); returns its last time."""
        images = self.include_images if include_images is None else include_images
        if t0_ns is None:
            t0_ns = self.episodes_written * EPISODE_PERIOD_NS
            if self._end_ns is not None:
                t0_ns = max(t0_ns, self._end_ns + STEP_NS)
        header = json.dumps(episode_header(episode, self.episodes_written), separators=(",", ":"))
        self._write(COMMAND.name, String(data=header), t0_ns)
        if graph is not None:
            self._write(COMMAND_GRAPH.name, graph_to_msg(graph), t0_ns + ACTION_DELAY_NS)
        world = None
        if images:
            from gscan_ros.world.world import World

            world = World(episode.situation)
        steps = (*episode.actions, Action.EOS)
        for t, (state, action) in enumerate(zip(episode.states(), steps)):
            t_ns = t0_ns + (t + 1) * STEP_NS
            self._write(OBSERVATION.name, observation_to_msg(state), t_ns)
            if world is not None:
                self._write(WORLD_IMAGE.name, image_to_msg(world.render()), t_ns)
                if action is not Action.EOS:
                    world.step(action)
            self._write(ACTION.name, action_to_msg(action), t_ns + ACTION_DELAY_NS)
        self.episodes_written += 1
        self._splits[episode.split] += 1
        self._file.flush()
        return self._end_ns

    # -- internals ---------------------------------------------------------------------
    def _prepare_dir(self) -> None:
        if self.bag_dir.exists() and any(self.bag_dir.iterdir()):
            if not self._overwrite:
                raise DatasetFormatError(f"{self.bag_dir}: exists and is not empty (refusing to overwrite)")
            if not (self.bag_dir / METADATA_FILE).is_file():
                raise DatasetFormatError(f"{self.bag_dir}: exists and is not a bag (refusing to overwrite)")
            for path in self.bag_dir.iterdir():
                if path.is_dir():
                    shutil.rmtree(path)
                else:
                    path.unlink()
        self.bag_dir.mkdir(parents=True, exist_ok=True)

    def _require_open(self) -> None:
        if self._mcap is None:
            raise RuntimeError(f"bag writer for {self.bag_dir} is not open")

    def _write(self, topic: str, msg, t_ns: int) -> None:
        self._require_open()
        channel_id = self._channels.get(topic)
        if channel_id is None:
            channel_id = self._register(topic, msg_type_name(type(msg)))
        self._mcap.add_message(channel_id, log_time=t_ns, publish_time=t_ns, data=msg_to_cdr(msg))
        self._counts[topic] += 1
        self._start_ns = t_ns if self._start_ns is None else min(self._start_ns, t_ns)
        self._end_ns = t_ns if self._end_ns is None else max(self._end_ns, t_ns)

    def _register(self, topic: str, msg_type: str) -> int:
        spec = TOPICS.get(topic)
        if spec is not None and spec.msg_type != msg_type:
            raise TypeError(f"topic {topic} carries {spec.msg_type}, got a {msg_type}")
        schema_id = self._schemas.get(msg_type)
        if schema_id is None:
            schema_id = self._mcap.register_schema(
                msg_type, SchemaEncoding.ROS2, message_definition(msg_type).encode()
            )
            self._schemas[msg_type] = schema_id
        qos = spec.qos if spec is not None else VOLATILE_QOS
        channel_id = self._mcap.register_channel(
            topic,
            MessageEncoding.CDR,
            schema_id,
            # rosbag2's MCAP storage keeps the offered QoS and type hash per channel.
            metadata={
                "offered_qos_profiles": yaml.dump([qos], Dumper=YamlDumper, sort_keys=False),
                "topic_type_hash": type_hash(msg_type),
            },
        )
        self._channels[topic] = channel_id
        self._topic_types[topic] = msg_type
        return channel_id

    def _write_metadata(self, status: str) -> str:
        return write_metadata(
            self.bag_dir,
            topic_types=self._topic_types,
            counts=self._counts,
            start_ns=self._start_ns,
            end_ns=self._end_ns,
            custom={
                "gscan_ros.format": EPISODE_FORMAT,
                "gscan_ros.format_version": str(EPISODE_FORMAT_VERSION),
                "gscan_ros.status": status,
                "gscan_ros.splits": json.dumps(dict(sorted(self._splits.items()))),
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


# ---------------------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------------------
@dataclass
class BagReadReport:
    """What a read recovered; `lost_*` compare against metadata.yaml when the writer closed."""

    bag_dir: Path
    expected_messages: int | None = None
    expected_episodes: int | None = None
    messages_read: int = 0
    episodes_read: int = 0  # complete episodes, whatever the split filter
    incomplete_episodes: int = 0  # started, never reached `<eos>`
    discarded_messages: int = 0  # read but outside any complete episode
    truncated_files: list[Path] = field(default_factory=list)  # ended before the MCAP footer
    unread_bytes: int = 0  # trailing bytes that held no complete record

    @property
    def truncated(self) -> bool:
        return bool(self.truncated_files)

    @property
    def lost_messages(self) -> int:
        """Messages not delivered in a complete episode (a lower bound when the writer died)."""
        kept = self.messages_read - self.discarded_messages
        if self.expected_messages is not None:
            return max(self.expected_messages - kept, 0)
        return self.discarded_messages

    @property
    def lost_episodes(self) -> int:
        if self.expected_episodes is not None:
            return max(self.expected_episodes - self.episodes_read, 0)
        return self.incomplete_episodes

    def summary(self) -> str:
        return (
            f"{self.bag_dir}: recovered {self.episodes_read} complete episodes; lost {self.lost_episodes} "
            f"episodes / {self.lost_messages} messages ({self.incomplete_episodes} incomplete, "
            f"{self.unread_bytes} unreadable trailing bytes)"
        )


@dataclass(frozen=True)
class RecordedEpisode:
    """An episode as recorded: the Episode, its observations (if decoded) and graph JSON."""

    episode: Episode
    header: dict
    states: np.ndarray | None  # uint8[T+1, 6, 6, 16]
    graph_json: str | None


class _ObservationDecoder:
    """CDR bytes -> uint8[6, 6, 16], decoding the layout once per distinct CDR prefix.

    Every observation of a bag has the same layout, so its CDR bytes differ only in the
    trailing data block. The first message with a new prefix is decoded in full with
    rclpy and checked (msg_to_observation); later ones with a byte-identical prefix
    (same layout, same data length) are the same message up to that tail, so the tail
    is their data.
    """

    def __init__(self) -> None:
        self._prefixes: dict[bytes, tuple[int, tuple[int, ...]]] = {}

    def __call__(self, data: bytes) -> np.ndarray:
        for prefix, (size, shape) in self._prefixes.items():
            if len(data) == len(prefix) + size and data.startswith(prefix):
                return np.frombuffer(data, np.uint8, count=size, offset=len(prefix)).reshape(shape)
        observation = msg_to_observation(cdr_to_msg(data, UInt8MultiArray))
        size = observation.size
        if data[len(data) - size :] == observation.tobytes():
            self._prefixes[bytes(data[: len(data) - size])] = (size, observation.shape)
        return observation


@dataclass
class _OpenEpisode:
    header: dict | None  # None: a `/command` without a JSON header (plain-text live command)
    selected: bool
    messages: int = 1
    actions: list = field(default_factory=list)
    observations: list = field(default_factory=list)
    observation_count: int = 0
    graph_json: str | None = None


class BagEpisodeReader(Iterator[Episode]):
    """Streaming reader: iterate it for Episodes; `report` describes what was recovered.

    Reads each MCAP file front to back with the non-seeking `mcap` StreamReader, so a bag
    whose writer was killed (no summary, torn last chunk) still yields every complete
    episode. Damage before the end of a file, or a file that is not MCAP, raises one
    DatasetFormatError naming the file.
    """

    def __init__(self, bag_dir: str | os.PathLike, splits: Iterable[str] | None = None, *, decode_states=False):
        self.info = read_bag_info(bag_dir)
        self.splits = None if splits is None else frozenset(splits)
        self.decode_states = decode_states
        self.report = BagReadReport(
            self.info.path,
            expected_messages=self.info.message_count if self.info.closed else None,
            expected_episodes=self.info.episodes,
        )
        self._episodes = (r.episode for r in self.records())

    def __next__(self) -> Episode:
        return next(self._episodes)

    def records(self) -> Iterator[RecordedEpisode]:
        """Complete episodes in bag order (with observations when `decode_states`)."""
        action_cache: dict[bytes, Action] = {}  # CDR bytes of the 7 action tokens
        decode_observation = _ObservationDecoder()
        graphs = GraphCache()
        current: _OpenEpisode | None = None
        for path, topic, data in self._messages():
            self.report.messages_read += 1
            if topic == COMMAND.name:
                self._drop(current)
                current = self._start(path, data)
                continue
            if current is None:  # between episodes: only episode topics count as lost data
                self.report.discarded_messages += topic in EPISODE_TOPICS
                continue
            current.messages += 1
            if topic == OBSERVATION.name:
                current.observation_count += 1
                if self.decode_states and current.selected:
                    current.observations.append(decode_observation(data))
            elif topic == ACTION.name:
                action = action_cache.get(data)
                if action is None:
                    action = self._decode_action(path, data, current)
                    action_cache[bytes(data)] = action
                if action is not Action.EOS:
                    current.actions.append(action)
                    continue
                done, current = current, None
                self.report.episodes_read += 1
                if done.selected:
                    yield self._finish(path, done, graphs)
            elif topic == COMMAND_GRAPH.name:
                current.graph_json = cdr_to_msg(data, String).data
        self._drop(current)
        if self.report.lost_episodes or self.report.lost_messages or self.report.truncated:
            log.warning(self.report.summary())

    # -- episode assembly ---------------------------------------------------------------
    def _start(self, path: Path, data: bytes) -> _OpenEpisode:
        text = cdr_to_msg(data, String).data
        try:
            header = json.loads(text)
        except json.JSONDecodeError:
            header = None
        if not isinstance(header, dict) or "situation" not in header:
            # A live command typed as plain text carries no initial situation: unusable.
            return _OpenEpisode(header=None, selected=False)
        version = header.get("version")
        if not isinstance(version, int) or version > EPISODE_FORMAT_VERSION:
            raise DatasetFormatError(f"{path}: episode header version {version!r} is not supported")
        selected = self.splits is None or header.get("split") in self.splits
        return _OpenEpisode(header=header, selected=selected)

    def _drop(self, episode: _OpenEpisode | None) -> None:
        if episode is not None:
            self.report.incomplete_episodes += 1
            self.report.discarded_messages += episode.messages

    def _decode_action(self, path: Path, data: bytes, episode: _OpenEpisode) -> Action:
        try:
            return msg_to_action(cdr_to_msg(data, String))
        except GscanError as exc:
            where = episode.header.get("episode_id") if episode.header else "?"
            raise DatasetFormatError(f"{path}: episode {where}: {exc}") from None

    def _finish(self, path: Path, done: _OpenEpisode, graphs: GraphCache) -> RecordedEpisode:
        if done.header is None:
            raise AssertionError("unselected episodes are never finished")
        where = f"{path}: episode {done.header.get('episode_id')}"
        if done.observation_count != len(done.actions) + 1:
            raise DatasetFormatError(
                f"{where}: {done.observation_count} observations for {len(done.actions) + 1} actions (with <eos>)"
            )
        episode = episode_from_header(done.header, done.actions, str(path))
        graphs.attach(episode, done.graph_json, where)
        states = np.stack(done.observations) if self.decode_states else None
        return RecordedEpisode(episode, done.header, states, done.graph_json)

    # -- MCAP ------------------------------------------------------------------------------
    def _messages(self) -> Iterator[tuple[Path, str, bytes]]:
        for path in self.info.mcap_paths:
            yield from self._file_messages(path)

    def _file_messages(self, path: Path) -> Iterator[tuple[Path, str, bytes]]:
        size = path.stat().st_size
        topics: dict[int, str] = {}
        seen_header = False
        good_until = 0  # file offset after the last complete record
        with open(path, "rb") as stream:
            records = StreamReader(stream, validate_crcs=True, record_size_limit=size).records
            try:
                for record in records:
                    good_until = stream.tell()
                    if isinstance(record, Message):
                        yield path, topics.get(record.channel_id), record.data
                    elif isinstance(record, Channel):
                        topics[record.id] = record.topic
                    elif isinstance(record, Header):
                        seen_header = True
                        if record.profile != Profile.ROS2:
                            raise DatasetFormatError(f"{path}: MCAP profile {record.profile!r} is not 'ros2'")
            except (McapError, struct.error, zstandard.ZstdError, ValueError, EOFError) as exc:
                if not seen_header:
                    raise DatasetFormatError(f"{path}: not an MCAP file ({exc.__class__.__name__})") from None
                if stream.tell() < size:
                    raise DatasetFormatError(
                        f"{path}: corrupt MCAP data before byte {stream.tell()} ({exc.__class__.__name__}: {exc})"
                    ) from None
                self.report.truncated_files.append(path)
                self.report.unread_bytes += size - good_until


def iter_bag_episodes(bag_dir: str | os.PathLike, splits: Iterable[str] | None = None) -> BagEpisodeReader:
    """Stream the complete episodes of a bag (optionally only `splits`), in bag order.

    The returned iterator's `report` (a BagReadReport) says, once exhausted, how many
    episodes/messages were recovered and lost; losses are also logged as a warning.
    """
    return BagEpisodeReader(bag_dir, splits)
