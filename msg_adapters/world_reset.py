"""World reset time (ns since the epoch) <-> std_msgs/Header (topic `world_reset`).

The stamp is the moment the world simulator loaded its new situation: every message
published before it belongs to the previous world (docs/ros.md "Resets").
"""
from __future__ import annotations

from msg_adapters.cdr import cdr_to_msg, msg_to_cdr
from msg_adapters.header import Header, make_header, time_ns


def reset_to_cdr(t_ns: int) -> bytes:
    return msg_to_cdr(make_header(t_ns))


def cdr_to_reset(data: bytes) -> int:
    return time_ns(cdr_to_msg(data, Header.__msgtype__).stamp)
