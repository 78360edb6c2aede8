"""CDR bytes <-> ROS 2 messages, with rosbags' pure-Python serializer (no ROS installation).

CDR is both what DDS carries (the nodes publish and take serialized messages) and what
rosbag2 MCAP files store (`message_encoding: cdr`), so nodes and bags share these
conversions. Messages are the dataclasses of rosbags' Jazzy type store; rosbags
serializes into a fresh zeroed buffer, so alignment padding is zero and the same
message always gives the same bytes. The type store also gives a bag its schemas.
"""
from __future__ import annotations

from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore

from msg_adapters.errors import MessageFormatError

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)

# Encapsulation ids whose body is plain (not parameter-list) CDR: CDR, XCDR2; even = big endian.
PLAIN_ENCAPSULATIONS = {0x0000: ">", 0x0001: "<", 0x0006: ">", 0x0007: "<"}


def message_class(msg_type: str) -> type:
    """The rosbags dataclass of "pkg/msg/Type"."""
    return TYPESTORE.types[msg_type]


def msg_to_cdr(msg: object) -> bytes:
    """The little-endian CDR bytes of a rosbags message."""
    return bytes(TYPESTORE.serialize_cdr(msg, msg.__msgtype__, little_endian=True))


def cdr_to_msg(data: bytes, msg_type: str) -> object:
    """The rosbags message of serialized "pkg/msg/Type" bytes; MessageFormatError when they
    do not hold one (truncated, wrong lengths, unknown encapsulation, invalid UTF-8)."""
    try:
        return TYPESTORE.deserialize_cdr(data, msg_type)
    except SerdeError as exc:
        raise MessageFormatError(f"malformed {msg_type}: {exc}") from None


def message_definition(msg_type: str) -> str:
    """The ros2msg schema text of "pkg/msg/Type": its fields, then each nested type's under a
    row of 80 '=' and a `MSG: pkg/Type` line (rosbag2's layout, without the comments)."""
    if msg_type not in TYPESTORE.types:
        raise MessageFormatError(f"{msg_type} is not a ROS 2 Jazzy message type")
    return TYPESTORE.generate_msgdef(msg_type, ros_version=2)[0]


def type_hash(msg_type: str) -> str:
    """The RIHS01 type description hash of "pkg/msg/Type" as ROS 2 Jazzy computes it ('' for
    a type outside Jazzy: another package's, copied from a bag)."""
    return TYPESTORE.hash_rihs01(msg_type) if msg_type in TYPESTORE.types else ""
