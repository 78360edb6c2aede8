"""Reading bags back as Episodes (`BagEpisodeReader`, `iter_bag_episodes`).

Streams each MCAP file through `McapScan`, so a truncated or damaged bag yields every
complete episode it still holds; an episode cut by lost data is dropped and counted in
the reader's `BagReadReport`, never assembled from the pieces around the damage.
Format-2 bags (the live topics: ours, or any all-topics recording of one or more
stacks) are cut into episodes by `episode_assembly`, each stack on its own; a bad
message costs the episode it belongs to. Format-1 bags are cut by their `/command` headers.
"""
from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

from gscan_ros import episode_status as es
from gscan_ros import interface
from gscan_ros.data.bag_format import LEGACY_EPISODE_TOPICS, GraphCache, episode_from_header
from gscan_ros.data.bag_metadata import LEGACY_FORMAT_VERSION, read_bag_info
from gscan_ros.data.bag_report import BagReadReport
from gscan_ros.data.bag_scan import LOSS, McapScan
from gscan_ros.data.bag_schema import ACTION, COMMAND, COMMAND_GRAPH, OBSERVATION
from gscan_ros.data.episode import Episode
from gscan_ros.data.episode_assembly import LOSS as STREAM_LOSS
from gscan_ros.data.episode_assembly import (
    REORDER_WINDOW,
    AssembledEpisode,
    EpisodeAssembler,
    Message,
    StackDecoder,
    StackTopics,
    publication_order,
    without_duplicates,
)
from gscan_ros.errors import DatasetFormatError, GscanError
from gscan_ros.world.types import Action
from msg_adapters import ObservationDecoder, cdr_to_action, cdr_to_episode_status, cdr_to_text

# Losses are logged under the bag API's name (docs/bags.md), whichever module reads.
log = logging.getLogger("gscan_ros.data.bag")


class _Unusable(Exception):
    """An assembled episode a message of which cannot be read: dropped, with this reason."""


@dataclass(frozen=True)
class RecordedEpisode:
    """An episode as recorded: the Episode, its observations (if decoded) and graph JSON."""

    episode: Episode
    header: dict
    states: np.ndarray | None  # uint8[T+1, G, G, 16]
    graph_json: str | None
    outcome: str = es.COMPLETE


@dataclass
class _OpenEpisode:
    header: dict | None  # None: a `/command` without a JSON header (plain-text live command)
    selected: bool
    messages: int = 1
    actions: list = field(default_factory=list)
    observations: list = field(default_factory=list)
    observation_count: int = 0
    graph_json: str | None = None
    outcome: str = es.COMPLETE  # header "outcome" (format 1 knew "aborted" only)
    damage: str | None = None  # a bad message of its own: it is dropped for this reason
    index: int = -1  # its `/command`'s place among the bag's `/command` messages


