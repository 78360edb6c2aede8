"""Rebuild lock-step episodes from independently delivered, timestamped topic streams.

DDS delivers each topic on its own, so a recorder may see action t after the
observation it caused. Every message is therefore kept with its DDS source timestamp,
and an episode is assembled when its `<eos>` arrives, with the same rule the policy
uses (docs/ros.md "Lock-step"):

- the episode's actions are those published after its command graph, up to `<eos>`;
- observation 0 is the newest one published before action 0; observation t+1 is the
  first one published after action t;
- the situation of observation 0 is the newest one published no later than it (the
  world publishes `situation` just before `observation`); each observation's image is
  the first one published after it and before the next observation.

Pure Python (no rclpy): messages are opaque payloads here.
"""
from __future__ import annotations

import bisect
from collections import deque
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

from gscan_ros.world.types import Action

T = TypeVar("T")


@dataclass(frozen=True)
class Stamped(Generic[T]):
    t_ns: int  # DDS source timestamp of the message
    value: T


class StampedBuffer(Generic[T]):
    """The last `capacity` messages of one topic, kept sorted by source timestamp."""

    def __init__(self, capacity: int) -> None:
        self._items: deque[Stamped[T]] = deque(maxlen=capacity)

    def __len__(self) -> int:
        return len(self._items)

    def add(self, t_ns: int, value: T) -> None:
        item = Stamped(t_ns, value)
        if not self._items or self._items[-1].t_ns <= t_ns:
            self._items.append(item)
        else:  # rare: delivered out of order; keep the buffer sorted
            items = list(self._items)
            items.insert(bisect.bisect_right([i.t_ns for i in items], t_ns), item)
            self._items = deque(items, maxlen=self._items.maxlen)

    def latest_before(self, t_ns: int, *, inclusive: bool = False) -> Stamped[T] | None:
        """Newest item published before `t_ns` (or at it, when inclusive)."""
        found = None
        for item in self._items:
            if item.t_ns > t_ns or (item.t_ns == t_ns and not inclusive):
                break
            found = item
        return found

    def first_after(self, t_ns: int) -> Stamped[T] | None:
        return next((item for item in self._items if item.t_ns > t_ns), None)

    def between(self, after_ns: int, until_ns: int) -> list[Stamped[T]]:
        """Items with after_ns < t <= until_ns, in time order."""
        return [item for item in self._items if after_ns < item.t_ns <= until_ns]

    def drop_until(self, t_ns: int) -> None:
        """Forget items older than `t_ns` (they cannot belong to a later episode)."""
        while self._items and self._items[0].t_ns < t_ns:
            self._items.popleft()


@dataclass(frozen=True)
class Step:
    observation: Stamped[Any]
    image: Stamped[Any] | None
    action: Stamped[Action]


@dataclass(frozen=True)
class EpisodeRecord:
    """One finished episode: its graph, initial situation and T+1 lock-step steps (last = `<eos>`)."""

    graph: Stamped[Any]
    situation: Stamped[Any]
    steps: tuple[Step, ...]

    @property
    def start_ns(self) -> int:
        return min(self.graph.t_ns, self.steps[0].observation.t_ns)

    @property
    def actions(self) -> tuple[Action, ...]:
        """The world actions (without the final `<eos>`)."""
        return tuple(step.action.value for step in self.steps[:-1])


class IncompleteEpisode(Exception):
    """The buffers lack a message the episode needs (it scrolled out, or never arrived)."""


def assemble_episode(
    eos_ns: int,
    graphs: StampedBuffer,
    actions: StampedBuffer[Action],
    observations: StampedBuffer,
    situations: StampedBuffer,
    images: StampedBuffer | None = None,
) -> EpisodeRecord:
    """The episode that the `<eos>` published at `eos_ns` closes; raises IncompleteEpisode."""
    graph = graphs.latest_before(eos_ns)
    if graph is None:
        raise IncompleteEpisode("no command graph before <eos>")
    episode_actions = actions.between(graph.t_ns, eos_ns)
    if not episode_actions or episode_actions[-1].value is not Action.EOS:
        raise IncompleteEpisode("the <eos> is not among the buffered actions")
    observation = observations.latest_before(episode_actions[0].t_ns)
    if observation is None:
        raise IncompleteEpisode("no observation before the first action")
    situation = situations.latest_before(observation.t_ns, inclusive=True)
    if situation is None:
        raise IncompleteEpisode("no situation published with the first observation")
    steps = []
    for action in episode_actions:
        if observation is None:
            raise IncompleteEpisode(f"no observation after action {len(steps) - 1}")
        steps.append(Step(observation, _image_of(observation, observations, images), action))
        observation = observations.first_after(action.t_ns)
    return EpisodeRecord(graph, situation, tuple(steps))


def _image_of(observation: Stamped, observations: StampedBuffer, images: StampedBuffer | None) -> Stamped | None:
    if images is None:
        return None
    image = images.first_after(observation.t_ns)
    following = observations.first_after(observation.t_ns)
    if image is None or (following is not None and image.t_ns > following.t_ns):
        return None
    return image
