"""Cut the stack's live topics into episodes: the rule every format-2 bag is read with.

A bag of the live topics (our generator's, our recorder's, or any all-topics recorder's
such as `ros2 bag record -a`) is read in publication order (the MCAP publish time, the
DDS source timestamp), and episodes are what the policy reports (docs/bags.md):

- an episode runs from the policy's ACTIVE report on `/episode_status` to its report of
  how it ended; its actions are the `/action` messages published in between (the policy
  publishes ACTIVE before its first action and the end after its last), so a preempted
  episode's last action never leaks into the next one. An end report that comes before
  any ACTIVE report and any lost data closes an episode that was running when the
  recording began: what came before it is the bag's prologue, not lost data;
- its initial situation is the newest `/situation` published before it started, with
  the actions published since (and after the newest `/world_reset`) replayed through
  the World: a depth-1 latched topic may skip states under load, the action stream
  (reliable, deep) does not;
- its command graph is the newest `/command_graph` before it started of the command its
  ACTIVE report names (two commands sent within milliseconds both reach the recorder
  before the first one's ACTIVE report; a stack whose reports name no command: the
  newest graph), its typed command the newest `/command` when that graph is the newest;
  in a bag without `/command_graph`, its command is the one its ACTIVE report names (a
  newer `/command` may be the one that preempted it); and what a bag adds (`/episode`,
  keyed by the report's id) its split, example id and dataset fields;
- its observations (for the training cache) follow the lock-step protocol: the state it
  acts on first is the newest `/observation` before its first action (the reply to a
  preempted episode's last action may come after the next ACTIVE report), and each
  action's state is the first `/observation` after it, before the next action. When one
  is missing (a recorder that lagged) or an action has two (a reset), the reader replays
  the states instead;
- a `/world_reset` ends what is known of the world: an episode that starts before the
  new world's `/situation` is read has no situation and is dropped.

A bag's stacks are found by their topics' names and types (`StackTopics`): each
namespace ('' at the root) whose topics include `/episode_status`, `/action` and
`/situation` of the stack's types holds one, and every stack of a bag is read, each on
its own (a fleet recorded with `ros2 bag record -a`); a topic of the same name from
another node (`/battery/status`) is context. A message that cannot be read (a bad
`/action` token, `/situation` or `/episode` that is not JSON, an `/episode_status` code
the policy never sends) is a *bad message* (`StackDecoder`): the episode it belongs to
is dropped with the reason, and the rest of the bag is read.

Pure Python, no rclpy: payloads are decoded by the reader's callbacks.
"""
from __future__ import annotations

import heapq
import json
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Iterator, NamedTuple

from gscan_ros import episode_status as es
from gscan_ros.data.bag_format import LIVE_SPLIT
from gscan_ros.data.bag_metadata import EPISODE_FORMAT_VERSION
from gscan_ros.data.bag_schema import ACTION, EPISODE, EPISODE_STATUS, SITUATION, TOPICS, TopicSpec
from gscan_ros.errors import DatasetFormatError, GscanError
from gscan_ros.world.types import Action, Situation

REORDER_WINDOW = 4096  # messages held back to restore publication order (a recorder logs in arrival order)
MAX_PENDING_RECORDS = 1024  # `/episode` records waiting for their episode (a bound, not a limit in practice)
RECENT_GRAPHS = 64  # command graphs an ACTIVE report's command is looked up in (commands queued at the policy)

LOSS = object()  # a marker in the message stream: data was lost here
RECORDING_STOPPED = "the recording stopped"  # why an episode still running when its bag closed ended
# The stack's topics (relative name -> spec, with the types it carries); anything else in a bag is context.
STACK_TOPICS: dict[str, TopicSpec] = {spec.name.lstrip("/"): spec for spec in TOPICS.values()}
# What a namespace carries when it holds a stack: the topics an episode is assembled from.
CORE_TOPICS = frozenset(spec.name.lstrip("/") for spec in (EPISODE_STATUS, ACTION, SITUATION))


