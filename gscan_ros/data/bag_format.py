"""The episode conventions of gscan_ros bags, shared by the writer, the readers, the repair and the cache.

Format 2 (docs/bags.md "Episodes"): a bag holds the live topics as the stack publishes
them. The policy's `/episode_status` reports delimit episodes (ACTIVE, then how it
ended); `/episode` carries what a bag adds to an episode (split, example id, the
dataset's fields), keyed by the report's id. Generated data gets synthetic times:
episode i at i s, its prologue (`/episode`, `/situation`, `/observation` 0, `/command`,
`/command_graph`, ACTIVE) PROLOGUE_NS apart, action t at +(t+1) ms, the world's reply
half a millisecond after it; live recordings keep their real times.

Format 1 (bags written before): a `/command` message carried a JSON header
`{"version": 1, "episode_id", "split", "example_id", "command", "situation", "meta"}`
(with `"outcome": "aborted"` for an episode a world reset ended), then optionally one
`/command_graph`, then `/observation` t (+ `/world_image` t) and `/action` t for t =
0..T, the last action `<eos>`. Readers still read it.
"""
from __future__ import annotations

from typing import Iterable

from gscan_ros.data.bag_metadata import EPISODE_FORMAT_VERSION, LEGACY_FORMAT_VERSION
from gscan_ros.data.bag_schema import ACTION, COMMAND, COMMAND_GRAPH, OBSERVATION, WORLD_IMAGE
from gscan_ros.data.episode import Episode
from gscan_ros.episode_status import outcome_of
from gscan_ros.errors import DatasetFormatError, GscanError
from gscan_ros.language.graph import CommandGraph
from gscan_ros.world.types import Action, Situation

EPISODE_PERIOD_NS = 1_000_000_000  # generated episode i starts at i s
STEP_NS = 1_000_000  # action t of an episode at +(t+1) ms
PROLOGUE_NS = 1_000  # the messages before an episode's first action, this far apart
ACTION_DELAY_NS = STEP_NS // 2  # the world's reply follows the action
# The episode topics of format 1 (what its readers count as lost when cut by damage).
LEGACY_EPISODE_TOPICS = frozenset(t.name for t in (COMMAND, COMMAND_GRAPH, OBSERVATION, ACTION, WORLD_IMAGE))
# Episode.meta keys the reader adds (not stored in a bag, so re-writing is clean).
READER_META_KEYS = frozenset({"episode_id", "command_graph", "outcome"})
LIVE_SPLIT = "live"  # the split of recorded episodes that no dataset names


def episode_record(episode: Episode, status_id: str, episode_id: int) -> dict:
    """What `/episode` says of a generated episode (module docstring): the reader joins it
    to the episode whose `/episode_status` reports carry `status_id`."""
    return {
        "version": EPISODE_FORMAT_VERSION,
        "id": status_id,
        "episode_id": episode_id,
        "split": episode.split,
        "example_id": episode.example_id,
        "command": episode.command,
        "meta": {k: v for k, v in episode.meta.items() if k not in READER_META_KEYS},
    }


def legacy_header(episode: Episode, episode_id: int) -> dict:
    """The format-1 `/command` header of a complete episode (tests write old bags with it)."""
    return {
        "version": LEGACY_FORMAT_VERSION,
        "episode_id": episode_id,
        "split": episode.split,
        "example_id": episode.example_id,
        "command": episode.command,
        "situation": episode.situation.to_json(),
        "meta": {k: v for k, v in episode.meta.items() if k not in READER_META_KEYS},
    }


def episode_from_header(header: dict, actions: Iterable[Action], where: str) -> Episode:
    """Rebuild an Episode from an episode header (format 1's `/command` JSON, or what the
    format-2 reader assembles) and its actions (EOS excluded); a recorded outcome other
    than complete goes to `meta["outcome"]`."""
    try:
        episode_id = header["episode_id"]
        return Episode(
            command=header["command"],
            situation=Situation.from_json(header["situation"]),
            actions=tuple(actions),
            split=header["split"],
            example_id=header.get("example_id"),
            meta={**(header.get("meta") or {}), "episode_id": episode_id,
                  **({"outcome": outcome_of(header["outcome"])} if "outcome" in header else {})},
        )
    except KeyError as exc:
        raise DatasetFormatError(f"{where}: episode header lacks field {exc}") from None
    except GscanError as exc:
        raise DatasetFormatError(f"{where}: episode {header.get('episode_id')}: {exc}") from None


class GraphCache:
    """Parses each distinct CommandGraph JSON once (a bag repeats the same few hundred)."""

    def __init__(self) -> None:
        self._graphs: dict[str, CommandGraph] = {}

    def parse(self, graph_json: str) -> CommandGraph:
        """The graph; a GraphError (a GscanError) for text that is none."""
        graph = self._graphs.get(graph_json)
        if graph is None:
            graph = self._graphs[graph_json] = CommandGraph.from_json(graph_json)
        return graph

    def attach(self, episode: Episode, graph_json: str | None, where: str) -> None:
        """Put the parsed graph into `episode.meta["command_graph"]` (no-op without one)."""
        if not graph_json:
            return
        try:
            episode.meta["command_graph"] = self.parse(graph_json)
        except GscanError as exc:
            raise DatasetFormatError(f"{where}: command_graph: {exc}") from None
