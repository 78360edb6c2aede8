"""Situation <-> std_msgs/String carrying gSCAN situation JSON (topic `situation`).

The world simulator publishes the state it is in; a recorder writes the one of an
episode's first observation into the bag header, so a recorded run replays.
"""
from __future__ import annotations

import json

from gscan_ros.world.types import Situation
from msg_adapters.errors import MessageFormatError
from msg_adapters.text import cdr_to_text, text_to_cdr


def situation_to_cdr(situation: Situation) -> bytes:
    """The situation's gSCAN JSON (as in dataset.txt)."""
    return text_to_cdr(json.dumps(situation.to_json()))


def cdr_to_situation(data: bytes) -> Situation:
    """Parse and validate; bad JSON raises MessageFormatError, a bad situation a GscanError naming the field."""
    try:
        fields = json.loads(cdr_to_text(data))
    except json.JSONDecodeError as exc:
        raise MessageFormatError(f"situation is not JSON ({exc.msg} at position {exc.pos})") from None
    if not isinstance(fields, dict):
        raise MessageFormatError(f"situation JSON must be an object, got {type(fields).__name__}")
    return Situation.from_json(fields)