def stack_topic(topic: str, msg_type: str | None) -> tuple[str, str] | None:
    """(namespace, relative name) when a bag's `topic` of `msg_type` is named and typed as
    one of the stack's topics ('' for the root namespace), else None."""
    for name, spec in STACK_TOPICS.items():
        if (topic == f"/{name}" or topic.endswith(f"/{name}")) and msg_type is not None and spec.carries(msg_type):
            return topic[: -len(name) - 1], name
    return None


class StackTopics:
    """The stacks of a bag: its topics classified by `stack_topic`, from metadata.yaml's
    list and the channels as they are read (a killed recorder's metadata lacks some), and
    the namespaces that hold a stack (their topics include CORE_TOPICS)."""

    def __init__(self, topics: Iterable[tuple[str, str]]):
        self._topics: dict[tuple[str, str | None], tuple[str, str] | None] = {}
        self._names: dict[str, set[str]] = {}
        for topic, msg_type in topics:
            self.classify(topic, msg_type)

    def classify(self, topic: str, msg_type: str | None) -> tuple[str, str] | None:
        """(namespace, relative name) of a stack topic, None for context: by name and type, so
        another node's topic of a stack topic's name (even on the same name) stays context."""
        key = (topic, msg_type)
        if key not in self._topics:
            found = self._topics[key] = stack_topic(topic, msg_type)
            if found is not None:
                self._names.setdefault(found[0], set()).add(found[1])
        return self._topics[key]

    def is_stack(self, namespace: str) -> bool:
        return CORE_TOPICS <= self._names.get(namespace, set())

    def missing_core(self) -> list[str]:
        """When no namespace holds a stack: the topics (with their types) that the one closest
        to a stack lacks, so a bag recorded without them is told what to record."""
        if any(self.is_stack(ns) for ns in self._names):
            return []
        namespace = max(self._names, key=lambda ns: len(CORE_TOPICS & self._names[ns]), default="")
        return [f"{namespace}/{name} ({STACK_TOPICS[name].msg_type})"
                for name in sorted(CORE_TOPICS - self._names.get(namespace, set()))]

    def carries_records(self, namespace: str) -> bool:
        """Whether the stack in `namespace` has `/episode` records (our writers' bags do)."""
        return EPISODE.name.lstrip("/") in self._names.get(namespace, set())


class Message(NamedTuple):
    """One message of a bag, undecoded. A tuple, ordered by (publish time, position in the
    file): a bag has millions of them, compared in C."""

    publish_ns: int
    order: int  # its position in the file (breaks ties of equal publish times)
    namespace: str  # of its stack ('' at the root)
    topic: str  # relative to the stack's namespace: "action", "episode_status", ...
    data: bytes


def publication_order(items: Iterable[Message | object], window: int = REORDER_WINDOW,
                      on_late: Callable[[Message], None] | None = None) -> Iterator[Message | object]:
    """`items` in publish-time order, as far as a window of `window` messages can restore it
    (0: as they come, for a bag written in publication order); a LOSS marker flushes the
    window first (nothing is reordered across lost data). A message that comes out older
    than one already passed was logged further from its place than the window reaches: it
    goes to `on_late` and a LOSS marker takes its place, so the episode it would have
    joined is dropped, not given a message of another."""
    newest = None
    for item in _reordered(items, window):
        if item is not LOSS and newest is not None and item.publish_ns < newest:
            if on_late is not None:
                on_late(item)
            yield LOSS
            continue
        if item is not LOSS:
            newest = item.publish_ns
        yield item


def _reordered(items: Iterable[Message | object], window: int) -> Iterator[Message | object]:
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


