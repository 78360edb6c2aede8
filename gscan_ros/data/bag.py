"""Episodes as rosbag2 bags: a directory with `metadata.yaml` and `<name>_0.mcap`.

MCAP profile `ros2`, CDR messages (rclpy serialization via msg_adapters), `ros2msg` schemas with full
dependency text, zstd chunks. The topics are the live stack's (DESIGN.md), so a
recorded run and a generated dataset are one format. Episode convention (docs/bags.md):

- a `/command` message starts an episode; its String data is a JSON header
  `{"version": 1, "episode_id", "split", "example_id", "command", "situation": <gSCAN
  situation JSON>, "meta"}`;
- optionally one `/command_graph` (CommandGraph JSON);
- then for t = 0..T: `/observation` t (+ `/world_image` t), then `/action` t, where the
  last action is `<eos>`, which closes the episode. A live episode that a world reset
  ended is written the same way with `"outcome": "aborted"` in its header; readers skip
  it (`include_aborted` to get it) and count it in `BagReadReport.aborted_episodes`.

An episode without its `<eos>` (writer killed, file truncated) or with messages in a
damaged chunk is incomplete: the reader drops it and counts it in `BagReadReport`;
reading goes on at the next intact chunk (`McapScan`). `repair_bag` rewrites what can be
read as a complete, indexed bag. Generated data gets synthetic
times (episode i at i s, step t at +(t+1) ms, the action half a millisecond after
its observation); live recordings pass real times to `BagWriter.write_message`.
"""
from __future__ import annotations

import io
import json
import logging
import mmap
import os
import shutil
import struct
import tempfile
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator, Mapping

import numpy as np
import yaml
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.records import Channel, ChunkIndex, Schema
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
    bag_owned_files,
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
    "McapScan",
    "RecordedEpisode",
    "RepairResult",
    "iter_bag_episodes",
    "read_bag_info",
    "repair_bag",
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
# Header "outcome" (absent: complete). An aborted episode (a live one that the world's
# reset ended) is framed like the others, its `<eos>` stamped when it ended, and is
# skipped by readers unless asked for: it is no demonstration (docs/bags.md).
OUTCOME_COMPLETE = "complete"
OUTCOME_ABORTED = "aborted"


