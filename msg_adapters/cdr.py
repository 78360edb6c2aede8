"""CDR bytes <-> ROS messages, the encoding of rosbag2 MCAP files (`message_encoding: cdr`).

Kept here so the data layer's bag code reaches ROS only through msg_adapters.
"""
from __future__ import annotations

from typing import TypeVar

from rclpy.serialization import deserialize_message, serialize_message

M = TypeVar("M")


def msg_to_cdr(msg: object) -> bytes:
    """Serialize a ROS message to the CDR bytes a bag stores."""
    return serialize_message(msg)


def cdr_to_msg(data: bytes, msg_type: type[M]) -> M:
    """Deserialize CDR bytes into a message of `msg_type`."""
    return deserialize_message(data, msg_type)
