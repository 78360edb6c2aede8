"""Rewriting a damaged or unfinished bag as a complete one (`repair_bag`, `gscan-ros bag repair`).

Everything the recovering scanner reads is copied with its channel, schema, sequence
and times; in an episode bag, the pieces of episodes that damage cut are left out
(docs/bags.md "Repair"): in format 2, the stack's messages from an episode's ACTIVE
report to its end (and those after lost data up to the end of the episode it cut), and
every episode that starts after lost data before a new `/situation` says where the
world is, or whose `/episode` record the lost data may have held.
"""
from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from mcap.records import Channel
from mcap.well_known import SchemaEncoding

from gscan_ros import episode_status as es
from gscan_ros.data.bag_format import LEGACY_EPISODE_TOPICS, LIVE_SPLIT
from gscan_ros.data.bag_metadata import EPISODE_FORMAT, LEGACY_FORMAT_VERSION, METADATA_FILE, BagInfo, read_bag_info
from gscan_ros.data.bag_report import BagReadReport
from gscan_ros.data.bag_scan import LOSS, McapScan
from gscan_ros.data.bag_schema import ACTION, COMMAND, TOPICS
from gscan_ros.data.bag_writer import BagWriter
from gscan_ros.data.episode_assembly import carries_records, stack_topic
from gscan_ros.errors import DatasetFormatError, GscanError
from gscan_ros.outputs import scratch
from gscan_ros.world.types import Action
from msg_adapters import cdr_to_episode_status, cdr_to_text, message_definition


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
    with scratch(out.parent, out.name) as staging:  # a killed repair's is removed by the next writer of `out`
        copier = _RepairCopier(info, BagWriter(staging / out.name))
        copier.copy()
        if out.exists():
            shutil.rmtree(out)
        os.replace(staging / out.name, out)
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
        self.legacy = info.format_version == LEGACY_FORMAT_VERSION
        self.episodes = self.messages = self.dropped = 0
        self._pending: list[tuple] | None = None  # the open episode's (channel id, topic, message)
        self._episode_id: str | None = None  # format 2: the open episode's report id
        self._state_known = True  # format 2: no data lost since the newest `/situation`
        self._rebuildable = True  # format 2: the open episode started where the world was known
        self._after_loss: list[tuple] | None = None  # format 2: stack messages since lost data, until a report
        self._has_records = carries_records(info.topics)  # format 2: `/episode` records are written
        self._record_lost = False  # format 2: data was lost since the last ACTIVE report
        self._open_record_lost = False  # format 2: the open episode started after such a loss
        self._cut: str | None = None  # format 2: the id of the episode lost data cut last (counted then)
        self._splits: dict[str, str | None] = {}  # format 2: report id -> split, from `/episode` records
        self._stack: dict[str, str | None] = {}  # bag topic -> stack topic (format 2)
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
                if item is LOSS:
                    self._lose()
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
        if self._after_loss is not None:
            self._leave_out(self._after_loss)
        self.report.finished = True
        writer.custom_data["gscan_ros.repaired_from"] = str(self.info.path)
        writer.custom_data["gscan_ros.repair"] = self.report.summary()
        writer.close()

    def _take(self, channel_id: int, item: tuple) -> None:
        if self.episode_bag and not self.legacy:
            self._take_live((channel_id, item[0].topic, item))
            return
        topic = item[0].topic
        entry = (channel_id, topic, item)
        if not self.episode_bag or topic not in LEGACY_EPISODE_TOPICS:
            if self._pending is not None:
                self._pending.append(entry)
            else:
                self._write(*entry)
            return
        if topic == COMMAND.name:
            self._drop()
            self._pending = [entry]
            try:
                header = json.loads(cdr_to_text(item[4]))
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
            outcome = es.outcome_of(header.get("outcome", es.COMPLETE))
            self._count(outcome, header.get("split"))

    def _lose(self) -> None:
        """Data was lost here: the open episode is cut; in format 2, the stack's messages that
        follow belong to it (its tail, left out at its end) or to the next episode (its
        prologue, kept at its ACTIVE report)."""
        if self._pending is not None:
            self._cut = self._episode_id
        self._drop()
        if self.episode_bag and not self.legacy:
            self._state_known = False
            self._record_lost = self._has_records
            if self._after_loss is None:
                self._after_loss = []

    def _take_live(self, entry: tuple) -> None:
        """Format 2: hold an episode's stack messages from its ACTIVE report to its end, and
        those after lost data until a report says whose they are."""
        topic = entry[1]
        name = self._stack.get(topic, "?")
        if name == "?":
            name = self._stack[topic] = stack_topic(topic, self._stack)
        if name == "situation":
            self._state_known = True
        elif name == "episode":  # what the bag adds to an episode: its split counts in the metadata
            self._has_records = True
            try:
                record = json.loads(cdr_to_text(entry[2][4]))
                self._splits[str(record["id"])] = record.get("split")
            except Exception:  # noqa: BLE001 - an unreadable record: the reader will say so
                pass
        report = None
        if name == "episode_status":
            try:
                report = cdr_to_episode_status(entry[2][4])
            except GscanError:
                report = None
        if self._after_loss is not None and name is not None:
            if report is None or report.outcome == es.REJECTED:
                self._after_loss.append(entry)
                return
            held, self._after_loss = self._after_loss, None
            if report.outcome != es.ACTIVE:  # the end of an episode the loss cut: its tail goes too
                self._leave_out([*held, entry])
                if report.episode_id != self._cut:  # not one counted when the loss cut it: its start was lost
                    self.report.incomplete_episodes += 1
                return
            for pending in held:  # the prologue of the episode this report starts
                self._write(*pending)
        if report is not None and report.outcome == es.ACTIVE:
            self._drop()
            # After lost data, where the world was is unknown until a new `/situation`, and the
            # episode's `/episode` record may have been lost: such an episode cannot be
            # rebuilt, so it is held and left out at its end.
            self._pending, self._episode_id, self._rebuildable = [entry], report.episode_id, self._state_known
            self._open_record_lost, self._record_lost = self._record_lost, False
            return
        if self._pending is None or name is None:
            self._write(*entry)
            return
        self._pending.append(entry)
        if report is not None and report.episode_id == self._episode_id:
            if not self._rebuildable or (self._open_record_lost and report.episode_id not in self._splits):
                self._drop()
                return
            for pending in self._pending:
                self._write(*pending)
            self._pending = None
            self._count(report.outcome, self._splits.pop(report.episode_id, LIVE_SPLIT))

    def _count(self, outcome: str, split: str | None) -> None:
        self.episodes += 1
        if outcome == es.COMPLETE:
            self.report.episodes_read += 1
        else:
            self.report.count_outcome(outcome)
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
        """The open episode was cut: keep its other topics' messages, leave out its own."""
        if self._pending is None:
            return
        self._leave_out(self._pending)
        self._pending = None
        self.report.incomplete_episodes += 1

    def _leave_out(self, entries: list[tuple]) -> None:
        """Write the other topics' messages of `entries`, leave out (and count) the episode topics'."""
        for entry in entries:
            if entry[1] in LEGACY_EPISODE_TOPICS if self.legacy else self._stack.get(entry[1]) is not None:
                self.dropped += 1
                self.report.discarded_messages += 1
            else:
                self._write(*entry)

    def _channel(self, scan: "McapScan", path: Path, channel: Channel) -> int | None:
        """Our channel id for a source channel (registered on first use), None if its type is unknown."""
        key = (path, channel.id)
        channel_id = self._channels.get(key)
        if channel_id is None:
            channel_id = self.writer.channel_id(channel.topic)
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
                except GscanError:  # not a ROS 2 Jazzy type
                    return None
            try:
                channel_id = self.writer.register_channel(
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
        self.writer.add_record(topic, channel_id, data, log_time, publish_time, sequence)
        self.messages += 1