def episode_header(episode: Episode, episode_id: int, outcome: str = OUTCOME_COMPLETE) -> dict:
    """The JSON header a `/command` message carries (see module docstring)."""
    header = {
        "version": EPISODE_FORMAT_VERSION,
        "episode_id": episode_id,
        "split": episode.split,
        "example_id": episode.example_id,
        "command": episode.command,
        "situation": episode.situation.to_json(),
        "meta": {k: v for k, v in episode.meta.items() if k not in READER_META_KEYS},
    }
    if outcome != OUTCOME_COMPLETE:
        header["outcome"] = outcome
    return header


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
        self.custom_data: dict[str, str] = {}  # extra metadata.yaml custom_data (`bag repair`'s notes)

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
        """Refuse a non-empty directory; with `overwrite`, replace only an old bag's own
        files (metadata.yaml, *.mcap and the decode cache) and refuse anything else there."""
        if self.bag_dir.exists() and not self.bag_dir.is_dir():
            raise DatasetFormatError(f"{self.bag_dir}: exists and is not a directory (refusing to overwrite)")
        if self.bag_dir.exists() and any(self.bag_dir.iterdir()):
            if not self._overwrite:
                raise DatasetFormatError(f"{self.bag_dir}: exists and is not empty (pass --overwrite to replace a bag)")
            own = bag_owned_files(self.bag_dir)
            foreign = sorted(p.name for p in self.bag_dir.iterdir() if p not in own)
            if not (self.bag_dir / METADATA_FILE).is_file() or foreign:
                raise DatasetFormatError(f"{self.bag_dir}: not a bag (holds {', '.join(foreign[:3]) or 'no metadata.yaml'});"
                                         " refusing to overwrite")
            for path in own:
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
        self._add(topic, channel_id, msg_to_cdr(msg), t_ns, t_ns, 0)

    def _add(self, topic: str, channel_id: int, data: bytes, log_time: int, publish_time: int, sequence: int) -> None:
        self._mcap.add_message(channel_id, log_time=log_time, publish_time=publish_time, data=data, sequence=sequence)
        self._counts[topic] += 1
        self._start_ns = log_time if self._start_ns is None else min(self._start_ns, log_time)
        self._end_ns = log_time if self._end_ns is None else max(self._end_ns, log_time)

    def _register(
        self,
        topic: str,
        msg_type: str,
        *,
        schema: tuple[str, bytes] | None = None,
        message_encoding: str = MessageEncoding.CDR,
        metadata: Mapping[str, str] | None = None,
    ) -> int:
        """Add `topic`'s channel (and its type's schema); `schema` = (encoding, text) and
        `metadata` keep a copied channel's own (`bag repair`), else ours are generated."""
        spec = TOPICS.get(topic)
        if spec is not None and spec.msg_type != msg_type:
            raise TypeError(f"topic {topic} carries {spec.msg_type}, got a {msg_type}")
        schema_id = self._schemas.get(msg_type)
        if schema_id is None:
            encoding, text = schema if schema is not None else (SchemaEncoding.ROS2, message_definition(msg_type).encode())
            schema_id = self._mcap.register_schema(msg_type, encoding, text)
            self._schemas[msg_type] = schema_id
        if metadata is None:
            qos = spec.qos if spec is not None else VOLATILE_QOS
            # rosbag2's MCAP storage keeps the offered QoS and type hash per channel.
            metadata = {
                "offered_qos_profiles": yaml.dump([qos], Dumper=YamlDumper, sort_keys=False),
                "topic_type_hash": type_hash(msg_type),
            }
        channel_id = self._mcap.register_channel(topic, message_encoding, schema_id, metadata=dict(metadata))
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
                **self.custom_data,
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
    """What a read recovered and what it lost.

    `lost_*` compare against metadata.yaml when the writer closed the bag; when it did
    not (killed recorder), they are lower bounds: what was seen to be lost.
    """

    bag_dir: Path
    expected_messages: int | None = None
    expected_episodes: int | None = None
    messages_read: int = 0
    episodes_read: int = 0  # complete episodes, whatever the split filter
    aborted_episodes: int = 0  # recorded as aborted (header "outcome"), whatever the split filter
    incomplete_episodes: int = 0  # started, never reached `<eos>` (end of data, or cut by damage)
    discarded_messages: int = 0  # read but outside any complete episode
    truncated_files: list[Path] = field(default_factory=list)  # ended before the MCAP footer
    unread_bytes: int = 0  # trailing bytes that held no complete record
    corrupt_regions: list[tuple[Path, int, int]] = field(default_factory=list)  # damaged bytes [start, end) skipped
    lost_chunks: int = 0  # MCAP chunks that could not be read (damaged, or torn off by a truncation)
    unreadable_messages: int = 0  # messages known to be in lost chunks (MCAP message indexes) or on unknown channels
    finished: bool = False  # every file was read to its end (the counts are final)

    @property
    def truncated(self) -> bool:
        return bool(self.truncated_files)

    @property
    def corrupt(self) -> bool:
        return bool(self.corrupt_regions)

    @property
    def damaged(self) -> bool:
        """A file ended early or held damaged bytes (even when no episode was lost)."""
        return self.truncated or self.corrupt

    @property
    def exact(self) -> bool:
        """The losses are exact (the writer closed the bag), not lower bounds."""
        return self.expected_messages is not None

    @property
    def skipped_bytes(self) -> int:
        return sum(end - start for _, start, end in self.corrupt_regions)

    @property
    def lost_messages(self) -> int:
        """Messages not delivered in a complete episode (a lower bound when the writer died)."""
        kept = self.messages_read - self.discarded_messages
        if self.expected_messages is not None:
            return max(self.expected_messages - kept, 0)
        return self.discarded_messages + self.unreadable_messages

    @property
    def lost_episodes(self) -> int:
        if self.expected_episodes is not None:
            return max(self.expected_episodes - self.episodes_read - self.aborted_episodes, 0)
        return self.incomplete_episodes

    @property
    def complete(self) -> bool:
        """Nothing lost and nothing damaged."""
        return not (self.damaged or self.lost_episodes or self.lost_messages)

    def state(self) -> str:
        """'intact', 'truncated', 'corrupt' or 'corrupt and truncated'."""
        parts = [word for word, flag in (("corrupt", self.corrupt), ("truncated", self.truncated)) if flag]
        return " and ".join(parts) or "intact"

    def summary(self) -> str:
        """One line: state, what was recovered, what was lost."""
        details = []
        if self.corrupt:
            details.append(
                f"{len(self.corrupt_regions)} damaged region(s), {self.skipped_bytes} bytes skipped"
            )
        if self.lost_chunks:
            details.append(f"{self.lost_chunks} chunk(s) unreadable")
        if self.truncated:
            torn = f": {self.unread_bytes} unreadable trailing bytes" if self.unread_bytes else ""
            details.append(f"no MCAP footer{torn}")
        if self.incomplete_episodes:
            details.append(f"{self.incomplete_episodes} incomplete")
        if self.aborted_episodes:
            details.append(f"{self.aborted_episodes} recorded as aborted, skipped")
        of = f" of {self.expected_episodes}" if self.expected_episodes is not None else ""
        bound = "" if self.exact else " at least"
        line = (
            f"{self.bag_dir}: {self.state()}: recovered {self.episodes_read}{of} complete episodes; "
            f"lost{bound} {self.lost_episodes} episodes / {self.lost_messages} messages"
        )
        if not self.exact:
            details.append("the writer did not close the bag")
        return line + (f" ({'; '.join(details)})" if details else "")


