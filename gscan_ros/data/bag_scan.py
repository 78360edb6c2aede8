"""One MCAP file read front to back, record by record, resynchronising after damage (`McapScan`).

The reader, `bag repair` and the decode cache get every intact message through here;
a torn or damaged chunk costs only itself (docs/bags.md "Damaged bags"). The summary
section is never needed, so a bag whose writer was killed reads up to its last chunk.
"""
from __future__ import annotations

import io
import mmap
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import yaml
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.records import Channel, ChunkIndex, Schema
from mcap.well_known import MessageEncoding, Profile, SchemaEncoding

from gscan_ros.data.bag_metadata import BagInfo
from gscan_ros.data.bag_report import BagReadReport
from gscan_ros.data.bag_schema import YamlDumper, offered_qos
from gscan_ros.errors import DatasetFormatError, GscanError
from msg_adapters import message_definition, type_hash

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


LOSS = object()  # yielded where data was lost: an episode across it cannot be assembled


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
    readable message, in file order, and the `LOSS` marker wherever data was lost (a
    damaged or torn chunk, a message on an unknown channel). Damage is recorded in the
    report: a record that fails validation is skipped up to the next valid chunk (its
    length fits, its data decompresses to the declared size and matches its CRC). A
    file that ends inside a record with nothing valid after it is *truncated*; damaged
    bytes before the end of the data are *corrupt*; an empty file (0 bytes) is truncated
    at its start, as one cut inside the magic; a file that is absent (a storage file of the
    bag that is missing) is one `LOSS`, recorded in `report.missing_files`. A file that is
    not MCAP, or not profile `ros2`, raises a DatasetFormatError naming it.

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
        if not self.path.is_file():  # a storage file of the bag that is absent: all it held is lost
            self.report.missing_files.append(self.path)
            yield LOSS
            return
        size = self.path.stat().st_size
        if size == 0:  # created, then nothing written (a recorder killed as it split): torn at its start
            yield LOSS
        else:
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
            yield LOSS
            return
        if size > pos and data[pos] != _OP_HEADER:
            raise DatasetFormatError(f"{self.path}: not an MCAP file (no header record)")
        if size < pos + 9 or pos + 9 + _U64.unpack_from(data, pos + 1)[0] > size:
            self._torn(pos, size, _OP_HEADER)  # the writer died before its header was out
            yield LOSS
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
        """(Channel, sequence, log time, publish time, data), or LOSS for an unknown channel."""
        channel = self.channels.get(message[0]) or self._fallback_channel(message[0])
        if channel is None:
            self.report.unreadable_messages += 1
            return LOSS
        return (channel, *message[1:])

    def msg_type(self, channel: Channel) -> str | None:
        """"pkg/msg/Type" of a channel's messages: its schema's name, else metadata.yaml's type of its topic."""
        schema = self.schemas.get(channel.schema_id)
        if schema is not None:
            return schema.name
        topic = self._info.topics.get(channel.topic) if self._info is not None else None
        return topic.msg_type if topic is not None else None

    def _fallback_channel(self, channel_id: int) -> Channel | None:
        """A gscan_ros writer registers one channel per metadata.yaml topic entry, in that order."""
        if self._info is None or not self.library.startswith("gscan_ros"):
            return None
        topics = self._info.entries
        if not 1 <= channel_id <= len(topics):
            return None
        topic = topics[channel_id - 1]
        try:
            definition = message_definition(topic.msg_type).encode()
            schema = Schema(channel_id, definition, SchemaEncoding.ROS2, topic.msg_type)
        except GscanError:  # not a ROS 2 Jazzy type
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
                "offered_qos_profiles": yaml.dump([offered_qos(topic.name)], Dumper=YamlDumper, sort_keys=False),
                "topic_type_hash": type_hash(topic.msg_type),
            },
            schema_id=schema_id,
        )
        self.channels[channel_id] = channel
        return channel

    # -- damage -----------------------------------------------------------------------------
    def _recover(self, data, size: int, start: int, op: int, tail: _Tail | None, torn: bool):
        """Skip the damage that starts at `start` (found in a record with opcode `op`): yields
        `LOSS` if data was lost, returns the offset to go on from (None: the file is done)."""
        limit = tail.data_limit if tail is not None else size
        resume = self._next_chunk(data, start + 1, limit) if start < limit else None
        if resume is not None:
            lossy = self._lost(data, start, resume, tail)
            self.report.corrupt_regions.append((self.path, start, resume))
            if lossy:
                yield LOSS
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
                yield LOSS
            self.complete = True
            return None
        if torn:
            self._torn(start, size, op)
        else:  # intact-length bytes that fail validation, and no footer after them
            self._lost(data, start, size, None)
            self.report.corrupt_regions.append((self.path, start, size))
        yield LOSS
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
