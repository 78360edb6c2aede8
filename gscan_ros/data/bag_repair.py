"""Rewriting a damaged or unfinished bag as a complete one (`repair_bag`, `gscan-ros bag repair`).

Everything the recovering scanner reads is copied with its channel, schema, sequence
and times, except what would make the new bag read differently from the old one
(docs/bags.md "Repair"): in format 2, the bad messages (`StackDecoder`) and the
`/episode_status` reports of every episode the reader could not assemble (cut by lost
data, started where the world's state was unknown, holding a bad message, ...), so
that what is left of them is the world's history, never an episode; in format 1, the
pieces of episodes that damage cut. The source is read once by the reader first, so
the repair reports exactly the losses that `verify` does.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Channel
from mcap.well_known import SchemaEncoding

from gscan_ros import episode_status as es
from gscan_ros.data.bag_format import LEGACY_EPISODE_TOPICS, LIVE_SPLIT, GraphCache
from gscan_ros.data.bag_metadata import (
    EPISODE_FORMAT,
    LEGACY_FORMAT_VERSION,
    BagInfo,
    read_bag_info,
    remove_bag_files,
    replaceable_bag,
)
from gscan_ros.data.bag_reader import BagEpisodeReader, live_decoder
from gscan_ros.data.bag_report import BagReadReport
from gscan_ros.data.bag_scan import LOSS, McapScan
from gscan_ros.data.bag_schema import ACTION, COMMAND, TOPICS
from gscan_ros.data.bag_writer import BagWriter
from gscan_ros.errors import DatasetFormatError, GscanError
from gscan_ros.outputs import scratch
from gscan_ros.world.types import Action
from msg_adapters import cdr_to_text, message_definition


@dataclass(frozen=True)
class RepairResult:
    """What `repair_bag` kept: the source's read report (the reader's, as `verify` prints
    it) and the new bag's metadata."""

    source: BagReadReport
    info: BagInfo
    episodes: int  # complete episodes written
    messages: int  # messages written
    dropped_messages: int  # readable messages left out: bad ones, reports of episodes that could not be read
    outcomes: dict[str, int] = field(default_factory=dict)  # episodes written that ended otherwise (cut, ...)

    def kept(self) -> str:
        """'9 complete episodes (and 6 cut, 3 preempted: no demonstrations)'."""
        others = ", ".join(f"{n} {outcome}" for outcome, n in sorted(self.outcomes.items()))
        return f"{self.episodes} complete episodes" + (f" (and {others}: no demonstrations)" if others else "")

    def summary(self) -> str:
        lost = "nothing lost" if self.source.complete else self.source.summary()
        return (
            f"wrote {self.info.path}: {self.kept()}, {self.messages} messages ({self.dropped_messages} "
            f"readable messages left out); source: {lost}"
        )


def repair_bag(bag_dir: str | os.PathLike, out_dir: str | os.PathLike, *, overwrite: bool = False) -> RepairResult:
    """Rewrite a damaged or unfinished bag as a complete one (MCAP summary, indexes, footer).

    The reader goes through `bag_dir` first (its report is the result's `source`); then
    every message the recovering scanner gets out of it is copied to `out_dir` with its
    channel, schema, sequence and times, but for what the reader refused (module
    docstring), so the new bag reads back as exactly the episodes the old one gave, with
    nothing lost. `out_dir` must not exist, be an empty folder or, with `overwrite`, hold
    nothing but a bag (`replaceable_bag`); it is written beside itself and renamed into
    place at the end.
    """
    src, out = Path(bag_dir), Path(out_dir)
    info = read_bag_info(src)
    real_src, real_out = src.resolve(), out.resolve()
    if real_out == real_src or real_src in real_out.parents or real_out in real_src.parents:
        raise DatasetFormatError(f"{out}: overlaps the bag being repaired ({src}); write the repaired bag elsewhere")
    replaceable_bag(out, overwrite)  # refused before any work
    reader = BagEpisodeReader(src, log_losses=False, include_incomplete=True)
    for _ in reader.records():
        pass
    if not reader.report.messages_read:  # an empty bag would only hide the loss
        raise DatasetFormatError(f"{src}: nothing to recover, no message could be read ({reader.report.summary()}); "
                                 f"no bag written")
    out.parent.mkdir(parents=True, exist_ok=True)
    with scratch(out.parent, out.name) as staging:  # a killed repair's is removed by the next writer of `out`
        copier = _RepairCopier(info, reader, BagWriter(staging / out.name))
        try:
            copier.copy()
        except BaseException:
            copier.writer.abandon()  # closes the file; the staging folder goes with it
            raise
        remove_bag_files(replaceable_bag(out, overwrite))
        os.replace(staging / out.name, out)
    return RepairResult(reader.report, read_bag_info(out), copier.outcomes.pop(es.COMPLETE, 0), copier.messages,
                        copier.dropped, copier.outcomes)


