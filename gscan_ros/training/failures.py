"""Where a failed episode went wrong, judged by replaying the gold and the predicted
actions in the one world. Torch-free, so that the report reads the kinds without it."""
from __future__ import annotations

from typing import Sequence

from gscan_ros.data.episode import Episode
from gscan_ros.errors import InvalidActionError
from gscan_ros.world.types import Action
from gscan_ros.world.world import World

FAILURE_KINDS = {  # kind -> what it means, in the order the reports print them
    "no_stop": "no <eos> of its own: stopped at the decoding cap",
    "target_not_reached": "never stood on the target",
    "wrong_end_state": "reached the target, but the agent or an object ended elsewhere",
    "right_end_state": "the gold end state (agent cell, every object's cell) by other actions",
}


def failure_label(kind: str) -> str:
    """How tables and logs print a kind: `no_stop` -> `no stop`."""
    return kind.replace("_", " ")


def classify_failure(episode: Episode, actions: Sequence[Action], stopped: bool = True) -> str | None:
    """The `FAILURE_KINDS` entry of `actions` decoded for `episode`, `stopped` by the
    model's own EOS or not (None when they are the gold). The end state ignores the
    agent's heading; an action the world rejects leaves it as it was, as in the closed loop."""
    if list(actions) == list(episode.actions):
        return None
    if not stopped:
        return "no_stop"
    gold, ours = _replay(episode, episode.actions), _replay(episode, actions)
    if ours[:2] == gold[:2]:
        return "right_end_state"
    return "wrong_end_state" if ours[2] else "target_not_reached"


def _replay(episode: Episode, actions: Sequence[Action]) -> tuple:
    """(agent cell, object cells, whether the agent stood on the target's cell) after `actions`."""
    world = World(episode.situation)

    def on_target() -> bool:
        return world.target is not None and world.agent_position == world.target.position

    reached = on_target()
    for action in actions:
        try:
            world.step(action)
        except InvalidActionError:
            pass
        reached = reached or on_target()
    return world.agent_position, tuple(o.position for o in world.objects), reached
