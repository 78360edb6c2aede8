"""Rewriting a damaged or unfinished bag as a complete one (`repair_bag`, `gscan-ros bag repair`).

Everything the recovering scanner reads is copied with its channel, schema, sequence
and times; in an episode bag, the pieces of episodes that damage cut are left out
(docs/bags.md "Repair").
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

from mcap.records import Channel
from mcap.well_known import SchemaEncoding

from gscan_ros.data.bag_format import EPISODE_TOPICS, OUTCOME_ABORTED
from gscan_ros.data.bag_metadata import EPISODE_FORMAT, METADATA_FILE, BagInfo, read_bag_info
from gscan_ros.data.bag_report import BagReadReport
from gscan_ros.data.bag_scan import LOSS, McapScan
from gscan_ros.data.bag_schema import ACTION, COMMAND, TOPICS, message_definition
from gscan_ros.data.bag_writer import BagWriter
from gscan_ros.errors import DatasetFormatError, GscanError
from gscan_ros.world.types import Action
from msg_adapters import cdr_to_text


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
                if item is LOSS:
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
            if header.get("outcome") == OUTCOME_ABORTED:
                self.report.aborted_episodes += 1
            else:
                self.report.episodes_read += 1
            self.writer.count_episode(header.get("split"))

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
                except (OSError, GscanError, ValueError):
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
