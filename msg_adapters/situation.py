"""Situation <-> std_msgs/String carrying gSCAN situation JSON (topic `situation`).

The world simulator publishes the state it is in; a recorder writes the one of an
episode's first observation into the bag header, so a recorded run replays.
"""
from __future__ import annotations

import json

from std_msgs.msg import String

from gscan_ros.world.types import Situation
from msg_adapters.errors import MessageFormatError


def situation_to_msg(situation: Situation) -> String:
    """The situation's gSCAN JSON (as in dataset.txt)."""
    return String(data=json.dumps(situation.to_json()))


def msg_to_situation(msg: String) -> Situation:
    """Parse and validate; bad JSON raises MessageFormatError, a bad situation a GscanError naming the field."""
    data = getattr(msg, "data", None)
    if not isinstance(data, str):
        raise MessageFormatError(f"expected a std_msgs/String with situation JSON, got {type(msg).__name__}")
    try:
        fields = json.loads(data)
    except json.JSONDecodeError as exc:
        raise MessageFormatError(f"situation is not JSON ({exc.msg} at position {exc.pos})") from None
    if not isinstance(fields, dict):
        raise MessageFormatError(f"situation JSON must be an object, got {type(fields).__name__}")
    return Situation.from_json(fields)
