"""Teacher-forcing data: parse graphs, a compact per-dataset state cache, batch samplers.

Teacher forcing needs all T+1 world states of every episode (initial + after each gold
action, as the data pipeline of ylkuo/compositional-gscan builds them). They are
replayed once per dataset through the one World physics (`Episode.states()`) or read
from a bag's decode-once cache, and kept as the *set-bit indices* of each one-hot
state (int16, ~20 per state instead of 576 bytes, ~40 bytes per state), which is both
the cache and the direct input of the sparse visual encoder.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterable, Iterator, Sequence, Sized

import numpy as np
import torch
from tqdm import tqdm

from gscan_ros.data.episode import Episode
from gscan_ros.errors import quoted
from gscan_ros.language.graph import CommandGraph
from gscan_ros.model.layout import Layout
from gscan_ros.model.modules import ModuleTable
from gscan_ros.model.teacher_forcing import TeacherBatch
from gscan_ros.world.types import AGENT_CHANNEL, GRID_SIZE, NUM_CHANNELS, Action

if TYPE_CHECKING:  # the bag layer imports rclpy's serializer; training must not
    from gscan_ros.data.bag_cache import EpisodeCache

BATCHING = ("mixed", "per_command")
_INTERACTIONS = (int(Action.PUSH), int(Action.PULL))


class EpisodeStore:
    """Commands + their graphs + cached states and actions, addressable by episode index.

    Built from Episodes (states replayed through `World`) or, for bags, from the bag's
    decode-once cache (`from_cache`: recorded states, no Situation parsed, no replay).
    """

    def __init__(self, episodes: Iterable[Episode], parser, progress: bool = False, chunk: int = 4096):
        """Streams `episodes` (any iterable) in chunks: only a chunk of Episodes is alive at once."""
        commands: list[str] = []
        actions: list[Sequence[Action]] = []

        def state_chunks() -> Iterator[np.ndarray]:
            batch: list[Episode] = []
            for ep in episodes:
                commands.append(ep.command)
                actions.append(ep.actions)
                batch.append(ep)
                if len(batch) == chunk:
                    yield np.concatenate([e.states() for e in batch])
                    batch = []
            if batch:
                yield np.concatenate([e.states() for e in batch])

        total = -(-len(episodes) // chunk) if isinstance(episodes, Sized) else None
        self._fill(commands, actions, state_chunks(), parser, progress=progress, total=total)

    @classmethod
    def from_cache(cls, cache: "EpisodeCache", parser, progress: bool = False, chunk: int = 4096) -> "EpisodeStore":
        """The store of a bag's `EpisodeCache`: the same arrays as `EpisodeStore(cache.episodes)`."""
        store = cls.__new__(cls)
        n = len(cache)
        chunks = (cache.stacked_states(range(start, min(start + chunk, n))) for start in range(0, n, chunk))
        store._fill(cache.commands, [cache.actions(i) for i in range(n)], chunks, parser,
                    progress=progress, total=-(-n // chunk))
        return store

    def _fill(self, commands: list[str], actions: list[Sequence[Action]], state_chunks: Iterable[np.ndarray],
              parser, progress: bool, total: int) -> None:
        """Parse each distinct command once; keep actions (+EOS) and the set bits of each state.

        `state_chunks` yields the episodes' T+1 states, concatenated in episode order; it
        is consumed first (it may be what fills `commands` and `actions`)."""
        bits, counts = [], []
        self.grid_size = None
        for states in tqdm(state_chunks, total=total, desc="caching states", unit="chunk", disable=not progress):
            if states.ndim != 4 or states.shape[1] != states.shape[2] or states.shape[3] != NUM_CHANNELS:
                raise ValueError(f"states must be [T, G, G, {NUM_CHANNELS}], got {list(states.shape)}")
            if self.grid_size not in (None, states.shape[1]):
                raise ValueError(f"episodes on {self.grid_size}x{self.grid_size} and {states.shape[1]}x"
                                 f"{states.shape[1]} grids in one dataset")
            self.grid_size = int(states.shape[1])
            flat = states.reshape(len(states), -1)
            if flat.max(initial=0) > 1:
                raise ValueError("observations must be one-hot (0/1) encodings")
            rows, cols = np.nonzero(flat)
            bits.append(cols.astype(np.int16))
            counts.append(np.bincount(rows, minlength=len(flat)))
        self.commands = list(commands)
        graphs: dict[str, CommandGraph] = {c: parser.parse(c) for c in dict.fromkeys(self.commands)}
        self.graphs = [graphs[c] for c in self.commands]
        self.lengths = np.array([len(a) + 1 for a in actions], dtype=np.int64)  # + EOS
        self.ep_ptr = np.zeros(len(self.commands) + 1, dtype=np.int64)
        self.ep_ptr[1:] = np.cumsum(self.lengths)  # states per episode = T + 1 = length
        self.actions = np.array([int(a) for acts in actions for a in (*acts, Action.EOS)], dtype=np.int64)
        self.bits = np.concatenate(bits) if bits else np.zeros(0, np.int16)
        counts_all = np.concatenate(counts) if counts else np.zeros(0, np.int64)
        if len(counts_all) != self.ep_ptr[-1]:
            raise ValueError(f"{len(counts_all)} states for {self.ep_ptr[-1]} steps (T+1 per episode)")
        self.state_ptr = np.zeros(len(counts_all) + 1, dtype=np.int64)
        self.state_ptr[1:] = np.cumsum(counts_all)

    def initial_states(self, ids: Sequence[int]) -> np.ndarray:
        """uint8[B, G, G, 16]: the first state of episodes `ids`, rebuilt from the set bits."""
        g = self.grid_size or GRID_SIZE
        out = np.zeros((len(ids), g * g * NUM_CHANNELS), dtype=np.uint8)
        for row, i in enumerate(ids):
            state = self.ep_ptr[i]
            out[row, self.bits[self.state_ptr[state] : self.state_ptr[state + 1]]] = 1
        return out.reshape(len(ids), g, g, NUM_CHANNELS)

    def target_cells(self, ids: Sequence[int]) -> np.ndarray:
        """int64[B]: the cell (row * G + column) of the target object of episodes `ids`.

        A gSCAN demonstration walks onto the target before it pushes or pulls (agent and
        object share the cell, quirk Q11), so the target's cell is the agent's in the state
        before the first push/pull, or in the last state of an episode without one. Read
        from the cached states, so bags need no Situation parsed (tests: equal to
        `Situation.target_object.position` on generated data)."""
        out = np.empty(len(ids), dtype=np.int64)
        for row, i in enumerate(ids):
            start, stop = self.ep_ptr[i], self.ep_ptr[i + 1]
            interacts = np.flatnonzero(np.isin(self.actions[start:stop], _INTERACTIONS))
            state = start + (interacts[0] if len(interacts) else stop - 1 - start)
            bits = self.bits[self.state_ptr[state] : self.state_ptr[state + 1]].astype(np.int64)
            out[row] = bits[bits % NUM_CHANNELS == AGENT_CHANNEL][0] // NUM_CHANNELS
        return out

    def __len__(self) -> int:
        return len(self.commands)

    def graph_table(self, lexicon=None) -> ModuleTable:
        return ModuleTable.from_graphs(self.graphs, lexicon)

    def batch(self, ids: Sequence[int], table: ModuleTable, quantum: int = 8) -> TeacherBatch:
        """A TeacherBatch of episodes `ids`: rows sorted by length, packed time-major, the
        number of rows computed per step rounded up to a multiple of `quantum`: fewer
        re-slices of the per-row tensors vs. fewer padded steps (docs/results.md,
        "Engine settings")."""
        ids = np.asarray(ids, dtype=np.int64)
        ids = ids[np.argsort(-self.lengths[ids], kind="stable")]
        lengths = self.lengths[ids]
        t_max = int(lengths[0])
        alive = np.array([(lengths > t).sum() for t in range(t_max)])
        active = np.minimum(-(-alive // quantum) * quantum, len(ids))
        rows = np.concatenate([np.arange(n) for n in active])
        steps = np.repeat(np.arange(t_max), active)
        valid = steps < lengths[rows]
        state_ids = np.where(valid, self.ep_ptr[ids[rows]] + steps, -1)
        starts = np.where(valid, self.state_ptr[state_ids], 0)
        counts = np.where(valid, self.state_ptr[state_ids + 1] - starts, 0)  # padded: empty grid
        offsets = np.zeros(len(state_ids), dtype=np.int64)
        offsets[1:] = np.cumsum(counts)[:-1]
        gather = np.repeat(starts - offsets, counts) + np.arange(int(counts.sum()))
        return TeacherBatch(
            layout=Layout([self.graphs[i] for i in ids], table),
            indices=torch.from_numpy(self.bits[gather].astype(np.int64)),
            offsets=torch.from_numpy(offsets),
            targets=torch.from_numpy(np.where(valid, self.actions[state_ids], -1)),
            rows=torch.from_numpy(rows),
            valid=torch.from_numpy(valid),
            lengths=torch.from_numpy(lengths.astype(np.float32)),
            active=[int(n) for n in active],
        )


def has_word(command: str, word: str) -> bool:
    """Whether `word` is one of the command's words (not a substring: "walk" is not in "walking")."""
    return word in command.split()


def word_repeats(commands: Sequence[str], word: str, factor: int) -> np.ndarray | None:
    """How many times each episode appears per epoch when the episodes whose command has
    `word` are oversampled `factor` times (TrainConfig.oversample_word); None: once each."""
    if not word or factor == 1:
        return None
    has = np.fromiter((has_word(command, word) for command in commands), dtype=bool, count=len(commands))
    if not has.any():
        raise ValueError(f"no train command has {quoted(word)} to oversample")
    return np.where(has, factor, 1)


def batch_order(store: Sized, batch_size: int, batching: str, rng: np.random.Generator,
                repeats: np.ndarray | None = None) -> list[np.ndarray]:
    """One epoch of batches (`repeats`: each episode's appearances per epoch, `word_repeats`).

    mixed: a random permutation cut into batches (graphs of any commands mixed).
    per_command: the original scheme (CG; quirk Q9, docs/model.md) — batches hold one command,
    each command's episodes reshuffled every epoch (the original fixed chunk contents
    after one initial shuffle), then the order of all chunks shuffled.
    """
    ids = np.arange(len(store)) if repeats is None else np.repeat(np.arange(len(store)), repeats)
    if batching == "mixed":
        perm = rng.permutation(ids)
        return [perm[i : i + batch_size] for i in range(0, len(perm), batch_size)]
    if batching == "per_command":
        by_command: dict[str, list[int]] = {}
        for i in ids:
            by_command.setdefault(store.commands[i], []).append(int(i))
        chunks = []
        for command in sorted(by_command):
            idx = rng.permutation(np.asarray(by_command[command]))
            chunks += [idx[i : i + batch_size] for i in range(0, len(idx), batch_size)]
        return [chunks[i] for i in rng.permutation(len(chunks))]
    raise ValueError(f"batching must be one of {BATCHING}, got {batching!r}")


@dataclass
class EpochCursor:
    """Where training stands in the (seeded, reproducible) stream of batches."""

    epoch: int = 0
    batch: int = 0


def iterate_batches(store: EpisodeStore, batch_size: int, batching: str, seed: int,
                    cursor: EpochCursor, repeats: np.ndarray | None = None) -> Iterator[tuple[EpochCursor, np.ndarray]]:
    """Endless batches; epoch e uses rng(seed, e), so resuming at `cursor` replays nothing."""
    while True:
        order = batch_order(store, batch_size, batching, np.random.default_rng([seed, cursor.epoch]), repeats)
        while cursor.batch < len(order):
            ids = order[cursor.batch]
            cursor = EpochCursor(cursor.epoch, cursor.batch + 1)
            yield cursor, ids
        cursor = EpochCursor(cursor.epoch + 1, 0)