def without_duplicates(items: Iterable[Message | object],
                       on_duplicate: Callable[[Message], None]) -> Iterator[Message | object]:
    """`items` (in publication order) without a message equal to one already passed at the
    same publish time: the same stack topic and the same bytes. DDS stamps each sample of a
    publisher with its own time, so two equal ones are one sample written twice (a bag
    merged with itself, a recorder that logged a sample twice); the second would add an
    action to a demonstration."""
    seen: set[tuple[str, str, bytes]] = set()
    now = None
    for item in items:
        if item is LOSS:
            seen.clear()
            now = None
        elif item.publish_ns != now:
            now = item.publish_ns
            seen = {(item.namespace, item.topic, item.data)}
        elif (item.namespace, item.topic, item.data) in seen:
            on_duplicate(item)
            continue
        else:
            seen.add((item.namespace, item.topic, item.data))
        yield item


class StackDecoder:
    """What a stack message holds, by topic: an Action, an EpisodeStatus, an `/episode`
    record (a dict), a situation (a JSON object), a command's or a graph's text, an
    observation (the grid array); other topics pass undecoded. A message that cannot be
    read raises a GscanError: it is a bad message. The one rule of the reader (so of
    `verify` and the training cache alike) and of `bag repair`, so that a repaired bag
    holds no message its reader would refuse.

    `decode_action`, `decode_status`, `decode_text` and `decode_observation` turn CDR bytes
    into an Action, an EpisodeStatus, a String's text and a uint8[row, col, channel] grid;
    `check_graph` raises for text that is no CommandGraph.
    """

    def __init__(self, *, decode_action: Callable[[bytes], Action], decode_status: Callable[[bytes], es.EpisodeStatus],
                 decode_text: Callable[[bytes], str], check_graph: Callable[[str], Any],
                 decode_observation: Callable[[bytes], Any]) -> None:
        self._action = decode_action
        self._status = decode_status
        self._text = decode_text
        self._check_graph = check_graph
        self._observation = decode_observation
        self._actions: dict[bytes, Action] = {}  # the CDR bytes of the few action tokens

    def __call__(self, topic: str, data: bytes) -> Any:
        if topic == "action":
            action = self._actions.get(data)
            if action is None:
                action = self._actions[bytes(data)] = self._action(data)
            return action
        if topic == "episode_status":
            return self._status(data)
        if topic == "observation":
            return self._observation(data)
        if topic not in ("command", "command_graph", "situation", "episode"):
            return data
        text = self._text(data)
        if topic == "command_graph":
            self._check_graph(text)
        elif topic == "situation":
            return _json_object(text, "situation")
        elif topic == "episode":
            return _episode_record(text)
        return text


def _json_object(text: str, what: str) -> dict:
    try:
        value = json.loads(text)
    except ValueError as exc:  # JSONDecodeError, or an integer beyond Python's digit limit
        raise DatasetFormatError(f"{what} is not JSON ({exc})") from None
    if not isinstance(value, dict):
        raise DatasetFormatError(f"{what} is not a JSON object")
    return value


def _episode_record(text: str) -> dict:
    """An `/episode` record: a JSON object with a string `id`, of a supported version."""
    record = _json_object(text, "/episode record")
    if not isinstance(record.get("id"), str):
        raise DatasetFormatError("/episode record must be a JSON object with a string 'id'")
    version = record.get("version")
    if not isinstance(version, int) or version > EPISODE_FORMAT_VERSION:
        raise DatasetFormatError(f"/episode record version {version!r} is not supported")
    return record


@dataclass
class AssembledEpisode:
    """An ended episode, in the shape of a format-1 header (what the cache and `episode_from_header` take)."""

    header: dict
    actions: list[Action]
    graph_json: str | None
    observations: list | None  # one decoded state per state, or None when some were not recorded
    outcome: str
    messages: int  # the bag's stack messages since the previous episode ended (its prologue included)
    status: es.EpisodeStatus  # its end report (id and start stamp: where the bag holds it)


@dataclass(frozen=True)
class _Unreadable:
    """A bad message where a newer one replaces the older (`/situation`, `/command`,
    `/command_graph`): the episode that would start from it is dropped for `reason`."""

    reason: str