# -- MCAP, read record by record, resynchronising after damage ---------------------------
MCAP_MAGIC = b"\x89MCAP0\r\n"
_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE = 0x01, 0x02, 0x03, 0x04, 0x05
_OP_CHUNK, _OP_MESSAGE_INDEX, _OP_CHUNK_INDEX, _OP_DATA_END = 0x06, 0x07, 0x08, 0x0F
_KNOWN_OPS = frozenset(range(0x01, 0x10))
_RECORD = struct.Struct("<BQ")  # opcode, length
_CHUNK = struct.Struct("<QQQII")  # start time, end time, uncompressed size, uncompressed crc, compression length
_MESSAGE = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_FOOTER_LEN = 9 + 20  # opcode, length, summary start, summary offset start, summary crc
_MAX_COMPRESSION_NAME = 16


class _Damage(Exception):
    """A record that fails validation (bad length, CRC, compression or layout)."""


_LOSS = object()  # yielded where data was lost: an episode across it cannot be assembled


@dataclass
class _Tail:
    """A footer + magic at the end of the file (so the file is not truncated)."""

    footer_pos: int
    data_limit: int  # chunks lie before this offset (the summary start)
    chunk_indexes: list[ChunkIndex] | None  # from the summary, when it has them
    summary_ok: bool = True  # False: the summary fails its CRC or does not parse (it is ignored)


def _lz4():
    try:
        import lz4.frame
    except ImportError:
        raise DatasetFormatError("an MCAP chunk is lz4-compressed and the lz4 package is not installed") from None
    return lz4.frame


def _keep_definition(op: int, buffer, start: int, end: int, schemas: dict, channels: dict) -> None:
    """Store a schema or channel record (body buffer[start:end]) by id; ignore other records."""
    if op == _OP_SCHEMA:
        schema = _read_record(Schema, buffer, start, end)
        schemas[schema.id] = schema
    elif op == _OP_CHANNEL:
        channel = _read_record(Channel, buffer, start, end)
        channels[channel.id] = channel


def _read_record(cls, buffer, start: int, end: int):
    """Parse one schema/channel/chunk-index body with the mcap library's reader."""
    try:
        return cls.read(ReadDataStream(io.BytesIO(buffer[start:end])))
    except (McapError, struct.error, UnicodeDecodeError, ValueError) as exc:
        raise _Damage(f"bad {cls.__name__} record ({exc.__class__.__name__})") from None


