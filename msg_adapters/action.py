"""Action <-> std_msgs/String carrying one gSCAN action token ("turn left", "<eos>", ...)."""
from __future__ import annotations

from gscan_ros.world.types import Action
from msg_adapters.text import cdr_to_text, text_to_cdr


def action_to_cdr(action: Action) -> bytes:
    """The dataset token of `action`; EOS is sent as "<eos>"."""
    return text_to_cdr(Action(action).token)


def cdr_to_action(data: bytes) -> Action:
    """Parse the token; an unknown token raises InvalidActionError naming it."""
    return Action.from_token(cdr_to_text(data))