@dataclass
class _Open:
    report: es.EpisodeStatus
    situation: tuple[int, dict] | None  # (publish ns, JSON) the episode started from, before `replay`
    replay: list[Action]
    graph_json: str | None
    command: str | None
    record: dict | None
    record_lost: str | None  # why its `/episode` record may be missing (lost data, a bad record)
    damage: str | None = None  # a bad message of its own: it is dropped for this reason
    observations: list = field(default_factory=list)  # the state before each action, then the last (decoded)
    aligned: bool = True  # False: some action lacks its one reply, so `observations` cannot be trusted
    actions: list[Action] = field(default_factory=list)
    eos: bool = False
    awaiting_reply: bool = False  # an action was published and its state has not come yet

    def act(self, action: Action) -> None:
        if self.awaiting_reply:
            self.aligned = False  # the reply to the previous action was not recorded
        self.actions.append(action)
        self.awaiting_reply = True

    def observe(self, observation: Any) -> None:
        """Take a state of the world by the lock-step protocol (docs/ros.md)."""
        if not self.actions:  # the policy acts first on the newest state (maybe a reply that came after ACTIVE)
            self.observations[:] = [observation]
        elif self.awaiting_reply:
            self.observations.append(observation)
            self.awaiting_reply = False
        else:
            self.aligned = False  # a second state for one action: not a reply (a reset)