class McapScan:
    """One MCAP file read front to back, recovering every intact chunk around damage.

    Iterating `items()` gives `(channel, sequence, log_time, publish_time, data)` for each
    readable message, in file order, and the `_LOSS` marker wherever data was lost (a
    damaged or torn chunk, a message on an unknown channel). Damage is recorded in the
    report: a record that fails validation is skipped up to the next valid chunk (its
    length fits, its data decompresses to the declared size and matches its CRC). A
    file that ends inside a record with nothing valid after it is *truncated*; damaged
    bytes before the end of the data are *corrupt*. A file that is not MCAP, or not
    profile `ros2`, raises a DatasetFormatError naming it.

    `channels` / `schemas` (by id) fill in as they are read; when the footer is intact,
    the summary's copies are known from the start, so messages after a lost chunk that
    held their channel definitions are still readable. Bags written by gscan_ros fall
    back on metadata.yaml's topic list (channel ids are assigned in that order).
    """

    def __init__(self, path: Path, report: BagReadReport, info: BagInfo | None = None):
        self.path = path
        self.report = report
        self.channels: dict[int, Channel] = {}
        self.schemas: dict[int, Schema] = {}
        self.library = ""
        self.complete = False  # reached a valid footer
        self._info = info
        self._zstd = zstandard.ZstdDecompressor()

    # -- public -----------------------------------------------------------------------------
    def items(self) -> Iterator[tuple | object]:
        size = self.path.stat().st_size
        if size == 0:
            raise DatasetFormatError(f"{self.path}: not an MCAP file (empty)")
        with open(self.path, "rb") as stream, mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_READ) as data:
            yield from self._scan(data, size)
        if not self.complete:
            self.report.truncated_files.append(self.path)

    # -- the file ---------------------------------------------------------------------------
    def _scan(self, data, size: int) -> Iterator[tuple | object]:
        head = data[: min(size, len(MCAP_MAGIC))]
        if head != MCAP_MAGIC[: len(head)]:
            raise DatasetFormatError(f"{self.path}: not an MCAP file (bad magic)")
        pos = len(MCAP_MAGIC)
        if size < pos:  # cut inside the magic
            self._torn(0, size, 0)
            yield _LOSS
            return
        if size > pos and data[pos] != _OP_HEADER:
            raise DatasetFormatError(f"{self.path}: not an MCAP file (no header record)")
        if size < pos + 9 or pos + 9 + _U64.unpack_from(data, pos + 1)[0] > size:
            self._torn(pos, size, _OP_HEADER)  # the writer died before its header was out
            yield _LOSS
            return
        pos = self._header(data, pos)
        tail = self._tail(data, size)
        unverified = None  # start of the last record taken on its length alone (no CRC)
        while pos < size:
            if tail is not None and pos == tail.footer_pos:
                if not tail.summary_ok:
                    self.report.corrupt_regions.append((self.path, tail.data_limit, tail.footer_pos))
                self.complete = True
                return
            op = data[pos]
            end = pos + 9 + _U64.unpack_from(data, pos + 1)[0] if pos + 9 <= size else size + 1
            try:
                if op not in _KNOWN_OPS or op == _OP_HEADER:
                    raise _Damage(f"unknown record opcode {op:#04x}")
                if end > size:
                    raise _Damage("record runs past the end of the file")
                if op == _OP_CHUNK:
                    messages, schemas, channels = self._chunk(data, pos, end)
                    self.schemas.update(schemas)
                    self.channels.update(channels)
                    unverified = None
                    pos = end
                    for message in messages:
                        yield self._resolve(message)
                    continue
                if op == _OP_MESSAGE:
                    message = self._message(data, pos + 9, end)
                    yield self._resolve(message)
                elif op == _OP_SCHEMA:
                    schema = _read_record(Schema, data, pos + 9, end)
                    self.schemas[schema.id] = schema
                elif op == _OP_CHANNEL:
                    channel = _read_record(Channel, data, pos + 9, end)
                    self.channels[channel.id] = channel
                elif op == _OP_FOOTER:
                    raise _Damage("footer before the end of the file")
                unverified = pos
                pos = end
                continue
            except _Damage:
                start = unverified if unverified is not None else pos
                torn = end > size and op in _KNOWN_OPS and tail is None
            resumed = yield from self._recover(data, size, start, op, tail, torn)
            if resumed is None:
                return
            pos, unverified = resumed, None

    def _header(self, data, pos: int) -> int:
        end = pos + 9 + _U64.unpack_from(data, pos + 1)[0]
        try:
            stream = ReadDataStream(io.BytesIO(data[pos + 9 : end]))
            profile = stream.read_prefixed_string()
            self.library = stream.read_prefixed_string()
        except (McapError, struct.error, UnicodeDecodeError) as exc:
            raise DatasetFormatError(f"{self.path}: not an MCAP file (bad header: {exc.__class__.__name__})") from None
        if profile != Profile.ROS2:
            raise DatasetFormatError(f"{self.path}: MCAP profile {profile!r} is not 'ros2'")
        return end

    def _tail(self, data, size: int) -> _Tail | None:
        """The footer and summary, if the file ends with an intact one (else None)."""
        footer = size - len(MCAP_MAGIC) - _FOOTER_LEN
        if footer < len(MCAP_MAGIC) or data[size - len(MCAP_MAGIC) : size] != MCAP_MAGIC:
            return None
        op, length = _RECORD.unpack_from(data, footer)
        if op != _OP_FOOTER or length != 20:
            return None
        summary_start, _, crc = struct.unpack_from("<QQI", data, footer + 9)
        if not summary_start:
            return _Tail(footer, footer, None)
        if not len(MCAP_MAGIC) < summary_start <= footer:
            return _Tail(footer, footer, None, summary_ok=False)
        damaged = _Tail(footer, summary_start, None, summary_ok=False)
        if crc and zlib.crc32(data[summary_start : footer + 9 + 16]) != crc:
            return damaged
        schemas, channels, indexes = {}, {}, []
        pos = summary_start
        try:
            while pos < footer:
                op, length = _RECORD.unpack_from(data, pos)
                end = pos + 9 + length
                if end > footer:
                    return damaged
                if op == _OP_CHUNK_INDEX:
                    indexes.append(_read_record(ChunkIndex, data, pos + 9, end))
                else:
                    _keep_definition(op, data, pos + 9, end, schemas, channels)
                pos = end
        except (_Damage, struct.error):
            return damaged
        self.schemas.update(schemas)
        self.channels.update(channels)
        return _Tail(footer, summary_start, indexes or None)

    # -- records ----------------------------------------------------------------------------
    def _chunk(self, data, pos: int, end: int) -> tuple[list[tuple], dict, dict]:
        """(messages, schemas, channels) of the chunk record at `pos`; _Damage if it fails validation."""
        body = pos + 9
        if body + _CHUNK.size > end:
            raise _Damage("short chunk record")
        _, _, size, crc, name_length = _CHUNK.unpack_from(data, body)
        start = body + _CHUNK.size
        if name_length > _MAX_COMPRESSION_NAME or start + name_length + 8 > end:
            raise _Damage("bad chunk compression field")
        compression = data[start : start + name_length]
        start += name_length
        length = _U64.unpack_from(data, start)[0]
        start += 8
        if start + length > end:
            raise _Damage("chunk data runs past its record")
        payload = data[start : start + length]
        try:
            if compression == b"zstd":
                # A frame that states its size must state the chunk's (else no allocation of it).
                if zstandard.frame_content_size(payload) not in (size, -1):
                    raise _Damage("zstd frame size differs from the chunk's")
                records = self._zstd.decompress(payload, max_output_size=size)
            elif compression == b"lz4":
                records = _lz4().decompress(payload)
            elif compression == b"":
                records = payload
            else:
                raise _Damage(f"unknown chunk compression {compression[:16]!r}")
        except (zstandard.ZstdError, RuntimeError, ValueError, MemoryError) as exc:
            raise _Damage(f"chunk does not decompress ({exc.__class__.__name__})") from None
        if len(records) != size:
            raise _Damage("chunk decompresses to the wrong size")
        if crc and zlib.crc32(records) != crc:
            raise _Damage("chunk CRC mismatch")
        return self._chunk_records(records)

    @staticmethod
    def _chunk_records(records: bytes) -> tuple[list[tuple], dict, dict]:
        messages, schemas, channels = [], {}, {}
        pos, size = 0, len(records)
        unpack_record, unpack_message = _RECORD.unpack_from, _MESSAGE.unpack_from
        while pos < size:
            if pos + 9 > size:
                raise _Damage("torn record inside a chunk")
            op, length = unpack_record(records, pos)
            end = pos + 9 + length
            if end > size:
                raise _Damage("record runs past its chunk")
            if op == _OP_MESSAGE:
                if length < _MESSAGE.size:
                    raise _Damage("short message record")
                messages.append((*unpack_message(records, pos + 9), records[pos + 9 + _MESSAGE.size : end]))
            else:
                _keep_definition(op, records, pos + 9, end, schemas, channels)
            pos = end
        return messages, schemas, channels

    def _message(self, data, start: int, end: int) -> tuple:
        if end - start < _MESSAGE.size:
            raise _Damage("short message record")
        return (*_MESSAGE.unpack_from(data, start), data[start + _MESSAGE.size : end])

    def _resolve(self, message: tuple):
        """(Channel, sequence, log time, publish time, data), or _LOSS for an unknown channel."""
        channel = self.channels.get(message[0]) or self._fallback_channel(message[0])
        if channel is None:
            self.report.unreadable_messages += 1
            return _LOSS
        return (channel, *message[1:])

    def _fallback_channel(self, channel_id: int) -> Channel | None:
        """A gscan_ros writer registers one channel per metadata.yaml topic, in that order."""
        if self._info is None or not self.library.startswith("gscan_ros"):
            return None
        topics = list(self._info.topics.values())
        if not 1 <= channel_id <= len(topics):
            return None
        topic = topics[channel_id - 1]
        spec = TOPICS.get(topic.name)
        qos = spec.qos if spec is not None else VOLATILE_QOS
        try:
            schema = Schema(channel_id, message_definition(topic.msg_type).encode(), SchemaEncoding.ROS2, topic.msg_type)
        except (OSError, GscanError, ValueError):
            return None
        schema_id = next((i for i, s in self.schemas.items() if s.name == topic.msg_type), None)
        if schema_id is None:
            schema_id = max(self.schemas, default=0) + 1
            self.schemas[schema_id] = Schema(schema_id, schema.data, schema.encoding, schema.name)
        channel = Channel(
            id=channel_id,
            topic=topic.name,
            message_encoding=MessageEncoding.CDR,
            metadata={
                "offered_qos_profiles": yaml.dump([qos], Dumper=YamlDumper, sort_keys=False),
                "topic_type_hash": type_hash(topic.msg_type),
            },
            schema_id=schema_id,
        )
        self.channels[channel_id] = channel
        return channel

    # -- damage -----------------------------------------------------------------------------
    def _recover(self, data, size: int, start: int, op: int, tail: _Tail | None, torn: bool):
        """Skip the damage that starts at `start` (found in a record with opcode `op`): yields
        `_LOSS` if data was lost, returns the offset to go on from (None: the file is done)."""
        limit = tail.data_limit if tail is not None else size
        resume = self._next_chunk(data, start + 1, limit) if start < limit else None
        if resume is not None:
            lossy = self._lost(data, start, resume, tail)
            self.report.corrupt_regions.append((self.path, start, resume))
            if lossy:
                yield _LOSS
            return resume
        if tail is not None:
            # The file is whole (footer intact): the damage lies in its last chunk(s) or
            # in the summary; the chunks before it were read.
            end = limit if start < limit else max(tail.footer_pos, start)
            lossy = start < limit and self._lost(data, start, limit, tail)
            self.report.corrupt_regions.append((self.path, start, end))
            if not tail.summary_ok and start < limit < tail.footer_pos:
                self.report.corrupt_regions.append((self.path, limit, tail.footer_pos))
            if lossy:
                yield _LOSS
            self.complete = True
            return None
        if torn:
            self._torn(start, size, op)
        else:  # intact-length bytes that fail validation, and no footer after them
            self._lost(data, start, size, None)
            self.report.corrupt_regions.append((self.path, start, size))
        yield _LOSS
        return None

    def _torn(self, start: int, size: int, op: int) -> None:
        """The file ends inside the record at `start` (a truncation: the writer died, a copy was cut)."""
        self.report.unread_bytes += size - start
        if op == _OP_CHUNK:
            self.report.lost_chunks += 1

    def _next_chunk(self, data, start: int, limit: int) -> int | None:
        """Offset of the next chunk record in [start, limit) that validates, or None."""
        pos = start
        while True:
            pos = data.find(b"\x06", pos, limit)
            if pos < 0:
                return None
            if pos + 9 + _CHUNK.size <= limit:
                end = pos + 9 + _U64.unpack_from(data, pos + 1)[0]
                if end <= limit:
                    name_length = _U32.unpack_from(data, pos + 9 + _CHUNK.size - 4)[0]
                    if name_length <= _MAX_COMPRESSION_NAME:
                        try:
                            self._chunk(data, pos, end)  # read again (and kept) by the caller
                            return pos
                        except _Damage:
                            pass
            pos += 1

    def _lost(self, data, start: int, end: int, tail: _Tail | None) -> bool:
        """Count the chunks (and their indexed messages) in the skipped bytes [start, end); True if any."""
        if tail is not None and tail.chunk_indexes is not None:
            chunks = [c for c in tail.chunk_indexes
                      if c.chunk_start_offset < end and c.chunk_start_offset + c.chunk_length > start]
            self.report.lost_chunks += len(chunks)
            for chunk in chunks:
                for offset in chunk.message_index_offsets.values():
                    self.report.unreadable_messages += self._indexed(data, offset, tail.footer_pos)
            return bool(chunks)
        # No chunk index: walk the skipped records by their (unchecked) lengths.
        pos, chunks, after_chunk = start, 0, False
        while pos + 9 <= end:
            op, length = _RECORD.unpack_from(data, pos)
            record_end = pos + 9 + length
            if op not in _KNOWN_OPS or record_end > end:
                chunks = max(chunks, 1)  # unparseable: assume it held data
                break
            if op == _OP_CHUNK:
                chunks, after_chunk = chunks + 1, True
            elif op == _OP_MESSAGE_INDEX and after_chunk:
                self.report.unreadable_messages += self._indexed(data, pos, end)
            else:
                after_chunk = False
            pos = record_end
        if pos < end and chunks == 0:
            chunks = 1
        self.report.lost_chunks += chunks
        return chunks > 0

    @staticmethod
    def _indexed(data, pos: int, limit: int) -> int:
        """Entries of the message index record at `pos` (0 if there is none)."""
        if pos + 9 + 6 > limit:
            return 0
        op, length = _RECORD.unpack_from(data, pos)
        if op != _OP_MESSAGE_INDEX or pos + 9 + length > limit:
            return 0
        entries = _U32.unpack_from(data, pos + 9 + 2)[0]
        return entries // 16 if 6 + entries <= length else 0


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
    aborted: bool = False  # header "outcome": "aborted"


