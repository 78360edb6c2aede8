"""Times (ns since the epoch) <-> builtin_interfaces/Time, and the header of a grid message.

Every stamped message of the stack says which world state it shows: `header.stamp` is
the time the world reached that state, `header.frame_id` the grid frame
(`gscan_ros.interface.GRID_FRAME`, docs/ros.md "Frames and stamps").
"""
from __future__ import annotations

from gscan_ros.interface import GRID_FRAME
from msg_adapters.cdr import message_class

Time = message_class("builtin_interfaces/msg/Time")
Header = message_class("std_msgs/msg/Header")

NS_PER_S = 1_000_000_000


def time_msg(t_ns: int) -> Time:
    return Time(sec=t_ns // NS_PER_S, nanosec=t_ns % NS_PER_S)


def time_ns(stamp: Time) -> int:
    return stamp.sec * NS_PER_S + stamp.nanosec


def make_header(t_ns: int = 0, frame_id: str = "") -> Header:
    """A std_msgs/Header stamped `t_ns` in `frame_id` (by default: time 0, no frame, as ROS's default Header)."""
    return Header(stamp=time_msg(t_ns), frame_id=frame_id)


def grid_header(t_ns: int) -> Header:
    """The header of a message that shows the world state reached at `t_ns`."""
    return make_header(t_ns, GRID_FRAME)
