"""Cut the stack's live topics into episodes: the rule every format-2 bag is read with.

A bag of the live topics (our generator's, our recorder's, or any all-topics recorder's
such as `ros2 bag record -a`) is read in publication order (the MCAP publish time, the
DDS source timestamp), and episodes are what the policy reports (docs/bags.md):

- an episode runs from the policy's ACTIVE report on `/episode_status` to its report of
  how it ended; its actions are the `/action` messages published in between (the policy
  publishes ACTIVE before its first action and the end after its last), so a preempted
  episode's last action never leaks into the next one;
- its initial situation is the newest `/situation` published before it started, with
  the actions published since (and after the newest `/world_reset`) replayed through
  the World: a depth-1 latched topic may skip states under load, the action stream
  (reliable, deep) does not;
- its command graph is the newest `/command_graph` before it started, its typed command
  the newest `/command`, and what a bag adds (`/episode`, keyed by the report's id) its
  split, example id and dataset fields;
- its observations (for the training cache) are the newest `/observation` before it
  started and one after each action; when any is missing (a recorder that lagged), the
  reader replays the states instead.

Pure Python, no rclpy: payloads are decoded by the reader's callbacks.
"""
from __future__ import annotations

import heapq
import json
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Iterator, NamedTuple

from gscan_ros import episode_status as es
from gscan_ros import interface
from gscan_ros.data.bag_format import LIVE_SPLIT
from gscan_ros.data.bag_metadata import EPISODE_FORMAT_VERSION
from gscan_ros.errors import DatasetFormatError, GscanError
from gscan_ros.world.types import Action, Situation

REORDER_WINDOW = 4096  # messages held back to restore publication order (a recorder logs in arrival order)
MAX_PENDING_RECORDS = 1024  # `/episode` records waiting for their episode (a bound, not a limit in practice)

LOSS = object()  # a marker in the message stream: data was lost here
# The stack's topics (relative names) that make episodes; anything else in a bag is context.
STACK_TOPICS = frozenset(
    e.name for e in interface.ENDPOINTS
    if e.kind == interface.TOPIC and e not in (interface.ATTENTION, interface.DIAGNOSTICS)
)


def stack_topic(topic: str, known: dict[str, str | None]) -> str | None:
    """The stack topic (relative name) a bag's `topic` is, or None for anything else;
    `known` maps the bag's topics seen so far to theirs. A stack in a namespace is found
    by its topics' suffix; the first namespace seen is the one read."""
    namespaces = {t[: -len(n) - 1] for t, n in known.items() if n is not None}
    for name in STACK_TOPICS:
        if topic == f"/{name}" or topic.endswith(f"/{name}"):
            namespace = topic[: -len(name) - 1]
            if not namespaces or namespace in namespaces:
                return name
    return None


def carries_records(topics: Iterable[str]) -> bool:
    """Whether a bag with these topics holds `/episode` records (our writers' bags do)."""
    return any(stack_topic(topic, {}) == interface.EPISODE.name for topic in topics)


class Message(NamedTuple):
    """One message of a bag, undecoded. A tuple, ordered by (publish time, position in the
    file): a bag has millions of them, compared in C."""

    publish_ns: int
    order: int  # its position in the file (breaks ties of equal publish times)
    topic: str  # relative to the stack's namespace: "action", "episode_status", ...
    data: bytes


def publication_order(items: Iterable[Message | object], window: int = REORDER_WINDOW) -> Iterator[Message | object]:
    """`items` in publish-time order, as far as a window of `window` messages can restore it
    (0: as they come, for a bag written in publication order); a LOSS marker flushes the
    window first (nothing is reordered across lost data)."""
    if window == 0:
        yield from items
        return
    heap: list[Message] = []
    for item in items:
        if item is LOSS:
            while heap:
                yield heapq.heappop(heap)
            yield LOSS
        elif len(heap) < window:
            heapq.heappush(heap, item)
        else:
            yield heapq.heappushpop(heap, item)
    while heap:
        yield heapq.heappop(heap)


@dataclass
class AssembledEpisode:
    """An ended episode, in the shape of a format-1 header (what the cache and `episode_from_header` take)."""

    header: dict
    actions: list[Action]
    graph_json: str | None
    observations: list[bytes] | None  # one per state, or None when some were not recorded
    outcome: str
    messages: int  # the bag's stack messages since the previous episode ended (its prologue included)


