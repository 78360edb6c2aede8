"""Decode-once cache of a bag's episodes and observations, for fast repeated training loads.

Decoding a bag (CDR + JSON + situations) runs at MCAP-reader speed; training reads
the same bag many times. The first `load_episode_cache` decodes the bag and stores
plain arrays in `<bag_dir>/.cache/episodes.npz` (no pickles); later calls load them
as long as the key (format version, each MCAP file's size and mtime or its absence, a
hash of metadata.yaml) still matches. A cache file that cannot be read (empty, torn, not an
npz, inconsistent arrays) is rebuilt with a warning. The cache records what the
decode lost: a cache built from a damaged bag (truncated, corrupt, episodes lost)
warns each time it is loaded, so the loss is not hidden by later fast loads.

Teacher-forced training needs commands, actions and observations, not Situations,
and parsing a Situation is the slowest step of a load, so situations stay JSON text
until an Episode is asked for (`cache.episode(i)`, `cache.episodes`). Observations
are 0/1 one-hot planes, stored bit-packed along the channel axis (16 -> 2 bytes).
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path
from typing import Iterable

import numpy as np

from gscan_ros import episode_status as es
from gscan_ros.data.bag_format import GraphCache, episode_from_header
from gscan_ros.data.bag_metadata import CACHE_DIR, METADATA_FILE, read_bag_info
from gscan_ros.data.bag_reader import BagEpisodeReader
from gscan_ros.data.bag_report import BagReadReport
from gscan_ros.data.episode import Episode
from gscan_ros.errors import DatasetFormatError
from gscan_ros.world.types import Action

log = logging.getLogger(__name__)

# 4: every outcome cached (headers' "outcome"), selected at load; 5: every stack of a bag read,
# bad messages cost their episode, `exact` says whether the episode count is known; 6: messages
# held twice read once, an episode without graphs named by its ACTIVE report, a message logged
# beyond the reorder window a loss.
CACHE_VERSION = 6
CACHE_FILE = "episodes.npz"
_ACTIONS = tuple(Action)


class EpisodeCache:
    """A bag's episodes (optionally one split subset) with all their observations.

    Row i is the i-th selected episode in bag order. `commands`, `splits`,
    `actions(i)` and `states(i)` are cheap; `episode(i)` builds the full Episode
    (parsing its situation once), `episodes` builds them all.
    """

    def __init__(self, arrays: dict[str, np.ndarray], rows: np.ndarray, where: str):
        self._arrays = arrays
        self._rows = rows
        self._where = where
        self.source: dict = json.loads(arrays["source"].tobytes())
        """What decoding the bag recovered and lost: `complete`, `state`, `episodes_read`,
        `lost_episodes`, `lost_messages`, `exact`, `summary` (a BagReadReport's)."""
        headers = json.loads(arrays["headers"].tobytes())
        self.headers: list[dict] = [headers[r] for r in rows]
        graphs = json.loads(arrays["graphs"].tobytes())
        self._graph_json: list[str] = [graphs[r] for r in rows]
        self._graphs = GraphCache()
        self._episodes: dict[int, Episode] = {}

    def __len__(self) -> int:
        return len(self._rows)

    @property
    def complete(self) -> bool:
        """The bag was read without damage or loss when this cache was built."""
        return bool(self.source["complete"])

    @property
    def lost_episodes(self) -> int:
        """Episodes of the bag that the cache lacks (a lower bound unless `source['exact']`:
        our writer closed the bag and counted its episodes)."""
        return int(self.source["lost_episodes"])

    @property
    def commands(self) -> list[str]:
        return [h["command"] for h in self.headers]

    @property
    def splits(self) -> list[str]:
        return [h["split"] for h in self.headers]

    def actions(self, index: int) -> tuple[Action, ...]:
        """Gold actions of episode `index` (EOS excluded)."""
        row = self._rows[index]
        start, stop = self._arrays["action_offsets"][row : row + 2]
        return tuple(_ACTIONS[a] for a in self._arrays["actions"][start:stop])

    def packed_states(self, index: int) -> np.ndarray:
        """uint8[T+1, 6, 6, 2]: episode `index`'s observations, bit-packed over channels."""
        row = self._rows[index]
        start, stop = self._arrays["state_offsets"][row : row + 2]
        return self._arrays["packed_states"][start:stop]

    def states(self, index: int) -> np.ndarray:
        """uint8[T+1, 6, 6, 16]: the same arrays as `episode(index).states()`."""
        return np.unpackbits(self.packed_states(index), axis=-1, count=int(self._arrays["channels"]))

    def stacked_states(self, indices: Iterable[int]) -> np.ndarray:
        """uint8[sum(T+1), 6, 6, 16]: the states of episodes `indices`, concatenated in order."""
        packed = [self.packed_states(i) for i in indices]
        if not packed:
            return np.zeros((0, *self._arrays["packed_states"].shape[1:-1], int(self._arrays["channels"])), np.uint8)
        return np.unpackbits(np.concatenate(packed), axis=-1, count=int(self._arrays["channels"]))

    def subset(self, indices: Iterable[int]) -> "EpisodeCache":
        """The episodes `indices` of this cache (in that order), sharing its arrays."""
        return EpisodeCache(self._arrays, self._rows[np.asarray(list(indices), dtype=np.int64)], self._where)

    def episode(self, index: int) -> Episode:
        episode = self._episodes.get(index)
        if episode is None:
            row = self._rows[index]
            start, stop = self._arrays["situation_offsets"][row : row + 2]
            header = {**self.headers[index], "situation": json.loads(self._arrays["situations"][start:stop].tobytes())}
            episode = episode_from_header(header, self.actions(index), self._where)
            self._graphs.attach(episode, self._graph_json[index], self._where)
            self._episodes[index] = episode
        return episode

    @property
    def episodes(self) -> list[Episode]:
        return [self.episode(i) for i in range(len(self))]


def cache_path(bag_dir: str | os.PathLike) -> Path:
    return Path(bag_dir) / CACHE_DIR / CACHE_FILE


def _cache_key(bag_dir: Path) -> str:
    info = read_bag_info(bag_dir)
    metadata = bag_dir / METADATA_FILE
    parts = [f"v{CACHE_VERSION}", hashlib.sha256(metadata.read_bytes()).hexdigest() if metadata.is_file() else "-"]
    for path in info.mcap_paths:  # a missing storage file (lost data) is part of the key too
        try:
            stat = path.stat()
        except OSError:
            parts.append(f"{path.name}:missing")
            continue
        parts.append(f"{path.name}:{stat.st_size}:{stat.st_mtime_ns}")
    return "|".join(parts)


_WARNED: set = set()  # the cache keys whose damage was logged in this process


def load_episode_cache(
    bag_dir: str | os.PathLike, splits: Iterable[str] | None = None, *, rebuild: bool = False,
    include_incomplete: bool = False,
) -> EpisodeCache:
    """Episodes and observations of a bag, decoded once and cached next to it.

    `splits` selects after loading (the cache always holds the whole bag), and so does
    `include_incomplete` (recorded episodes that ended cut, preempted or rejected). A bag whose
    directory is read-only is decoded without writing the cache (logged). An unreadable
    cache file is rebuilt (logged). If the bag was damaged or lost episodes when the
    cache was built, the first load of it in a process logs a warning saying how many
    (training loads the train and the dev split of one bag: one warning); every cache
    says so too (`cache.complete`, `cache.lost_episodes`, `cache.source`).
    """
    bag_dir = Path(bag_dir)
    key = _cache_key(bag_dir)
    path = cache_path(bag_dir)
    arrays = None if rebuild else _load(path, key)
    if arrays is None:
        arrays = _decode(bag_dir, key)
        _save(path, arrays)
    source = json.loads(arrays["source"].tobytes())
    if not source["complete"] and key not in _WARNED:
        _WARNED.add(key)
        bound = BagReadReport.bound(source["exact"])
        log.warning(
            "%s: episode cache built from a damaged bag: %s%d episodes lost (%s); "
            "`gscan-ros bag repair` writes what is left as a complete bag",
            bag_dir, bound, source["lost_episodes"], source["summary"],
        )
    headers = json.loads(arrays["headers"].tobytes())
    wanted = None if splits is None else frozenset(splits)
    rows = np.asarray([r for r, h in enumerate(headers)
                       if (wanted is None or h["split"] in wanted)
                       and (include_incomplete or h.get("outcome", es.COMPLETE) == es.COMPLETE)], dtype=np.int64)
    return EpisodeCache(arrays, rows, str(bag_dir))


def _buffer(texts: list[bytes]) -> tuple[np.ndarray, np.ndarray]:
    """Concatenated byte strings plus int64 offsets (len + 1)."""
    offsets = np.zeros(len(texts) + 1, dtype=np.int64)
    np.cumsum([len(t) for t in texts], out=offsets[1:])
    return np.frombuffer(b"".join(texts), dtype=np.uint8), offsets


def _decode(bag_dir: Path, key: str) -> dict[str, np.ndarray]:
    reader = BagEpisodeReader(bag_dir, decode_states=True, log_losses=False,  # load_episode_cache warns
                              include_incomplete=True)
    headers, situations, graphs, actions, action_offsets, states = [], [], [], [], [0], []
    for record in reader.records():
        header = dict(record.header)
        header.pop("outcome", None)
        if record.outcome != es.COMPLETE:
            header["outcome"] = record.outcome
        situations.append(json.dumps(header.pop("situation"), separators=(",", ":")).encode())
        headers.append(header)
        graphs.append(record.graph_json or "")
        actions.extend(int(a) for a in record.episode.actions)
        action_offsets.append(len(actions))
        states.append(record.states)
    mixed = reader.report.mixed_grid_sizes()
    if mixed:
        raise DatasetFormatError(mixed)
    all_states = np.concatenate(states) if states else np.zeros((0, 6, 6, 16), np.uint8)
    if all_states.size and all_states.max() > 1:
        raise DatasetFormatError(f"{bag_dir}: observations are not 0/1 one-hot encodings")
    situation_bytes, situation_offsets = _buffer(situations)
    report = reader.report
    source = {
        "complete": report.complete,
        "state": report.state(),
        "exact": report.episodes_exact,
        "episodes_read": report.episodes_read,
        "lost_episodes": report.lost_episodes,
        "lost_messages": report.lost_messages,
        "summary": report.summary(),
    }
    return {
        "key": np.array(key),
        "source": np.frombuffer(json.dumps(source).encode(), dtype=np.uint8),
        "headers": np.frombuffer(json.dumps(headers).encode(), dtype=np.uint8),
        "situations": situation_bytes,
        "situation_offsets": situation_offsets,
        "graphs": np.frombuffer(json.dumps(graphs).encode(), dtype=np.uint8),
        "actions": np.asarray(actions, dtype=np.uint8),
        "action_offsets": np.asarray(action_offsets, dtype=np.int64),
        "packed_states": np.packbits(all_states, axis=-1),
        "state_offsets": np.cumsum([0] + [len(s) for s in states], dtype=np.int64),
        "channels": np.array(all_states.shape[-1]),
    }


_ARRAYS = ("key", "source", "headers", "situations", "situation_offsets", "graphs", "actions",
           "action_offsets", "packed_states", "state_offsets", "channels")


def _load(path: Path, key: str) -> dict[str, np.ndarray] | None:
    """The cached arrays, or None to rebuild: no file, another bag/layout (silently), or a
    file that cannot be read (logged: empty, torn, not an npz, inconsistent)."""
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            if "key" not in data.files or str(data["key"]) != key:
                log.info("bag cache %s is for another version of the bag; rebuilding", path)
                return None
            arrays = {name: data[name] for name in data.files}
        _check(arrays)
    except Exception as exc:  # noqa: BLE001 - any unreadable cache is rebuilt, never fatal
        log.warning("bag cache %s is unreadable (%s: %s); rebuilding it", path, exc.__class__.__name__, exc)
        return None
    return arrays


def _check(arrays: dict[str, np.ndarray]) -> None:
    """ValueError unless the arrays fit together (a cache written by `_decode`)."""
    missing = [name for name in _ARRAYS if name not in arrays]
    if missing:
        raise ValueError(f"missing arrays {missing}")
    headers = json.loads(arrays["headers"].tobytes())
    graphs = json.loads(arrays["graphs"].tobytes())
    source = json.loads(arrays["source"].tobytes())
    count = len(headers)
    if not isinstance(source, dict) or not {"complete", "exact", "lost_episodes", "summary"} <= source.keys():
        raise ValueError("bad source record")
    for name, total in (("action_offsets", len(arrays["actions"])), ("state_offsets", len(arrays["packed_states"])),
                        ("situation_offsets", len(arrays["situations"]))):
        offsets = arrays[name]
        if offsets.ndim != 1 or len(offsets) != count + 1 or offsets[0] != 0 or offsets[-1] != total \
                or np.any(np.diff(offsets) < 0):
            raise ValueError(f"{name} do not match the data")
    if len(graphs) != count:
        raise ValueError("graphs do not match the headers")
    if np.any(np.diff(arrays["state_offsets"]) != np.diff(arrays["action_offsets"]) + 1):
        raise ValueError("states do not match the actions")
    if arrays["actions"].size and int(arrays["actions"].max()) >= len(_ACTIONS):
        raise ValueError("unknown action codes")


def _save(path: Path, arrays: dict[str, np.ndarray]) -> None:
    try:
        path.parent.mkdir(exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, **arrays)
        os.replace(tmp, path)
    except OSError as exc:
        log.warning("cannot write bag cache %s (%s); decoding again next time", path, exc)
