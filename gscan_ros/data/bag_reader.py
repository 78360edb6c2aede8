"""Reading gscan_ros bags back as Episodes (`BagEpisodeReader`, `iter_bag_episodes`).

Streams each MCAP file through `McapScan`, so a truncated or damaged bag yields every
complete episode it still holds; an episode cut by lost data is dropped and counted in
the reader's `BagReadReport`, never assembled from the pieces around the damage.
"""
from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from gscan_ros.data.bag_format import (
    EPISODE_TOPICS,
    OUTCOME_ABORTED,
    OUTCOME_COMPLETE,
    GraphCache,
    episode_from_header,
)
from gscan_ros.data.bag_metadata import EPISODE_FORMAT_VERSION, read_bag_info
from gscan_ros.data.bag_report import BagReadReport
from gscan_ros.data.bag_scan import LOSS, McapScan
from gscan_ros.data.bag_schema import ACTION, COMMAND, COMMAND_GRAPH, OBSERVATION
from gscan_ros.data.episode import Episode
from gscan_ros.errors import DatasetFormatError, GscanError
from gscan_ros.world.types import Action
from msg_adapters import cdr_to_action, cdr_to_observation, cdr_to_text

# Losses are logged under the bag API's name (docs/bags.md), whichever module reads.
log = logging.getLogger("gscan_ros.data.bag")


@dataclass(frozen=True)
class RecordedEpisode:
    """An episode as recorded: the Episode, its observations (if decoded) and graph JSON."""

    episode: Episode
    header: dict
    states: np.ndarray | None  # uint8[T+1, 6, 6, 16]
    graph_json: str | None


class _ObservationDecoder:
    """CDR bytes -> uint8[6, 6, 16], decoding the layout once per distinct CDR prefix.

    Every observation of a bag has the same layout, so its CDR bytes differ only in the
    trailing data block. The first message with a new prefix is decoded in full with
    msg_adapters and checked (cdr_to_observation); later ones with a byte-identical prefix
    (same layout, same data length) are the same message up to that tail, so the tail
    is their data.
    """

    def __init__(self) -> None:
        self._prefixes: dict[bytes, tuple[int, tuple[int, ...]]] = {}

    def __call__(self, data: bytes) -> np.ndarray:
        for prefix, (size, shape) in self._prefixes.items():
            if len(data) == len(prefix) + size and data.startswith(prefix):
                return np.frombuffer(data, np.uint8, count=size, offset=len(prefix)).reshape(shape)
        observation = cdr_to_observation(data)
        size = observation.size
        if data[len(data) - size :] == observation.tobytes():
            self._prefixes[bytes(data[: len(data) - size])] = (size, observation.shape)
        return observation


@dataclass
class _OpenEpisode:
    header: dict | None  # None: a `/command` without a JSON header (plain-text live command)
    selected: bool
    messages: int = 1
    actions: list = field(default_factory=list)
    observations: list = field(default_factory=list)
    observation_count: int = 0
    graph_json: str | None = None
    aborted: bool = False  # header "outcome": "aborted"


