"""Plain text <-> std_msgs/String: commands, status lines, and the JSON that actions, command
graphs, situations and a bag's episode records are sent as.

Decoding reads the serialized string itself instead of through rosbags, whose strict
UTF-8 decoding refuses what a client may send: `cdr_to_string_bytes` keeps the bytes as
sent (parser_node judges them), `cdr_to_text` replaces what is not UTF-8, so a recording
of a bad command still reads.
"""
from __future__ import annotations

import struct

from msg_adapters.cdr import PLAIN_ENCAPSULATIONS, message_class, msg_to_cdr
from msg_adapters.errors import MessageFormatError

String = message_class("std_msgs/msg/String")


def text_to_cdr(text: str) -> bytes:
    return msg_to_cdr(String(data=text))


def cdr_to_text(data: bytes) -> str:
    """The text of a serialized std_msgs/String, invalid UTF-8 replaced by U+FFFD (decoded in
    place: a huge message is not copied first)."""
    start, end = _string_span(data)
    return str(memoryview(data)[start:end], "utf-8", "replace")


def cdr_to_string_bytes(data: bytes) -> bytes:
    """The undecoded bytes of a serialized std_msgs/String (without its NUL terminator)."""
    start, end = _string_span(data)
    return bytes(data[start:end])


def _string_span(data: bytes) -> tuple[int, int]:
    """Where the characters of a serialized std_msgs/String are; MessageFormatError when it is none."""
    if len(data) < 8:
        raise MessageFormatError(f"serialized std_msgs/String needs at least 8 bytes, got {len(data)}")
    endian = PLAIN_ENCAPSULATIONS.get(int.from_bytes(data[:2], "big"))
    if endian is None:
        raise MessageFormatError(f"unsupported CDR encapsulation {bytes(data[:2]).hex()} for std_msgs/String")
    (length,) = struct.unpack_from(f"{endian}I", data, 4)  # string length, terminator included
    if length < 1 or 8 + length > len(data) or data[7 + length] != 0:
        raise MessageFormatError(
            f"serialized std_msgs/String has a bad length field ({length} for {len(data) - 8} bytes)"
        )
    return 8, 7 + length