class BagEpisodeReader(Iterator[Episode]):
    """Streaming reader: iterate it for Episodes; `report` describes what was recovered.

    Reads each MCAP file front to back (`McapScan`), without its summary, so a bag whose
    writer was killed (no summary, torn last chunk) still yields every complete episode,
    and a damaged chunk costs only the episodes that had messages in it: reading goes on
    at the next intact chunk, and an episode cut by lost data is dropped (counted in the
    report), never assembled from the pieces around the damage. A file that is not MCAP
    raises one DatasetFormatError naming the file.
    """

    def __init__(
        self,
        bag_dir: str | os.PathLike,
        splits: Iterable[str] | None = None,
        *,
        decode_states: bool = False,
        log_losses: bool = True,
        include_aborted: bool = False,
    ):
        self.info = read_bag_info(bag_dir)
        self.splits = None if splits is None else frozenset(splits)
        self.decode_states = decode_states
        self.include_aborted = include_aborted  # also yield episodes recorded as aborted
        self.log_losses = log_losses  # log report.summary() as a warning when something was lost
        self.report = BagReadReport(
            self.info.path,
            expected_messages=self.info.message_count if self.info.closed else None,
            expected_episodes=self.info.episodes,
        )
        self._episodes = (r.episode for r in self.records())

    def __next__(self) -> Episode:
        return next(self._episodes)

    def records(self) -> Iterator[RecordedEpisode]:
        """Complete episodes in bag order (with observations when `decode_states`), and
        those recorded as aborted when `include_aborted`."""
        action_cache: dict[bytes, Action] = {}  # CDR bytes of the 7 action tokens
        decode_observation = _ObservationDecoder()
        graphs = GraphCache()
        current: _OpenEpisode | None = None
        for item in self._messages():
            if item is _LOSS:  # data lost here: the open episode cannot be completed
                self._drop(current)
                current = None
                continue
            path, topic, data = item
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
                if done.aborted:
                    self.report.aborted_episodes += 1
                    if not self.include_aborted:
                        continue
                else:
                    self.report.episodes_read += 1
                if done.selected:
                    yield self._finish(path, done, graphs)
            elif topic == COMMAND_GRAPH.name:
                current.graph_json = cdr_to_msg(data, String).data
        self._drop(current)
        self.report.finished = True
        if self.log_losses and not self.report.complete:
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
        outcome = header.get("outcome", OUTCOME_COMPLETE)
        if outcome not in (OUTCOME_COMPLETE, OUTCOME_ABORTED):
            raise DatasetFormatError(f"{path}: episode {header.get('episode_id')}: unknown outcome {outcome!r}")
        selected = self.splits is None or header.get("split") in self.splits
        return _OpenEpisode(header=header, selected=selected, aborted=outcome == OUTCOME_ABORTED)

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
        # An aborted episode may lack the state its last action led to (the reset came first).
        if done.observation_count != len(done.actions) + 1 and not (
            done.aborted and done.observation_count == len(done.actions)
        ):
            raise DatasetFormatError(
                f"{where}: {done.observation_count} observations for {len(done.actions) + 1} actions (with <eos>)"
            )
        episode = episode_from_header(done.header, done.actions, str(path))
        graphs.attach(episode, done.graph_json, where)
        states = np.stack(done.observations) if self.decode_states else None
        return RecordedEpisode(episode, done.header, states, done.graph_json)

    # -- MCAP ------------------------------------------------------------------------------
    def _messages(self) -> Iterator[tuple[Path, str, bytes] | object]:
        """(path, topic, CDR data) per readable message, and `_LOSS` where data was lost."""
        for path in self.info.mcap_paths:
            for item in McapScan(path, self.report, self.info).items():
                yield item if item is _LOSS else (path, item[0].topic, item[4])


