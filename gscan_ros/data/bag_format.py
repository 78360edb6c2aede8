"""The episode convention of gscan_ros bags: the `/command` header, outcomes, synthetic times.

An episode is the run of messages from one `/command` to its `<eos>` action
(docs/bags.md "Episode convention"):

- a `/command` message starts an episode; its String data is a JSON header
  `{"version": 1, "episode_id", "split", "example_id", "command", "situation": <gSCAN
  situation JSON>, "meta"}`;
- optionally one `/command_graph` (CommandGraph JSON);
- then for t = 0..T: `/observation` t (+ `/world_image` t), then `/action` t, where the
  last action is `<eos>`, which closes the episode. A live episode that a world reset
  ended is written the same way with `"outcome": "aborted"` in its header; readers skip
  it (`include_aborted` to get it) and count it in `BagReadReport.aborted_episodes`.

Generated data gets synthetic times (episode i at i s, step t at +(t+1) ms, the action
half a millisecond after its observation); live recordings keep their real times.
Shared by the writer, the reader, the repair and the decode cache.
"""
from __future__ import annotations

from typing import Iterable

from gscan_ros.data.bag_metadata import EPISODE_FORMAT_VERSION
from gscan_ros.data.bag_schema import ACTION, COMMAND, COMMAND_GRAPH, OBSERVATION, WORLD_IMAGE
from gscan_ros.data.episode import Episode
from gscan_ros.errors import DatasetFormatError, GscanError
from gscan_ros.language.graph import CommandGraph
from gscan_ros.world.types import Action, Situation

EPISODE_PERIOD_NS = 1_000_000_000  # generated episode i starts at i seconds
STEP_NS = 1_000_000  # step t of an episode at +(t+1) ms
ACTION_DELAY_NS = STEP_NS // 2  # an action follows its observation
EPISODE_TOPICS = frozenset(t.name for t in (COMMAND, COMMAND_GRAPH, OBSERVATION, ACTION, WORLD_IMAGE))
# Episode.meta keys the reader adds (not stored in the header, so re-writing is clean).
READER_META_KEYS = frozenset({"episode_id", "command_graph"})
# Header "outcome" (absent: complete). An aborted episode (a live one that the world's
# reset ended) is framed like the others, its `<eos>` stamped when it ended, and is
# skipped by readers unless asked for: it is no demonstration (docs/bags.md).
OUTCOME_COMPLETE = "complete"
OUTCOME_ABORTED = "aborted"


def episode_header(episode: Episode, episode_id: int, outcome: str = OUTCOME_COMPLETE) -> dict:
    """The JSON header a `/command` message carries (module docstring)."""
    header = {
        "version": EPISODE_FORMAT_VERSION,
        "episode_id": episode_id,
        "split": episode.split,
        "example_id": episode.example_id,
        "command": episode.command,
        "situation": episode.situation.to_json(),
        "meta": {k: v for k, v in episode.meta.items() if k not in READER_META_KEYS},
    }
    if outcome != OUTCOME_COMPLETE:
        header["outcome"] = outcome
    return header


def episode_from_header(header: dict, actions: Iterable[Action], where: str) -> Episode:
    """Rebuild an Episode from its `/command` header and recorded actions (EOS excluded)."""
    try:
        episode_id = header["episode_id"]
        return Episode(
            command=header["command"],
            situation=Situation.from_json(header["situation"]),
            actions=tuple(actions),
            split=header["split"],
            example_id=header.get("example_id"),
            meta={**(header.get("meta") or {}), "episode_id": episode_id},
        )
    except KeyError as exc:
        raise DatasetFormatError(f"{where}: episode header lacks field {exc}") from None
    except GscanError as exc:
        raise DatasetFormatError(f"{where}: episode {header.get('episode_id')}: {exc}") from None


class GraphCache:
    """Parses each distinct CommandGraph JSON once (a bag repeats the same few hundred)."""

    def __init__(self) -> None:
        self._graphs: dict[str, CommandGraph] = {}

    def attach(self, episode: Episode, graph_json: str | None, where: str) -> None:
        """Put the parsed graph into `episode.meta["command_graph"]` (no-op without one)."""
        if not graph_json:
            return
        graph = self._graphs.get(graph_json)
        if graph is None:
            try:
                graph = self._graphs[graph_json] = CommandGraph.from_json(graph_json)
            except GscanError as exc:
                raise DatasetFormatError(f"{where}: command_graph: {exc}") from None
        episode.meta["command_graph"] = graph


LIVE_SPLIT = "live"  # the split of episodes a live recorder writes


def live_episode(graph: CommandGraph, situation: Situation, actions: Iterable[Action], *, recorded_by: str,
                 aborted_because: str | None = None) -> Episode:
    """A recorded live episode: the command the policy followed (the graph's canonical one;
    the typed text goes to `meta.typed_command`), from `situation`, in split `live`."""
    meta = {"parser": graph.parser, "recorded_by": recorded_by}
    if graph.typed is not None:
        meta["typed_command"] = graph.typed
    if aborted_because is not None:
        meta["aborted_because"] = aborted_because
    return Episode(command=graph.command, situation=situation, actions=tuple(actions), split=LIVE_SPLIT, meta=meta)