class EpisodeAssembler:
    """Feed one stack's messages in publication order (`feed`, `lose`); get ended episodes back.

    `decode` is a `StackDecoder`; `keep_observations` keeps each episode's observation
    bytes; `records` says the stack has `/episode` records (`StackTopics.carries_records`),
    so an episode that starts after lost data without one lost it there and is dropped,
    not read as a live one. Counts of what could not be assembled are kept in `dropped`
    (reason -> episodes), `dropped_messages` (an episode's messages are those since the
    previous one ended) and `dropped_keys` ((report id, start stamp) of each); commands
    refused before any episode began (REJECTED reports without an ACTIVE one) in
    `rejected`; bad messages in `bad_messages`, the first described in `first_bad`.
    """

    def __init__(self, *, decode: Callable[[str, bytes], Any], keep_observations: bool = False,
                 records: bool = False) -> None:
        self._decode = decode
        self._keep_observations = keep_observations
        self._has_records = records
        self._record_lost: str | None = None  # why a record may be missing since the last ACTIVE report
        self._prologue = True  # neither an ACTIVE report nor lost data yet: the recording may have begun mid-episode
        self._cut: str | None = None  # the id of the episode lost data cut last (its tail is no new loss)
        self._status_damage: str | None = None  # a bad report since the last ACTIVE one (maybe an episode's start)
        self._situation: tuple[int, dict] | _Unreadable | None = None
        self._since_situation: list[Action] = []  # world actions published after the newest situation
        self._graph: str | _Unreadable | None = None
        self._graphs: deque[str | _Unreadable] = deque(maxlen=RECENT_GRAPHS)  # the newest last
        self._command: str | _Unreadable | None = None
        self._observation: Any = None  # the newest state, decoded
        self._records: dict[str, dict] = {}
        self._open: _Open | None = None
        self.dropped: dict[str, int] = {}
        self.dropped_messages = 0
        self.dropped_keys: set[tuple[str, int]] = set()
        self._span = 0  # messages since the last episode ended (or data was lost)
        self.rejected = 0
        self.bad_messages = 0
        self.first_bad: str | None = None

    # -- input -------------------------------------------------------------------------
    def feed(self, message: Message) -> AssembledEpisode | None:
        """Take one message; returns the episode it ends, if any."""
        topic = message.topic
        self._span += 1
        try:
            value = self._decode(topic, message.data)
        except GscanError as exc:
            self._bad(message, str(exc))
            return None
        if topic == "action":
            if value is not Action.EOS:
                self._since_situation.append(value)
            if self._open is not None:
                if value is Action.EOS:
                    self._open.eos = True
                else:
                    self._open.act(value)
        elif topic == "observation":
            self._observation = value
            if self._open is not None and self._keep_observations:
                self._open.observe(value)
        elif topic == "situation":
            self._situation, self._since_situation = (message.publish_ns, value), []
        elif topic == "world_reset":
            # The world ignores what was sent before, and the old world's state is no start
            # for the next episode: its new situation and observation follow.
            self._situation = self._observation = None
            self._since_situation = []
            if self._open is not None:
                self._open.aligned = False
        elif topic == "command_graph":
            self._graph = value
            self._graphs.append(value)
        elif topic == "command":
            self._command = value
        elif topic == "episode":
            self._take_record(value)
        elif topic == "episode_status":
            return self._report(value)
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
        self._prologue = False
        if self._has_records:
            self._record_lost = "its /episode record was lost"
        self._drop("cut by lost data")
        self._situation = self._graph = self._command = self._observation = None
        self._graphs.clear()
        self._since_situation = []

    def finish(self, *, closed: bool) -> AssembledEpisode | None:
        """The bag ended. An episode still open never reported its end: when the bag was
        `closed` (its recorder stopped, as `ros2 bag record` does on Ctrl-C) it ended there,
        and is returned PREEMPTED, as our recorder reports it; in a bag whose writer died
        what followed may be lost, so it is dropped."""
        if self._open is None:
            return None
        if not closed:
            self._drop("no end report (the recording stopped first)")
            return None
        episode, self._open = self._open, None
        report = es.EpisodeStatus(episode.report.episode_id, episode.report.start_ns, es.PREEMPTED,
                                  f"{episode.report.text!r}: {RECORDING_STOPPED}")
        done = self._assemble(episode, report, self._span)
        self._span = 0
        return done

    def discard(self, episode: AssembledEpisode, reason: str) -> None:
        """An episode it ended that the reader could not build after all: dropped for `reason`."""
        self._count_drop(reason, episode.messages, episode.status)

    # -- bad messages ------------------------------------------------------------------
    def _bad(self, message: Message, detail: str) -> None:
        """A message that cannot be read: counted (lost) on its own, and the episode it
        belongs to is dropped: the open one for an action or a report; the next to start
        for a situation, command or graph (the newest before an ACTIVE report is its own);
        for a record, the open episode if it has none yet, else the next without one."""
        self._span -= 1
        self.dropped_messages += 1
        self.bad_messages += 1
        if self.first_bad is None:
            self.first_bad = f"/{message.topic} at {message.publish_ns} ns: {detail}"
        reason = f"a bad /{message.topic} message"
        topic, episode = message.topic, self._open
        if topic == "observation":
            self._observation = None  # the world's state is not known from it (the world replays it)
        if topic == "situation":
            self._situation, self._since_situation = _Unreadable(reason), []
        elif topic == "command_graph":
            self._graph = _Unreadable(reason)
            self._graphs.append(self._graph)
        elif topic == "command":
            self._command = _Unreadable(reason)
        elif topic == "episode" and (episode is None or episode.record is not None):
            self._record_lost = reason
        elif episode is not None:
            episode.damage = episode.damage or reason
        elif topic == "episode_status":
            self._status_damage = reason  # maybe the ACTIVE report of the episode whose end comes next

    # -- episodes ----------------------------------------------------------------------
    def _report(self, report: es.EpisodeStatus) -> AssembledEpisode | None:
        if report.outcome == es.ACTIVE:
            self._prologue = False
            self._status_damage = None
            if self._open is not None:
                self._span -= 1  # this report starts the next one
                self._drop("a new episode started before it reported its end")
                self._span = 1
            graph = self._graph_of(report.text)
            # The newest command made the newest graph; with no graph recorded, the newest
            # command may be one typed after this episode's (the ACTIVE report names the one taken).
            typed = self._command if graph is self._graph and (graph is not None or not report.text) else None
            prologue = [v for v in (self._situation, graph, typed) if isinstance(v, _Unreadable)]
            self._open = _Open(
                report=report,
                situation=None if isinstance(self._situation, _Unreadable) else self._situation,
                replay=list(self._since_situation),
                graph_json=None if isinstance(graph, _Unreadable) else graph,
                command=None if isinstance(typed, _Unreadable) else typed,
                record=self._records.pop(report.episode_id, None),
                record_lost=self._record_lost,
                damage=prologue[0].reason if prologue else None,
                observations=[self._observation] if self._keep_observations and self._observation is not None else [],
            )
            self._record_lost = None
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
            elif self._status_damage is not None:  # the end of an episode whose ACTIVE report was bad
                self._count_drop(self._status_damage, self._span, report)
                self._span = 0
            elif self._prologue:  # the end of an episode that ran when the recording began
                self._span = 0
            else:
                self._count_drop("its start was not recorded", self._span, report)
                self._span = 0
            return None
        done = self._assemble(episode, report, self._span)
        self._span = 0
        return done

    def _assemble(self, episode: _Open, report: es.EpisodeStatus, messages: int) -> AssembledEpisode | None:
        reason = self._unusable(episode, report.outcome)
        situation = None
        if reason is None:
            try:
                situation = self._initial_situation(episode)
            except GscanError:
                reason = "its /situation is no gSCAN situation"
        record = episode.record or {}
        graph = _graph_fields(episode.graph_json)
        command = record.get("command") or graph.get("command") or episode.report.text or episode.command
        if reason is None and command is None:
            reason = "no command or command graph before it started"
        if reason is not None:
            self._count_drop(reason, messages, report)
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
        if report.outcome != es.COMPLETE:
            header["outcome"] = report.outcome
        states = len(episode.actions) + 1
        observations = episode.observations if episode.aligned and len(episode.observations) == states else None
        return AssembledEpisode(header, episode.actions, episode.graph_json,
                                observations if self._keep_observations else None, report.outcome, messages,
                                report)

    def _graph_of(self, command: str) -> str | _Unreadable | None:
        """The newest graph of `command` (the policy's ACTIVE report names the command it
        took), else the newest graph."""
        for graph in reversed(self._graphs):
            if not isinstance(graph, _Unreadable) and command and _graph_fields(graph).get("command") == command:
                return graph
        return self._graph

    @staticmethod
    def _unusable(episode: _Open, outcome: str) -> str | None:
        """Why an ended episode cannot be assembled from what it holds (None: it can)."""
        if episode.damage is not None:
            return episode.damage
        if episode.situation is None:
            return "no situation before it started"
        if episode.record is None and episode.record_lost is not None:
            return episode.record_lost
        if outcome in (es.COMPLETE, es.CUT) and not episode.eos:
            return "it ended without its <eos>"
        return None

    def _initial_situation(self, episode: _Open) -> dict:
        """The situation JSON the episode started from (replaying what the newest one missed)."""
        _, fields = episode.situation
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

    def _take_record(self, record: dict) -> None:
        self._has_records = True
        if self._open is not None and self._open.report.episode_id == record["id"]:
            self._open.record = record  # a recorder writes it once it has seen the episode start
            return
        if len(self._records) >= MAX_PENDING_RECORDS:
            self._records.pop(next(iter(self._records)))
        self._records[record["id"]] = record

    def _drop(self, reason: str) -> None:
        if self._open is not None:
            self._count_drop(self._open.damage or reason, self._span, self._open.report)
            self._open, self._span = None, 0

    def _count_drop(self, reason: str, messages: int, report: es.EpisodeStatus) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + 1
        self.dropped_messages += messages
        self.dropped_keys.add((report.episode_id, report.start_ns))


def _graph_fields(graph_json: str | None) -> dict[str, str]:
    """The command and parser a CommandGraph JSON names ({} without a readable graph)."""
    try:
        value: Any = json.loads(graph_json) if graph_json else {}
    except json.JSONDecodeError:
        return {}
    if not isinstance(value, dict):
        return {}
    return {k: value[k] for k in ("command", "parser") if isinstance(value.get(k), str)}