def iter_bag_episodes(
    bag_dir: str | os.PathLike, splits: Iterable[str] | None = None, *, log_losses: bool = True
) -> BagEpisodeReader:
    """Stream the complete episodes of a bag (optionally only `splits`), in bag order.

    The returned iterator's `report` (a BagReadReport) says, once exhausted, how many
    episodes/messages were recovered and lost; losses are also logged as a warning
    (unless `log_losses=False`: the caller reports them itself).
    """
    return BagEpisodeReader(bag_dir, splits, log_losses=log_losses)


# ---------------------------------------------------------------------------------------
# Repair
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RepairResult:
    """What `repair_bag` kept: the source's read report and the new bag's metadata."""

    source: BagReadReport
    info: BagInfo
    episodes: int  # complete episodes written
    messages: int  # messages written
    dropped_messages: int  # intact messages left out: pieces of episodes that damage cut

    def summary(self) -> str:
        lost = "nothing lost" if self.source.complete else self.source.summary()
        return (
            f"wrote {self.info.path}: {self.episodes} complete episodes, {self.messages} messages "
            f"({self.dropped_messages} intact messages of cut episodes left out); source: {lost}"
        )


def repair_bag(bag_dir: str | os.PathLike, out_dir: str | os.PathLike, *, overwrite: bool = False) -> RepairResult:
    """Rewrite a damaged or unfinished bag as a complete one (MCAP summary, indexes, footer).

    Every message the recovering reader gets out of `bag_dir` is copied to `out_dir` with
    its channel, schema, sequence and times. In a gscan_ros episode bag, messages on the
    episode topics are copied only for complete episodes: the pieces of an episode that
    damage cut are left out (and counted), since two pieces joined across a lost region
    would read back as one wrong episode. `out_dir` must not exist, or, with `overwrite`,
    be a previous bag; it is written beside itself and renamed into place at the end.
    """
    src, out = Path(bag_dir), Path(out_dir)
    info = read_bag_info(src)
    real_src, real_out = src.resolve(), out.resolve()
    if real_out == real_src or real_src in real_out.parents or real_out in real_src.parents:
        raise DatasetFormatError(f"{out}: overlaps the bag being repaired ({src}); write the repaired bag elsewhere")
    if out.exists() or out.is_symlink():
        if not overwrite:
            raise DatasetFormatError(f"{out}: exists (pass --overwrite to replace a previous bag there)")
        if out.is_symlink() or not out.is_dir() or (any(out.iterdir()) and not (out / METADATA_FILE).is_file()):
            raise DatasetFormatError(f"{out}: exists and is not a bag (refusing to overwrite)")
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.repair-", dir=out.parent))
    try:
        copier = _RepairCopier(info, BagWriter(staging / out.name))
        copier.copy()
        if out.exists():
            shutil.rmtree(out)
        os.replace(staging / out.name, out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return RepairResult(copier.report, read_bag_info(out), copier.episodes, copier.messages, copier.dropped)


class _RepairCopier:
    """Copies a bag's readable messages into a BagWriter, an episode at a time."""

    def __init__(self, info: BagInfo, writer: BagWriter):
        self.info = info
        self.writer = writer
        self.report = BagReadReport(
            info.path,
            expected_messages=info.message_count if info.closed else None,
            expected_episodes=info.episodes,
        )
        # Pieces of episodes matter only in episode bags (any other bag: copy everything).
        self.episode_bag = info.custom.get("gscan_ros.format", EPISODE_FORMAT) == EPISODE_FORMAT
        self.episodes = self.messages = self.dropped = 0
        self._pending: list[tuple] | None = None  # the open episode's (channel id, topic, message)
        self._header: dict | None = None
        self._eos: dict[bytes, bool] = {}
        self._channels: dict[tuple[Path, int], int] = {}  # (file, source channel id) -> our id

    def copy(self) -> None:
        writer = self.writer
        writer.custom_data = {k: v for k, v in self.info.custom.items() if not k.startswith("gscan_ros.")}
        writer.open()
        for path in self.info.mcap_paths:
            scan = McapScan(path, self.report, self.info)
            for item in scan.items():
                if item is _LOSS:
                    self._drop()
                    continue
                channel_id = self._channel(scan, path, item[0])
                if channel_id is None:  # a channel whose type is unknown: the message is lost
                    self.report.unreadable_messages += 1
                    self.dropped += 1
                    self._drop()
                    continue
                self.report.messages_read += 1
                self._take(channel_id, item)
        self._drop()
        self.report.finished = True
        writer.custom_data["gscan_ros.repaired_from"] = str(self.info.path)
        writer.custom_data["gscan_ros.repair"] = self.report.summary()
        writer.close()

    def _take(self, channel_id: int, item: tuple) -> None:
        topic = item[0].topic
        entry = (channel_id, topic, item)
        if not self.episode_bag or topic not in EPISODE_TOPICS:
            if self._pending is not None:
                self._pending.append(entry)
            else:
                self._write(*entry)
            return
        if topic == COMMAND.name:
            self._drop()
            self._pending = [entry]
            try:
                header = json.loads(cdr_to_msg(item[4], String).data)
            except Exception:  # noqa: BLE001 - a plain-text (or undecodable) command: no header
                header = None
            self._header = header if isinstance(header, dict) and "situation" in header else None
            return
        if self._pending is None:  # the tail of an episode whose start was lost
            self.dropped += 1
            self.report.discarded_messages += 1
            return
        self._pending.append(entry)
        if topic == ACTION.name and self._is_eos(item[4]):
            for pending in self._pending:
                self._write(*pending)
            self._pending = None
            self.episodes += 1
            header = self._header or {}
            if header.get("outcome") == OUTCOME_ABORTED:
                self.report.aborted_episodes += 1
            else:
                self.report.episodes_read += 1
            if header.get("split") is not None:
                self.writer._splits[header["split"]] += 1

    def _is_eos(self, data: bytes) -> bool:
        eos = self._eos.get(data)
        if eos is None:
            try:
                eos = cdr_to_msg(data, String).data == Action.EOS.token
            except Exception:  # noqa: BLE001 - an undecodable action ends no episode
                eos = False
            self._eos[bytes(data)] = eos
        return eos

    def _drop(self) -> None:
        """The open episode was cut: keep its other topics' messages, leave out its own."""
        if self._pending is None:
            return
        for entry in self._pending:
            if entry[1] in EPISODE_TOPICS:
                self.dropped += 1
                self.report.discarded_messages += 1
            else:
                self._write(*entry)
        self._pending = None
        self.report.incomplete_episodes += 1

    def _channel(self, scan: "McapScan", path: Path, channel: Channel) -> int | None:
        """Our channel id for a source channel (registered on first use), None if its type is unknown."""
        key = (path, channel.id)
        channel_id = self._channels.get(key)
        if channel_id is None:
            channel_id = self.writer._channels.get(channel.topic)
        if channel_id is None:
            schema = scan.schemas.get(channel.schema_id)
            if schema is not None:
                msg_type, encoding, text = schema.name, schema.encoding, schema.data
            else:  # its schema record was lost: the type from metadata.yaml or our topic table
                topic = self.info.topics.get(channel.topic) or TOPICS.get(channel.topic)
                if topic is None:
                    return None
                msg_type = topic.msg_type
                try:
                    encoding, text = SchemaEncoding.ROS2, message_definition(msg_type).encode()
                except (OSError, GscanError, ValueError):
                    return None
            try:
                channel_id = self.writer._register(
                    channel.topic,
                    msg_type,
                    schema=(encoding, text),
                    message_encoding=channel.message_encoding,
                    metadata=channel.metadata,
                )
            except TypeError as exc:
                raise DatasetFormatError(f"{path}: {exc}") from None
        self._channels[key] = channel_id
        return channel_id

    def _write(self, channel_id: int, topic: str, item: tuple) -> None:
        _, sequence, log_time, publish_time, data = item
        self.writer._add(topic, channel_id, data, log_time, publish_time, sequence)
        self.messages += 1
