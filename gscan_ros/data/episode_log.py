"""Rebuild lock-step episodes from independently delivered, timestamped topic streams.

DDS delivers each topic on its own, so a recorder may see action t after the
observation it caused. Every message is therefore kept with its DDS source timestamp
(and an action with its publisher's sequence number), and an episode is cut out of the
buffers when it ends, with the rule the policy follows (docs/ros.md "Lock-step"):

- an episode's actions are one lock-step chain after its command graph: the first is
  the first action after the graph; each next one is sent after the world's reply to
  the previous one (the first observation after it) and, where the middleware reports
  publication sequence numbers, is the next message of the same publisher. An action
  that does not extend the chain (another publisher's, or a second answer to the same
  observation) is not part of the episode, and an `<eos>` that does not closes nothing;
- observation 0 is the newest one published before action 0; observation t+1 is the
  reply to action t;
- the situation of observation 0 is the newest one published no later than it (the
  world publishes `situation` just before `observation`); each observation's image is
  the first one published after it and before the next observation.

An episode ends **complete** with its `<eos>`, or **aborted** by a world reset (the
world's `world_reset` stamp): then the chain up to the reset is recorded as aborted,
and nothing published before the reset counts for a later episode. The reset notice can
overtake the world's last replies (another topic), so it is cut only once the world's
new state, published after it, has arrived (`reset_settled`): one publisher's messages
arrive in order, so every reply sent before the reset is in by then.

Pure Python (no rclpy): messages are opaque payloads here.
"""
from __future__ import annotations

import bisect
from collections import deque
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

from gscan_ros.data.bag_format import OUTCOME_ABORTED, OUTCOME_COMPLETE
from gscan_ros.world.types import Action

T = TypeVar("T")

COMPLETE = OUTCOME_COMPLETE
ABORTED = OUTCOME_ABORTED
RESET_REASON = "the world was reset"
NO_REPLY = "no reply to the episode's previous action has arrived"


@dataclass(frozen=True)
class Stamped(Generic[T]):
    t_ns: int  # DDS source timestamp of the message
    value: T
    seq: int | None = None  # the publisher's sequence number of the message, when known


class StampedBuffer(Generic[T]):
    """The last `capacity` messages of one topic, kept sorted by source timestamp."""

    def __init__(self, capacity: int) -> None:
        self._items: deque[Stamped[T]] = deque(maxlen=capacity)

    def __len__(self) -> int:
        return len(self._items)

    def add(self, t_ns: int, value: T, seq: int | None = None) -> Stamped[T]:
        item = Stamped(t_ns, value, seq)
        if not self._items or self._items[-1].t_ns <= t_ns:
            self._items.append(item)
        else:  # rare: delivered out of order; keep the buffer sorted
            items = list(self._items)
            items.insert(bisect.bisect_right([i.t_ns for i in items], t_ns), item)
            self._items = deque(items, maxlen=self._items.maxlen)
        return item

    def remove(self, item: Stamped[T]) -> None:
        self._items.remove(item)

    def resize(self, capacity: int) -> None:
        """Keep at most `capacity` messages from now on (the newest, when it shrinks)."""
        self._items = deque(self._items, maxlen=capacity)

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
    action: Stamped[Action] | None  # None: the state an aborted episode's last action led to


@dataclass(frozen=True)
class EpisodeRecord:
    """One ended episode: its graph, initial situation and lock-step steps.

    Complete: T+1 steps, the last action `<eos>`. Aborted: one step per action sent
    before the end, then (when it was published in time) the state the last one led to.
    """

    graph: Stamped[Any]
    situation: Stamped[Any]
    steps: tuple[Step, ...]
    end_ns: int  # its `<eos>`, or the reset that aborted it
    left_out: int = 0  # actions in the episode's time span that were not part of its chain
    outcome: str = COMPLETE
    reason: str = ""  # why an aborted episode ended

    @property
    def start_ns(self) -> int:
        return min(self.graph.t_ns, self.steps[0].observation.t_ns)

    @property
    def actions(self) -> tuple[Action, ...]:
        """The world actions (without `<eos>`)."""
        return tuple(
            step.action.value for step in self.steps if step.action is not None and step.action.value is not Action.EOS
        )


