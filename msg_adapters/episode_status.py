"""EpisodeStatus <-> actionlib_msgs/GoalStatus (topic `episode_status`).

An episode is a goal the policy pursues: `goal_id.id` names the episode, `goal_id.stamp`
is when the policy took its command graph, `status` is ACTIVE while it runs and then the
terminal state that says how it ended, `text` is for people (docs/ros.md "Episodes").
"""
from __future__ import annotations

from gscan_ros import episode_status as es
from gscan_ros.errors import GscanError
from msg_adapters.cdr import cdr_to_msg, message_class, msg_to_cdr
from msg_adapters.errors import MessageFormatError
from msg_adapters.header import time_msg, time_ns

GoalStatus = message_class("actionlib_msgs/msg/GoalStatus")
GoalID = message_class("actionlib_msgs/msg/GoalID")

MAX_TEXT = 1024  # a status is a short line; longer texts are cut

_STATUS = {
    es.ACTIVE: GoalStatus.ACTIVE,
    es.COMPLETE: GoalStatus.SUCCEEDED,
    es.CUT: GoalStatus.ABORTED,
    es.PREEMPTED: GoalStatus.PREEMPTED,
    es.REJECTED: GoalStatus.REJECTED,
}
_OUTCOME = {code: outcome for outcome, code in _STATUS.items()}


def episode_status_to_cdr(status: es.EpisodeStatus) -> bytes:
    return msg_to_cdr(GoalStatus(goal_id=GoalID(stamp=time_msg(status.start_ns), id=status.episode_id),
                                 status=_STATUS[status.outcome], text=status.text[:MAX_TEXT]))


def cdr_to_episode_status(data: bytes) -> es.EpisodeStatus:
    """A report as the policy sends it and a bag stores it."""
    msg = cdr_to_msg(data, GoalStatus.__msgtype__)
    outcome = _OUTCOME.get(msg.status)
    if outcome is None:
        raise MessageFormatError(f"episode status {msg.status} is not one the policy sends "
                                 f"({', '.join(f'{c} {o}' for c, o in sorted(_OUTCOME.items()))})")
    try:
        return es.EpisodeStatus(msg.goal_id.id, time_ns(msg.goal_id.stamp), outcome, msg.text)
    except GscanError as exc:
        raise MessageFormatError(str(exc)) from None