class _RepairCopier:
    """Copies a bag's readable messages into a BagWriter, but for what its reader refused."""

    def __init__(self, info: BagInfo, reader: BagEpisodeReader, writer: BagWriter):
        self.info = info
        self.writer = writer
        self.stacks = reader.stacks  # format 2: the stack topics, as the reader found them
        self.dropped_keys = reader.dropped_keys  # format 2: the episodes it could not assemble
        self.dropped_commands = reader.dropped_commands  # format 1: the episodes it dropped at their <eos>
        self._commands = 0  # format 1: `/command` messages seen
        self.decode = live_decoder(GraphCache(), reader.observation)
        self.source_summary = reader.report.summary()
        # Pieces of episodes matter only in episode bags (any other bag: copy everything).
        self.episode_bag = info.custom.get("gscan_ros.format", EPISODE_FORMAT) == EPISODE_FORMAT
        self.legacy = info.format_version == LEGACY_FORMAT_VERSION
        self.messages = self.dropped = 0
        self.outcomes: dict[str, int] = {}  # episodes written, by outcome
        self._started: set[tuple[str, str, int]] = set()  # format 2: the episodes whose ACTIVE report was written
        self._splits: dict[tuple[str, str], str] = {}  # format 2: (namespace, report id) -> split, from `/episode`
        self._pending: list[tuple] | None = None  # format 1: the open episode's (channel id, topic, message)
        self._index = -1  # format 1: the open episode's place among the `/command` messages
        self._header: dict | None = None
        self._eos: dict[bytes, bool] = {}
        self._channels: dict[tuple[Path, int], int] = {}  # (file, source channel id) -> our id

    def copy(self) -> None:
        writer = self.writer
        writer.custom_data = {k: v for k, v in self.info.custom.items() if not k.startswith("gscan_ros.")}
        writer.format_version = self.info.format_version  # the messages are copied, not converted
        writer.open()
        scratch_report = BagReadReport(self.info.path)  # the reader's report says what was lost
        for path in self.info.mcap_paths:
            scan = McapScan(path, scratch_report, self.info)
            for item in scan.items():
                if item is LOSS:
                    self._drop()
                    continue
                channel_id = self._channel(scan, path, item[0])
                if channel_id is None:  # a channel whose type is unknown: the message is lost
                    self.dropped += 1
                    self._drop()
                elif self.episode_bag and not self.legacy:
                    self._take_live(scan, channel_id, item)
                else:
                    self._take(channel_id, item)
        self._drop()
        writer.custom_data["gscan_ros.repaired_from"] = str(self.info.path)
        writer.custom_data["gscan_ros.repair"] = self.source_summary
        writer.close()

    def _take_live(self, scan: McapScan, channel_id: int, item: tuple) -> None:
        """Format 2: copy, leaving out bad messages and the reports of the episodes the reader dropped."""
        topic = item[0].topic
        found = self.stacks.classify(topic, scan.msg_type(item[0]))
        if found is None or not self.stacks.is_stack(found[0]):
            self._write(channel_id, item)
            return
        namespace, name = found
        try:
            value = self.decode(name, item[4])
        except GscanError:
            self.dropped += 1
            return
        if name == "episode":
            self._splits[(namespace, value["id"])] = value.get("split", LIVE_SPLIT)
        elif name == "episode_status":
            key = (namespace, value.episode_id, value.start_ns)
            if key in self.dropped_keys:
                self.dropped += 1
                return
            if value.outcome == es.ACTIVE:
                self._started.add(key)
            elif key in self._started:
                self._started.discard(key)
                self._count(value.outcome, self._splits.pop((namespace, value.episode_id), LIVE_SPLIT))
            elif value.outcome == es.REJECTED:  # a command refused before any episode began
                self._count(value.outcome, None)
        self._write(channel_id, item)

    def _take(self, channel_id: int, item: tuple) -> None:
        """Format 1 (and bags that are not episode bags): an episode's messages are held from
        its `/command` header to its `<eos>`, and left out when lost data cuts it."""
        topic = item[0].topic
        entry = (channel_id, topic, item)
        if not self.episode_bag or topic not in LEGACY_EPISODE_TOPICS:
            if self._pending is not None:
                self._pending.append(entry)
            else:
                self._write(entry[0], entry[2])
            return
        if topic == COMMAND.name:
            self._drop()
            self._pending = [entry]
            self._index, self._commands = self._commands, self._commands + 1
            try:
                header = json.loads(cdr_to_text(item[4]))
            except Exception:  # noqa: BLE001 - a plain-text (or undecodable) command: no header
                header = None
            self._header = header if isinstance(header, dict) and "situation" in header else None
            return
        if self._pending is None:  # the tail of an episode whose start was lost
            self.dropped += 1
            return
        self._pending.append(entry)
        if topic == ACTION.name and self._is_eos(item[4]):
            if self._index in self.dropped_commands:  # an episode the reader drops (a bad message, no header)
                self._drop()
                return
            for pending in self._pending:
                self._write(pending[0], pending[2])
            self._pending = None
            header = self._header or {}
            self._count(es.outcome_of(header.get("outcome", es.COMPLETE)), header.get("split"))

    def _count(self, outcome: str, split: str | None) -> None:
        self.outcomes[outcome] = self.outcomes.get(outcome, 0) + 1
        self.writer.count_episode(split if outcome == es.COMPLETE else None)

    def _is_eos(self, data: bytes) -> bool:
        eos = self._eos.get(data)
        if eos is None:
            try:
                eos = cdr_to_text(data) == Action.EOS.token
            except Exception:  # noqa: BLE001 - an undecodable action ends no episode
                eos = False
            self._eos[bytes(data)] = eos
        return eos

    def _drop(self) -> None:
        """Format 1: lost data cut the open episode, or the reader dropped it: keep its other
        topics' messages, leave out its own."""
        if self._pending is None:
            return
        for entry in self._pending:
            if entry[1] in LEGACY_EPISODE_TOPICS:
                self.dropped += 1
            else:
                self._write(entry[0], entry[2])
        self._pending = None

    def _channel(self, scan: "McapScan", path: Path, channel: Channel) -> int | None:
        """Our channel id for a source channel (one per topic and type, registered on first
        use), None if its type is unknown."""
        key = (path, channel.id)
        channel_id = self._channels.get(key)
        if channel_id is not None:
            return channel_id
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
            except GscanError:  # not a ROS 2 Jazzy type
                return None
        channel_id = self._channels[key] = self.writer.channel(
            channel.topic, msg_type, schema=(encoding, text), message_encoding=channel.message_encoding,
            metadata=channel.metadata)
        return channel_id

    def _write(self, channel_id: int, item: tuple) -> None:
        _, sequence, log_time, publish_time, data = item
        self.writer.add_record(channel_id, data, log_time, publish_time, sequence)
        self.messages += 1
