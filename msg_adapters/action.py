"""Action <-> std_msgs/String carrying one gSCAN action token ("turn left", "<eos>", ...)."""
from __future__ import annotations

from std_msgs.msg import String

from gscan_ros.world.types import Action
from msg_adapters.cdr import cdr_to_msg


def action_to_msg(action: Action) -> String:
    """The dataset token of `action`; EOS is sent as "<eos>"."""
    return String(data=Action(action).token)


def msg_to_action(msg: String) -> Action:
    """Parse the token; an unknown token raises InvalidActionError naming it."""
    return Action.from_token(msg.data)


def cdr_to_action(data: bytes) -> Action:
    """msg_to_action of a serialized std_msgs/String (a bag's `/action` record)."""
    return msg_to_action(cdr_to_msg(data, String))