@dataclass
class _Open:
    report: es.EpisodeStatus
    situation: tuple[int, str] | None  # (publish ns, JSON) the episode started from, before `replay`
    replay: list[Action]
    graph_json: str | None
    command: str | None
    record: dict | None
    record_lost: bool  # data was lost before it started, and its `/episode` record may be in it
    observations: list[bytes] = field(default_factory=list)
    actions: list[Action] = field(default_factory=list)
    eos: bool = False


class EpisodeAssembler:
    """Feed a bag's messages in publication order (`feed`, `lose`); get ended episodes back.

    `decode_action`, `decode_status` and `decode_text` turn CDR bytes into an Action, an
    EpisodeStatus and a String's text; `keep_observations` keeps each episode's
    observation bytes; `records` says the bag holds `/episode` records (`carries_records`),
    so an episode that starts after lost data without one lost it there and is dropped,
    not read as a live one. Counts of what could not be assembled are kept in `dropped`
    (reason -> episodes) and `dropped_messages` (an episode's messages are those since the
    previous one ended); commands refused before any episode began (REJECTED reports
    without an ACTIVE one) in `rejected`.
    """

    def __init__(self, *, decode_action: Callable[[bytes], Action],
                 decode_status: Callable[[bytes], es.EpisodeStatus], decode_text: Callable[[bytes], str],
                 keep_observations: bool = False, records: bool = False) -> None:
        self._action = decode_action
        self._status = decode_status
        self._text = decode_text
        self._keep_observations = keep_observations
        self._has_records = records
        self._record_lost = False  # data was lost since the last ACTIVE report
        self._cut: str | None = None  # the id of the episode lost data cut last (its tail is no new loss)
        self._situation: tuple[int, bytes] | None = None
        self._since_situation: list[Action] = []  # world actions published after the newest situation
        self._graph: bytes | None = None
        self._command: bytes | None = None
        self._observation: bytes | None = None
        self._records: dict[str, dict] = {}
        self._open: _Open | None = None
        self.dropped: dict[str, int] = {}
        self.dropped_messages = 0
        self._span = 0  # messages since the last episode ended (or data was lost)
        self.rejected = 0

    # -- input -------------------------------------------------------------------------
    def feed(self, message: Message) -> AssembledEpisode | None:
        """Take one message; returns the episode it ends, if any."""
        topic, data = message.topic, message.data
        self._span += 1
        if topic == "action":
            action = self._action(data)
            if action is not Action.EOS:
                self._since_situation.append(action)
            if self._open is not None:
                if action is Action.EOS:
                    self._open.eos = True
                else:
                    self._open.actions.append(action)
        elif topic == "observation":
            self._observation = data
            if self._open is not None and self._keep_observations:
                self._open.observations.append(data)
        elif topic == "situation":
            self._situation, self._since_situation = (message.publish_ns, data), []
        elif topic == "world_reset":
            self._since_situation = []  # the world ignores what was sent before; its new state follows
        elif topic == "command_graph":
            self._graph = data
        elif topic == "command":
            self._command = data
        elif topic == "episode":
            self._take_record(data)
        elif topic == "episode_status":
            return self._report(self._status(data))
        return None

    def lose(self) -> None:
        """Data was lost here: the open episode cannot be completed (what was read of the next
        one's prologue is lost with it, and maybe its `/episode` record), and the world's state
        is unknown."""
        if self._open is None:
            self.dropped_messages += self._span
            self._span = 0
        else:
            self._cut = self._open.report.episode_id
        self._record_lost = self._has_records
        self._drop("cut by lost data")
        self._situation = self._graph = self._command = self._observation = None
        self._since_situation = []

    def finish(self) -> None:
        """The bag ended: an episode still open never reported its end."""
        self._drop("no end report (the recording stopped first)")

    # -- episodes ----------------------------------------------------------------------
    def _report(self, report: es.EpisodeStatus) -> AssembledEpisode | None:
        if report.outcome == es.ACTIVE:
            if self._open is not None:
                self._span -= 1  # this report starts the next one
                self._drop("a new episode started before it reported its end")
                self._span = 1
            self._open = _Open(
                report=report,
                situation=None if self._situation is None else (self._situation[0], self._situation[1]),
                replay=list(self._since_situation),
                graph_json=None if self._graph is None else self._text(self._graph),
                command=None if self._command is None else self._text(self._command),
                record=self._records.pop(report.episode_id, None),
                record_lost=self._record_lost,
                observations=[self._observation] if self._keep_observations and self._observation else [],
            )
            self._record_lost = False
            return None
        episode, self._open = self._open, None
        if episode is None or episode.report.episode_id != report.episode_id:
            if episode is not None:
                self._open = episode  # someone else's report (another policy): not this episode's end
            if report.outcome == es.REJECTED:
                self.rejected += 1  # a command refused before any episode began
            elif report.episode_id == self._cut:  # the end of the episode lost data cut (counted then)
                self.dropped_messages += self._span
                self._span = 0
            else:
                self._count_drop("its start was not recorded", self._span)
                self._span = 0
            return None
        done = self._assemble(episode, report.outcome, self._span)
        self._span = 0
        return done

    def _assemble(self, episode: _Open, outcome: str, messages: int) -> AssembledEpisode | None:
        if episode.situation is None:
            self._count_drop("no situation before it started", messages)
            return None
        if episode.record is None and episode.record_lost:
            self._count_drop("its /episode record was lost", messages)
            return None
        if outcome in (es.COMPLETE, es.CUT) and not episode.eos:
            self._count_drop("it ended without its <eos>", messages)
            return None
        situation = self._initial_situation(episode)
        record = episode.record or {}
        graph = _graph_fields(episode.graph_json)
        command = record.get("command") or graph.get("command") or episode.command
        if command is None:
            self._count_drop("no command or command graph before it started", messages)
            return None
        meta = dict(record.get("meta") or {})
        if record:
            episode_id = record.get("episode_id", episode.report.episode_id)
        else:  # a live episode: what the policy followed, and what was typed
            episode_id = episode.report.episode_id
        if "episode_id" not in record:
            if "parser" in graph:
                meta.setdefault("parser", graph["parser"])
            if episode.command is not None and episode.command != command:
                meta.setdefault("typed_command", episode.command)
        header = {
            "version": EPISODE_FORMAT_VERSION,
            "episode_id": episode_id,
            "split": record.get("split", LIVE_SPLIT),
            "example_id": record.get("example_id"),
            "command": command,
            "situation": situation,
            "meta": meta,
        }
        if outcome != es.COMPLETE:
            header["outcome"] = outcome
        states = len(episode.actions) + 1
        observations = episode.observations if len(episode.observations) == states else None
        return AssembledEpisode(header, episode.actions, episode.graph_json,
                                observations if self._keep_observations else None, outcome, messages)

    def _initial_situation(self, episode: _Open) -> dict:
        """The situation JSON the episode started from (replaying what the newest one missed)."""
        _, data = episode.situation
        try:
            fields = json.loads(self._text(data))
        except json.JSONDecodeError as exc:
            where = f"episode {episode.report.episode_id}"
            raise DatasetFormatError(f"{where}: situation is not JSON ({exc.msg})") from None
        if not episode.replay:
            return fields
        from gscan_ros.world.world import World

        world = World(Situation.from_json(fields))
        for action in episode.replay:
            try:
                world.step(action)
            except GscanError:
                continue  # the world rejected it too and stayed where it was
        return world.snapshot().to_json()

    def _take_record(self, data: bytes) -> None:
        try:
            record = json.loads(self._text(data))
        except json.JSONDecodeError as exc:
            raise DatasetFormatError(f"/episode record is not JSON ({exc.msg})") from None
        if not isinstance(record, dict) or not isinstance(record.get("id"), str):
            raise DatasetFormatError("/episode record must be a JSON object with a string 'id'")
        version = record.get("version")
        if not isinstance(version, int) or version > EPISODE_FORMAT_VERSION:
            raise DatasetFormatError(f"/episode record version {version!r} is not supported")
        self._has_records = True
        if self._open is not None and self._open.report.episode_id == record["id"]:
            self._open.record = record  # a recorder writes it once it has seen the episode start
            return
        if len(self._records) >= MAX_PENDING_RECORDS:
            self._records.pop(next(iter(self._records)))
        self._records[record["id"]] = record

    def _drop(self, reason: str) -> None:
        if self._open is not None:
            self._count_drop(reason, self._span)
            self._open, self._span = None, 0

    def _count_drop(self, reason: str, messages: int) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + 1
        self.dropped_messages += messages


def _graph_fields(graph_json: str | None) -> dict[str, str]:
    """The command and parser a CommandGraph JSON names ({} without a readable graph)."""
    try:
        value: Any = json.loads(graph_json) if graph_json else {}
    except json.JSONDecodeError:
        return {}
    if not isinstance(value, dict):
        return {}
    return {k: value[k] for k in ("command", "parser") if isinstance(value.get(k), str)}
