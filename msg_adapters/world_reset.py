"""World reset time (ns since the epoch) <-> std_msgs/Header (topic `world_reset`).

The stamp is the moment the world simulator loaded its new situation: every message
published before it belongs to the previous world (docs/ros.md "Resets").
"""
from __future__ import annotations

from builtin_interfaces.msg import Time
from std_msgs.msg import Header

from msg_adapters.errors import MessageFormatError
from msg_adapters.header import time_msg, time_ns


def reset_to_msg(t_ns: int) -> Header:
    return Header(stamp=time_msg(t_ns))


def msg_to_reset(msg: Header) -> int:
    stamp = getattr(msg, "stamp", None)
    if not isinstance(stamp, Time):
        raise MessageFormatError(f"expected a std_msgs/Header with the reset time, got {type(msg).__name__}")
    return time_ns(stamp)
