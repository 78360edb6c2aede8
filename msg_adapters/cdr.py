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
    """Serialize a ROS message to the CDR bytes a bag stores. The serializer leaves CDR's
    alignment padding as it found the memory; it is zeroed for the types with padding that
    our bags carry, so the same episodes always give the same bytes."""
    data = serialize_message(msg)
    padding = _PADDING.get(f"{type(msg).__module__.split('.')[0]}/{type(msg).__name__}")
    return data if padding is None else _zeroed(data, padding(data))


def _aligned(position: int) -> int:
    """The next 4-byte boundary of a CDR body (which starts after the 4-byte encapsulation)."""
    return position + (-(position - 4)) % 4


def _string_end(data: bytes, position: int, endian: str) -> int:
    (chars,) = struct.unpack_from(f"{endian}I", data, position)
    return position + 4 + chars


def _image_padding(data: bytes) -> list[slice]:
    """sensor_msgs/Image: after header.frame_id, and after encoding + is_bigendian."""
    endian = PLAIN_ENCAPSULATIONS[int.from_bytes(data[:2], "big")]
    frame_end = _string_end(data, 12, endian)  # encapsulation 4, stamp 8
    encoding_end = _string_end(data, _aligned(frame_end) + 8, endian)  # height, width
    return [slice(frame_end, _aligned(frame_end)), slice(encoding_end + 1, _aligned(encoding_end + 1))]


def _goal_status_padding(data: bytes) -> list[slice]:
    """actionlib_msgs/GoalStatus: after goal_id.id + the status byte."""
    endian = PLAIN_ENCAPSULATIONS[int.from_bytes(data[:2], "big")]
    status_end = _string_end(data, 12, endian) + 1  # encapsulation 4, stamp 8, id, status
    return [slice(status_end, _aligned(status_end))]


_PADDING = {"sensor_msgs/Image": _image_padding, "actionlib_msgs/GoalStatus": _goal_status_padding}


def _zeroed(data: bytes, spans: list[slice]) -> bytes:
    if all(not any(data[span]) for span in spans):
        return data
    out = bytearray(data)
    for span in spans:
        out[span] = bytes(span.stop - span.start)
    return bytes(out)


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
