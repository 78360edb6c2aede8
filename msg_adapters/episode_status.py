"""EpisodeStatus <-> actionlib_msgs/GoalStatus (topic `episode_status`).

An episode is a goal the policy pursues: `goal_id.id` names the episode, `goal_id.stamp`
is when the policy took its command graph, `status` is ACTIVE while it runs and then the
terminal state that says how it ended, `text` is for people (docs/ros.md "Episodes").
"""
from __future__ import annotations

from actionlib_msgs.msg import GoalID, GoalStatus

from gscan_ros import episode_status as es
from gscan_ros.errors import GscanError
from msg_adapters.cdr import cdr_to_msg
from msg_adapters.errors import MessageFormatError
from msg_adapters.header import time_msg, time_ns

MAX_TEXT = 1024  # a status is a short line; longer texts are cut

_STATUS = {
    es.ACTIVE: GoalStatus.ACTIVE,
    es.COMPLETE: GoalStatus.SUCCEEDED,
    es.CUT: GoalStatus.ABORTED,
    es.PREEMPTED: GoalStatus.PREEMPTED,
    es.REJECTED: GoalStatus.REJECTED,
}
_OUTCOME = {code: outcome for outcome, code in _STATUS.items()}


def episode_status_to_msg(status: es.EpisodeStatus) -> GoalStatus:
    return GoalStatus(goal_id=GoalID(stamp=time_msg(status.start_ns), id=status.episode_id),
                      status=_STATUS[status.outcome], text=status.text[:MAX_TEXT])


def msg_to_episode_status(msg: GoalStatus) -> es.EpisodeStatus:
    if not isinstance(msg, GoalStatus):
        raise MessageFormatError(f"expected an actionlib_msgs/GoalStatus, got {type(msg).__name__}")
    outcome = _OUTCOME.get(msg.status)
    if outcome is None:
        raise MessageFormatError(f"episode status {msg.status} is not one the policy sends "
                                 f"({', '.join(f'{c} {o}' for c, o in sorted(_OUTCOME.items()))})")
    try:
        return es.EpisodeStatus(msg.goal_id.id, time_ns(msg.goal_id.stamp), outcome, msg.text)
    except GscanError as exc:
        raise MessageFormatError(str(exc)) from None


def cdr_to_episode_status(data: bytes) -> es.EpisodeStatus:
    """A report as a bag stores it (CDR bytes)."""
    return msg_to_episode_status(cdr_to_msg(data, GoalStatus))
