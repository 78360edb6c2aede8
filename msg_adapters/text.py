"""Plain text <-> std_msgs/String: commands, status lines and a bag's JSON episode headers.

The bag code stores and reads `/command` and `/command_graph` text through here, so the
data layer never builds ROS messages itself.
"""
from __future__ import annotations

from std_msgs.msg import String

from msg_adapters.cdr import cdr_to_msg


def text_to_msg(text: str) -> String:
    return String(data=text)


def msg_to_text(msg: String) -> str:
    return msg.data


def cdr_to_text(data: bytes) -> str:
    """The text of a serialized std_msgs/String (rclpy's decoding: invalid UTF-8 is replaced)."""
    return cdr_to_msg(data, String).data
