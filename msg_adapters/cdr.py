"""CDR bytes <-> ROS messages, the encoding of rosbag2 MCAP files (`message_encoding: cdr`).

Kept here so the data layer's bag code reaches ROS only through msg_adapters.
"""
from __future__ import annotations

import struct
from typing import TypeVar

from rclpy.serialization import deserialize_message, serialize_message

from msg_adapters.errors import MessageFormatError

M = TypeVar("M")

# Encapsulation ids whose body is plain (not parameter-list) CDR: CDR, XCDR2; even = big endian.
PLAIN_ENCAPSULATIONS = {0x0000: ">", 0x0001: "<", 0x0006: ">", 0x0007: "<"}


def msg_to_cdr(msg: object) -> bytes:
    """Serialize a ROS message to the CDR bytes a bag stores."""
    return serialize_message(msg)


def cdr_to_msg(data: bytes, msg_type: type[M]) -> M:
    """Deserialize CDR bytes into a message of `msg_type`."""
    return deserialize_message(data, msg_type)


def cdr_to_string_bytes(data: bytes) -> bytes:
    """The undecoded bytes of a serialized std_msgs/String (without its NUL terminator).

    rclpy's own decoding replaces invalid UTF-8 and stops at an embedded NUL, so a node
    that must judge the text as sent (parser_node) reads the bytes here instead.
    """
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
    return bytes(data[8 : 7 + length])