class BagEpisodeReader(Iterator[Episode]):
    """Streaming reader: iterate it for Episodes; `report` describes what was recovered.

    Reads each MCAP file front to back (`McapScan`), without its summary, so a bag whose
    writer was killed (no summary, torn last chunk) still yields every complete episode,
    and a damaged chunk costs only the episodes that had messages in it: reading goes on
    at the next intact chunk, and an episode cut by lost data is dropped (counted in the
    report), never assembled from the pieces around the damage. A file that is not MCAP
    raises one DatasetFormatError naming the file.
    """

    def __init__(
        self,
        bag_dir: str | os.PathLike,
        splits: Iterable[str] | None = None,
        *,
        decode_states: bool = False,
        log_losses: bool = True,
        include_aborted: bool = False,
    ):
        self.info = read_bag_info(bag_dir)
        self.splits = None if splits is None else frozenset(splits)
        self.decode_states = decode_states
        self.include_aborted = include_aborted  # also yield episodes recorded as aborted
        self.log_losses = log_losses  # log report.summary() as a warning when something was lost
        self.report = BagReadReport(
            self.info.path,
            expected_messages=self.info.message_count if self.info.closed else None,
            expected_episodes=self.info.episodes,
        )
        self._episodes = (r.episode for r in self.records())

    def __next__(self) -> Episode:
        return next(self._episodes)

    def records(self) -> Iterator[RecordedEpisode]:
        """Complete episodes in bag order (with observations when `decode_states`), and
        those recorded as aborted when `include_aborted`."""
        action_cache: dict[bytes, Action] = {}  # CDR bytes of the 7 action tokens
        decode_observation = _ObservationDecoder()
        graphs = GraphCache()
        current: _OpenEpisode | None = None
        for item in self._messages():
            if item is LOSS:  # data lost here: the open episode cannot be completed
                self._drop(current)
                current = None
                continue
            path, topic, data = item
            self.report.messages_read += 1
            if topic == COMMAND.name:
                self._drop(current)
                current = self._start(path, data)
                continue
            if current is None:  # between episodes: only episode topics count as lost data
                self.report.discarded_messages += topic in EPISODE_TOPICS
                continue
            current.messages += 1
            if topic == OBSERVATION.name:
                current.observation_count += 1
                if self.decode_states and current.selected:
                    current.observations.append(decode_observation(data))
            elif topic == ACTION.name:
                action = action_cache.get(data)
                if action is None:
                    action = self._decode_action(path, data, current)
                    action_cache[bytes(data)] = action
                if action is not Action.EOS:
                    current.actions.append(action)
                    continue
                done, current = current, None
                if done.aborted:
                    self.report.aborted_episodes += 1
                    if not self.include_aborted:
                        continue
                else:
                    self.report.episodes_read += 1
                if done.selected:
                    yield self._finish(path, done, graphs)
            elif topic == COMMAND_GRAPH.name:
                current.graph_json = cdr_to_text(data)
        self._drop(current)
        self.report.finished = True
        if self.log_losses and not self.report.complete:
            log.warning(self.report.summary())

    # -- episode assembly ---------------------------------------------------------------
    def _start(self, path: Path, data: bytes) -> _OpenEpisode:
        text = cdr_to_text(data)
        try:
            header = json.loads(text)
        except json.JSONDecodeError:
            header = None
        if not isinstance(header, dict) or "situation" not in header:
            # A live command typed as plain text carries no initial situation: unusable.
            return _OpenEpisode(header=None, selected=False)
        version = header.get("version")
        if not isinstance(version, int) or version > EPISODE_FORMAT_VERSION:
            raise DatasetFormatError(f"{path}: episode header version {version!r} is not supported")
        outcome = header.get("outcome", OUTCOME_COMPLETE)
        if outcome not in (OUTCOME_COMPLETE, OUTCOME_ABORTED):
            raise DatasetFormatError(f"{path}: episode {header.get('episode_id')}: unknown outcome {outcome!r}")
        selected = self.splits is None or header.get("split") in self.splits
        return _OpenEpisode(header=header, selected=selected, aborted=outcome == OUTCOME_ABORTED)

    def _drop(self, episode: _OpenEpisode | None) -> None:
        if episode is not None:
            self.report.incomplete_episodes += 1
            self.report.discarded_messages += episode.messages

    def _decode_action(self, path: Path, data: bytes, episode: _OpenEpisode) -> Action:
        try:
            return cdr_to_action(data)
        except GscanError as exc:
            where = episode.header.get("episode_id") if episode.header else "?"
            raise DatasetFormatError(f"{path}: episode {where}: {exc}") from None

    def _finish(self, path: Path, done: _OpenEpisode, graphs: GraphCache) -> RecordedEpisode:
        if done.header is None:
            raise AssertionError("unselected episodes are never finished")
        where = f"{path}: episode {done.header.get('episode_id')}"
        # An aborted episode may lack the state its last action led to (the reset came first).
        if done.observation_count != len(done.actions) + 1 and not (
            done.aborted and done.observation_count == len(done.actions)
        ):
            raise DatasetFormatError(
                f"{where}: {done.observation_count} observations for {len(done.actions) + 1} actions (with <eos>)"
            )
        episode = episode_from_header(done.header, done.actions, str(path))
        graphs.attach(episode, done.graph_json, where)
        states = np.stack(done.observations) if self.decode_states else None
        return RecordedEpisode(episode, done.header, states, done.graph_json)

    # -- MCAP ------------------------------------------------------------------------------
    def _messages(self) -> Iterator[tuple[Path, str, bytes] | object]:
        """(path, topic, CDR data) per readable message, and `LOSS` where data was lost."""
        for path in self.info.mcap_paths:
            for item in McapScan(path, self.report, self.info).items():
                yield item if item is LOSS else (path, item[0].topic, item[4])


def iter_bag_episodes(
    bag_dir: str | os.PathLike, splits: Iterable[str] | None = None, *, log_losses: bool = True
) -> BagEpisodeReader:
    """Stream the complete episodes of a bag (optionally only `splits`), in bag order.

    The returned iterator's `report` (a BagReadReport) says, once exhausted, how many
    episodes/messages were recovered and lost; losses are also logged as a warning
    (unless `log_losses=False`: the caller reports them itself).
    """
    return BagEpisodeReader(bag_dir, splits, log_losses=log_losses)