LeftOut = tuple[Stamped[Action], str]  # an action of no chain, and why


class IncompleteEpisode(Exception):
    """The buffers lack a message the episode needs (it scrolled out, or never arrived)."""


class UnpairedAction(Exception):
    """An `<eos>` that ends no episode: not part of its lock-step chain, or its episode already ended."""


class EpisodeLog:
    """The recorder's buffers, and the rules that cut them into episodes (module docstring).

    Feed every message with its source timestamp. `add_action` returns the episode an
    `<eos>` completes, `add_reset` the episode a world reset aborts (None when nothing
    ran). Everything up to the end of an episode that was returned, or abandoned,
    belongs to no later one.
    """

    def __init__(self, capacity: int, *, images: bool = False) -> None:
        self.capacity = capacity
        self.graphs: StampedBuffer[Any] = StampedBuffer(capacity)
        self.actions: StampedBuffer[Action] = StampedBuffer(capacity)
        self.observations: StampedBuffer[Any] = StampedBuffer(capacity)
        self.situations: StampedBuffer[Any] = StampedBuffer(capacity)
        self.images: StampedBuffer[Any] | None = StampedBuffer(capacity) if images else None
        self._ended_ns = -1  # the end of the last episode that was returned or abandoned

    def resize(self, capacity: int) -> None:
        """Bound every buffer to `capacity` messages (a live recorder's `buffer_messages`)."""
        self.capacity = capacity
        for buffer in (self.graphs, self.actions, self.observations, self.situations, self.images):
            if buffer is not None:
                buffer.resize(capacity)

    def record_images(self, on: bool) -> None:
        """Pair images with observations (on) or not (off); a step without its image has none."""
        if on and self.images is None:
            self.images = StampedBuffer(self.capacity)
        elif not on:
            self.images = None

    def add_action(self, t_ns: int, action: Action, seq: int | None = None) -> EpisodeRecord | None:
        """Buffer an action; for an `<eos>`, the complete episode it closes.

        Raises UnpairedAction for an `<eos>` that closes nothing (it is then forgotten, so
        it cannot break a later chain) and IncompleteEpisode when a message is missing.
        """
        eos = self.actions.add(t_ns, action, seq)
        if action is not Action.EOS:
            return None
        return self.close(eos)

    def close(self, eos: Stamped[Action]) -> EpisodeRecord | None:
        """The episode the buffered `<eos>` closes. Topics arrive independently, so an
        `<eos>` can come before the world's last replies: on IncompleteEpisode the caller
        may call again when more observations have arrived."""
        t_ns = eos.t_ns
        graph = self.graphs.latest_before(t_ns)
        if graph is None and self._ended_ns < 0:
            raise IncompleteEpisode("no command graph before <eos>")
        if graph is None or graph.t_ns <= self._ended_ns:
            self.actions.remove(eos)
            raise UnpairedAction("no command graph has started an episode since the last one ended")
        chain, left_out = self._chain(graph.t_ns, t_ns)
        if chain[-1] is not eos:
            reason = left_out[-1][1]
            if reason == NO_REPLY:
                raise IncompleteEpisode(f"no observation after action {len(chain) - 1}")
            self.actions.remove(eos)
            raise UnpairedAction(reason)
        record = self._record(graph, chain, COMPLETE, t_ns, left_out=len(left_out))
        self._end(record)
        return record

    def superseded(self, eos: Stamped[Action]) -> bool:
        """A command graph newer than `eos` arrived: its episode will not complete any more."""
        return self.graphs.first_after(eos.t_ns) is not None

    def reset_settled(self, reset_ns: int) -> bool:
        """Whether an observation published at or after the reset has arrived, and with it
        every earlier one (the world publishes its new state after the reset notice)."""
        return self.observations.first_after(reset_ns - 1) is not None

    def add_reset(self, reset_ns: int) -> EpisodeRecord | None:
        """The world was reset at `reset_ns`: the episode running then, recorded as aborted
        with the replies that have arrived (call it once `reset_settled`, to have them all)."""
        if reset_ns <= self._ended_ns:
            return None
        graph = self.graphs.latest_before(reset_ns)
        running = graph is not None and graph.t_ns > self._ended_ns
        chain, left_out = self._chain(graph.t_ns, reset_ns - 1) if running else ([], [])
        self._ended_ns = reset_ns  # recorded or not, nothing before the reset belongs to a later episode
        if not chain:
            return None
        record = self._record(graph, chain, ABORTED, reset_ns, left_out=len(left_out))
        self._end(record)
        return record

    # -- rules ---------------------------------------------------------------------------
    def _chain(self, after_ns: int, until_ns: int) -> tuple[list[Stamped[Action]], list[LeftOut]]:
        """The lock-step chain of the actions in (after_ns, until_ns], and the actions left
        out with the reason for each (the chain stops where a reply is missing)."""
        chain: list[Stamped[Action]] = []
        left_out: list[LeftOut] = []
        for action in self.actions.between(after_ns, until_ns):
            if not chain:
                chain.append(action)
                continue
            last = chain[-1]
            reply = self.observations.first_after(last.t_ns)
            if None not in (action.seq, last.seq) and action.seq != last.seq + 1:
                left_out.append((action, "it is not the next message of the episode's action publisher"))
            elif reply is None:  # missing: the rest cannot be judged
                left_out.append((action, NO_REPLY))
                break
            elif reply.t_ns > action.t_ns:
                left_out.append((action, "it was sent before the world replied to the episode's previous action"))
            else:
                chain.append(action)
        return chain, left_out

    def _record(self, graph: Stamped, chain: list[Stamped[Action]], outcome: str, end_ns: int, *,
                left_out: int) -> EpisodeRecord:
        observation = self.observations.latest_before(chain[0].t_ns)
        if observation is None:
            raise IncompleteEpisode("no observation before the first action")
        situation = self.situations.latest_before(observation.t_ns, inclusive=True)
        if situation is None:
            raise IncompleteEpisode("no situation published with the first observation")
        steps = []
        for action in chain:
            if observation is None:
                raise IncompleteEpisode(f"no observation after action {len(steps) - 1}")
            steps.append(Step(observation, self._image_of(observation), action))
            observation = self.observations.first_after(action.t_ns)
        if outcome == ABORTED:
            if observation is not None and observation.t_ns < end_ns:
                steps.append(Step(observation, self._image_of(observation), None))
            return EpisodeRecord(graph, situation, tuple(steps), end_ns, left_out, ABORTED, RESET_REASON)
        return EpisodeRecord(graph, situation, tuple(steps), end_ns, left_out)

    def _end(self, record: EpisodeRecord) -> None:
        """Forget what only the ended episode used; its last state (observation and the
        situation published with it) may start the next one."""
        self._ended_ns = record.end_ns
        keep_from = record.steps[-1].observation.t_ns
        for buffer in (self.graphs, self.actions, self.observations, self.images):
            if buffer is not None:
                buffer.drop_until(keep_from)
        situation = self.situations.latest_before(keep_from, inclusive=True)
        self.situations.drop_until(keep_from if situation is None else situation.t_ns)

    def _image_of(self, observation: Stamped) -> Stamped | None:
        if self.images is None:
            return None
        image = self.images.first_after(observation.t_ns)
        following = self.observations.first_after(observation.t_ns)
        if image is None or (following is not None and image.t_ns > following.t_ns):
            return None
        return image
