"""Times (ns since the epoch) <-> builtin_interfaces/Time, and the header of a grid message.

Every stamped message of the stack says which world state it shows: `header.stamp` is
the time the world reached that state, `header.frame_id` the grid frame
(`gscan_ros.interface.GRID_FRAME`, docs/ros.md "Frames and stamps").
"""
from __future__ import annotations

from builtin_interfaces.msg import Time
from std_msgs.msg import Header

from gscan_ros.interface import GRID_FRAME

NS_PER_S = 1_000_000_000


def time_msg(t_ns: int) -> Time:
    return Time(sec=t_ns // NS_PER_S, nanosec=t_ns % NS_PER_S)


def time_ns(stamp: Time) -> int:
    return stamp.sec * NS_PER_S + stamp.nanosec


def grid_header(t_ns: int) -> Header:
    """The header of a message that shows the world state reached at `t_ns`."""
    return Header(stamp=time_msg(t_ns), frame_id=GRID_FRAME)