class BagEpisodeReader(Iterator[Episode]):
    """Streaming reader: iterate it for Episodes; `report` describes what was recovered.

    Reads each MCAP file front to back (`McapScan`), without its summary, so a bag whose
    writer was killed (no summary, torn last chunk) still yields every complete episode,
    and a damaged chunk costs only the episodes that had messages in it: reading goes on
    at the next intact chunk, and an episode cut by lost data is dropped (counted in the
    report), never assembled from the pieces around the damage. A storage file that is
    missing (`BagInfo.missing`) is lost data at its place in the file order, recorded in
    `report.missing_files`. A file that is not MCAP raises one DatasetFormatError naming the file.
    """

    def __init__(
        self,
        bag_dir: str | os.PathLike,
        splits: Iterable[str] | None = None,
        *,
        decode_states: bool = False,
        log_losses: bool = True,
        include_incomplete: bool = False,
    ):
        self.info = read_bag_info(bag_dir)
        for warning in self.info.warnings:
            log.warning(warning)
        self.splits = None if splits is None else frozenset(splits)
        self.decode_states = decode_states
        self.include_incomplete = include_incomplete  # also yield cut, preempted and rejected episodes
        self.log_losses = log_losses  # log report.summary() as a warning when something was lost
        self.report = BagReadReport(
            self.info.path,
            expected_messages=self.info.message_count if self.info.closed else None,
            expected_episodes=self.info.episodes,
        )
        self._episodes = (r.episode for r in self.records())
        self._decode_observation: ObservationDecoder | None = None  # for the type of the bag's `/observation`
        self.stacks = StackTopics((t.name, t.msg_type) for t in self.info.entries)
        self.dropped_keys: set[tuple[str, str, int]] = set()  # format 2: (namespace, report id, start)
        self.dropped_commands: set[int] = set()  # format 1: the n-th `/command`s whose complete episode was dropped
        self._commands = 0

    def __next__(self) -> Episode:
        return next(self._episodes)

    def records(self) -> Iterator[RecordedEpisode]:
        """Complete episodes in bag order (with observations when `decode_states`), and
        those that ended otherwise when `include_incomplete`."""
        if self.info.format_version == LEGACY_FORMAT_VERSION:
            yield from self._legacy_records()
        else:
            yield from self._live_records()
        self.report.finished = True
        if self.log_losses and not self.report.complete:
            log.warning(self.report.summary())

    # -- format 2: the live topics --------------------------------------------------------
    def _live_records(self) -> Iterator[RecordedEpisode]:
        graphs = GraphCache()
        decode = live_decoder(graphs, self.observation)
        assemblers: dict[str, EpisodeAssembler] = {}  # one per stack namespace
        lost = False
        window = 0 if self.info.publish_ordered else REORDER_WINDOW
        ordered = publication_order(self._live_messages(), window, self.report.count_late)
        for item in without_duplicates(ordered, self.report.count_duplicate):
            if item is STREAM_LOSS:
                lost = True
                for assembler in assemblers.values():
                    assembler.lose()
                continue
            assembler = assemblers.get(item.namespace)
            if assembler is None:
                assembler = assemblers[item.namespace] = EpisodeAssembler(
                    decode=decode, keep_observations=self.decode_states,
                    records=self.stacks.carries_records(item.namespace))
                if lost:  # its stack lost data before its first message
                    assembler.lose()
            yield from self._ended(assembler, assembler.feed(item), item.namespace, graphs)
        # A bag its recorder closed ends the episodes still running there (a third-party
        # recorder writes no end report for them); in one whose writer died, data may be lost.
        closed = self.info.closed and not self.report.truncated_files
        self.report.missing_topics = self.stacks.missing_core()
        for namespace, assembler in assemblers.items():
            yield from self._ended(assembler, assembler.finish(closed=closed), namespace, graphs)
            if not self.stacks.is_stack(namespace):
                continue  # another node's topics that share a stack topic's name and type
            for _ in range(assembler.rejected):
                self.report.count_refused()
            self.report.discarded_messages += assembler.dropped_messages
            for reason, count in assembler.dropped.items():
                self.report.count_drop(reason, count)
            self.report.bad_messages += assembler.bad_messages
            self.report.first_bad_message = self.report.first_bad_message or assembler.first_bad
            self.dropped_keys.update((namespace, *key) for key in assembler.dropped_keys)

    def _ended(self, assembler: EpisodeAssembler, done: AssembledEpisode | None, namespace: str,
               graphs: GraphCache) -> Iterator[RecordedEpisode]:
        """Count the episode the assembler just ended (if any), and yield it when wanted."""
        if done is None or not self.stacks.is_stack(namespace):
            return
        wanted = ((done.outcome == es.COMPLETE or self.include_incomplete)
                  and (self.splits is None or done.header["split"] in self.splits))
        try:
            record = self._assembled(self.info.path, done, graphs) if wanted else None
        except _Unusable as exc:  # it costs the episode, not the bag
            assembler.discard(done, str(exc))
            return
        if done.outcome == es.COMPLETE:
            self.report.episodes_read += 1
        else:
            self.report.count_outcome(done.outcome, taken=record is not None)
        if record is not None:
            self.report.count_grid_size(record.episode.situation.grid_size)
            yield record

    def _assembled(self, path: Path, done: AssembledEpisode, graphs: GraphCache) -> RecordedEpisode:
        """The episode `done` as read; `_Unusable` when a message it needs cannot be."""
        where = f"{path}: episode {done.header['episode_id']}"
        try:
            episode = episode_from_header(done.header, done.actions, str(path))
        except GscanError:
            raise _Unusable("its /situation is no gSCAN situation") from None
        graphs.attach(episode, done.graph_json, where)
        states = None
        if self.decode_states:
            # A recorder that lagged may lack some states: they are the world's, so replay them.
            states = np.stack(done.observations or episode.states())
        return RecordedEpisode(episode, done.header, states, done.graph_json, done.outcome)

    def _live_messages(self) -> Iterator[Message | object]:
        """The stacks' messages (topics relative to their namespace), and LOSS where data was lost."""
        channels: dict[tuple[Path, int], tuple[str, str] | None] = {}
        order = 0
        for scan, item in self._scan():
            if item is LOSS:
                yield STREAM_LOSS
                continue
            channel = item[0]
            self.report.messages_read += 1
            order += 1
            key = (scan.path, channel.id)
            if key not in channels:
                found = channels[key] = self.stacks.classify(channel.topic, scan.msg_type(channel))
                if found is not None and found[1] == interface.OBSERVATION.name:
                    self._observation_type(scan, channel)
            found = channels[key]
            if found is not None:
                yield Message(item[3], order, found[0], found[1], item[4])

    # -- format 1: `/command` headers ------------------------------------------------------
    def _legacy_records(self) -> Iterator[RecordedEpisode]:
        action_cache: dict[bytes, Action] = {}  # CDR bytes of the 7 action tokens
        graphs = GraphCache()
        current: _OpenEpisode | None = None
        for item in self._messages():
            if item is LOSS:  # data lost here: the open episode cannot be completed
                self._drop(current, "cut by lost data")
                current = None
                continue
            path, topic, data = item
            self.report.messages_read += 1
            if topic == COMMAND.name:
                self._drop(current, "a new episode started before its <eos>")
                current = self._start(path, data)
                continue
            if current is None:  # between episodes: only episode topics count as lost data
                self.report.discarded_messages += topic in LEGACY_EPISODE_TOPICS
                continue
            current.messages += 1
            if topic == OBSERVATION.name:
                try:  # read whether kept or not, so that `verify` and the cache drop the same episodes
                    observation = self.observation(data)
                except GscanError as exc:
                    self._bad(current, topic, str(exc))
                    continue
                current.observation_count += 1
                if self.decode_states and current.selected:
                    current.observations.append(observation)
            elif topic == ACTION.name:
                action = action_cache.get(data)
                if action is None:
                    try:
                        action = action_cache[bytes(data)] = cdr_to_action(data)
                    except GscanError as exc:
                        self._bad(current, topic, str(exc))
                        continue
                if action is not Action.EOS:
                    current.actions.append(action)
                    continue
                done, current = current, None
                if done.header is None:  # a command typed as plain text: no situation to follow it from
                    self._drop(done, "a /command with no episode header", ended=True)
                    continue
                if done.damage is not None:
                    self._drop(done, ended=True)
                    continue
                wanted = done.selected and (done.outcome == es.COMPLETE or self.include_incomplete)
                try:
                    record = self._finish(path, done, graphs) if wanted else None
                except _Unusable as exc:  # it costs the episode, not the bag
                    self._drop(done, str(exc), ended=True)
                    continue
                if done.outcome == es.COMPLETE:
                    self.report.episodes_read += 1
                else:
                    self.report.count_outcome(done.outcome, taken=record is not None)
                if record is not None:
                    self.report.count_grid_size(record.episode.situation.grid_size)
                    yield record
            elif topic == COMMAND_GRAPH.name:
                try:
                    current.graph_json = cdr_to_text(data)
                    graphs.parse(current.graph_json)
                except GscanError as exc:
                    self._bad(current, topic, str(exc))
        self._drop(current, "no <eos> (the recording stopped first)")

    # -- episode assembly ---------------------------------------------------------------
    def _start(self, path: Path, data: bytes) -> _OpenEpisode:
        """The episode a `/command` starts, numbered among the bag's `/command`s."""
        episode = self._open_episode(path, data)
        episode.index, self._commands = self._commands, self._commands + 1
        return episode

    def _open_episode(self, path: Path, data: bytes) -> _OpenEpisode:
        try:
            header = json.loads(cdr_to_text(data))
        except GscanError as exc:  # no String: the episode it starts is lost with it
            episode = _OpenEpisode(header=None, selected=False)
            self._bad(episode, COMMAND.name, str(exc))
            return episode
        except json.JSONDecodeError:
            header = None
        if not isinstance(header, dict) or "situation" not in header:
            # A live command typed as plain text carries no initial situation: unusable.
            return _OpenEpisode(header=None, selected=False)
        version = header.get("version")
        if version != LEGACY_FORMAT_VERSION:
            raise DatasetFormatError(f"{path}: episode header version {version!r} is not supported")
        try:
            outcome = es.outcome_of(header.get("outcome", es.COMPLETE))
        except GscanError as exc:
            raise DatasetFormatError(f"{path}: episode {header.get('episode_id')}: {exc}") from None
        selected = self.splits is None or header.get("split") in self.splits
        return _OpenEpisode(header=header, selected=selected, outcome=outcome)

    def _drop(self, episode: _OpenEpisode | None, reason: str | None = None, *, ended: bool = False) -> None:
        """`episode` (if any) cannot be read back: for its own bad message, else for `reason`.
        One that `ended` (its `<eos>` came) is recorded in `dropped_commands` for `bag repair`,
        which leaves it out; the others are cut by what it sees itself (lost data, the next
        `/command`, the end of the bag)."""
        if episode is not None:
            self.report.count_drop(episode.damage or reason)
            self.report.discarded_messages += episode.messages
            if ended:
                self.dropped_commands.add(episode.index)

    def _bad(self, episode: _OpenEpisode, topic: str, detail: str) -> None:
        """A message of `episode` that cannot be read: counted, and the episode is dropped at its end."""
        self.report.bad_messages += 1
        if self.report.first_bad_message is None:
            where = episode.header.get("episode_id") if episode.header else "?"
            self.report.first_bad_message = f"{topic} of episode {where}: {detail}"
        episode.damage = episode.damage or f"a bad {topic} message"

    def _finish(self, path: Path, done: _OpenEpisode, graphs: GraphCache) -> RecordedEpisode:
        """The episode `done` as read; `_Unusable` when what it holds does not make one."""
        where = f"{path}: episode {done.header.get('episode_id')}"
        # An aborted episode may lack the state its last action led to (the reset came first).
        complete_states = done.observation_count == len(done.actions) + 1
        if not complete_states and not (done.outcome != es.COMPLETE and done.observation_count == len(done.actions)):
            raise _Unusable("its /observation count does not match its actions")
        try:
            episode = episode_from_header(done.header, done.actions, str(path))
        except GscanError:
            raise _Unusable("its header's situation is no gSCAN situation") from None
        graphs.attach(episode, done.graph_json, where)
        states = None
        if self.decode_states:
            states = np.stack(done.observations) if complete_states else np.stack(episode.states())
        return RecordedEpisode(episode, done.header, states, done.graph_json, done.outcome)

    # -- MCAP ------------------------------------------------------------------------------
    def _scan(self) -> Iterator[tuple[McapScan, tuple | object]]:
        """(the file's McapScan, one of its items) over every storage file in order; the item is
        `LOSS` where data was lost, a missing storage file included (`McapScan`, `BagInfo.missing`)."""
        for path in self.info.mcap_paths:
            scan = McapScan(path, self.report, self.info)
            for item in scan.items():
                yield scan, item

    def _messages(self) -> Iterator[tuple[Path, str, bytes] | object]:
        """(path, topic, CDR data) per readable message, and `LOSS` where data was lost."""
        channels: set[tuple[Path, int]] = set()
        for scan, item in self._scan():
            if item is LOSS:
                yield item
                continue
            channel = item[0]
            if (scan.path, channel.id) not in channels:
                channels.add((scan.path, channel.id))
                if channel.topic == OBSERVATION.name:
                    self._observation_type(scan, channel)
            yield scan.path, channel.topic, item[4]

    def observation(self, data: bytes) -> np.ndarray:
        """An `/observation` of this bag, decoded as its channel's type (a GscanError if it is
        no observation): the one reading of observations for the reader, `verify`, the
        training cache and `bag repair` (which reads the bag with a reader first)."""
        if self._decode_observation is None:  # set when its channel is first seen, before its messages
            raise DatasetFormatError(f"{self.info.path}: an /observation before its channel")
        return self._decode_observation(data)

    def _observation_type(self, scan: McapScan, channel) -> None:
        """Decode observations as `channel`'s type: an Image, or an earlier bag's UInt8MultiArray."""
        msg_type = scan.msg_type(channel) or OBSERVATION.msg_type
        if self._decode_observation is None:
            self._decode_observation = ObservationDecoder(msg_type)
        elif self._decode_observation.msg_type != msg_type:
            raise DatasetFormatError(f"{self.info.path}: {channel.topic} carries both "
                                     f"{self._decode_observation.msg_type} and {msg_type}")


def live_decoder(graphs: GraphCache, decode_observation: Callable[[bytes], np.ndarray]) -> StackDecoder:
    """The `StackDecoder` of format-2 bags (the reader's and `bag repair`'s): msg_adapters'
    conversions, graphs parsed once by `graphs`, observations read by `decode_observation`
    (`BagEpisodeReader.observation`)."""
    return StackDecoder(decode_action=cdr_to_action, decode_status=cdr_to_episode_status,
                        decode_text=cdr_to_text, check_graph=graphs.parse, decode_observation=decode_observation)


def iter_bag_episodes(
    bag_dir: str | os.PathLike, splits: Iterable[str] | None = None, *, log_losses: bool = True,
    include_incomplete: bool = False,
) -> BagEpisodeReader:
    """Stream the complete episodes of a bag (optionally only `splits`), in bag order.

    The returned iterator's `report` (a BagReadReport) says, once exhausted, how many
    episodes/messages were recovered and lost; losses are also logged as a warning
    (unless `log_losses=False`: the caller reports them itself).
    """
    return BagEpisodeReader(bag_dir, splits, log_losses=log_losses, include_incomplete=include_incomplete)

