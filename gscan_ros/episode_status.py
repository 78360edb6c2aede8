"""How an episode went, as the policy reports it on `episode_status` (docs/ros.md "Episodes").

The policy announces every episode it starts (`active`) and says how it ended: the model's
own `<eos>` (`complete`), an `<eos>` it forced (`cut`: at `max_steps`, after a failed step,
or when no reply came within `step_timeout`), a new command or a world reset that replaced
it (`preempted`; a recorder ends so an episode still running when its bag closes), or a
command graph it could not follow (`rejected`). Only complete episodes are
demonstrations: readers skip the rest unless asked (`include_incomplete`) and count them
by outcome. One vocabulary for the policy, the bag writer and readers, the commander and
the reports; `msg_adapters.episode_status` maps it to actionlib_msgs/GoalStatus.
"""
from __future__ import annotations

from dataclasses import dataclass

from gscan_ros.errors import DatasetFormatError

ACTIVE = "active"
COMPLETE = "complete"
CUT = "cut"
PREEMPTED = "preempted"
REJECTED = "rejected"
ENDINGS = (COMPLETE, CUT, PREEMPTED, REJECTED)
INCOMPLETE = (CUT, PREEMPTED, REJECTED)
# The first bag format called an episode a world reset ended "aborted".
LEGACY_OUTCOMES = {"aborted": PREEMPTED}


@dataclass(frozen=True)
class EpisodeStatus:
    """One report of the policy on an episode: it started, or how it ended."""

    # "<node name>/<n>", n from 1 each time the node starts (unique with start_ns, as a
    # GoalID); a generated bag's "<episode number>"
    episode_id: str
    start_ns: int  # when the policy took the episode's command graph (its goal stamp)
    outcome: str  # ACTIVE or one of ENDINGS
    text: str = ""  # for people: the command, or why it ended

    def __post_init__(self) -> None:
        if self.outcome != ACTIVE and self.outcome not in ENDINGS:
            raise DatasetFormatError(f"unknown episode outcome {self.outcome!r}")

    @property
    def ended(self) -> bool:
        return self.outcome != ACTIVE


def outcome_of(name: str) -> str:
    """An outcome as stored in a bag header, today's name for a legacy one."""
    outcome = LEGACY_OUTCOMES.get(name, name)
    if outcome not in ENDINGS:
        raise DatasetFormatError(f"unknown episode outcome {name!r}")
    return outcome
