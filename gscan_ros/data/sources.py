"""Where the world simulator's situations come from: a dataset split, or seeded sampling.

Both sources are sequences: the node starts at `index` (or `seed`) and each
`reset_world` call moves to the next one, so a reset is reproducible from the
parameters alone. The data layer does the work (dataset/bag streaming, the generator's
command/target/layout sampling, the planner); this module only picks the item.
"""
from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from gscan_ros.data.episode import Episode
from gscan_ros.errors import DatasetFormatError
from gscan_ros.world.types import GRID_SIZE, SUPPORTED_GRID_SIZES


@dataclass
class DatasetSource:
    """Episodes `index`, `index + 1`, ... of one split of a dataset.txt or bag (wraps around).

    The file is streamed once, in order; it is reopened only when the split runs out or
    reading it failed. A malformed example fails its own `next()` with the reason, and
    the next call serves the example after it.
    """

    path: str
    split: str
    index: int = 0
    _position: int = field(init=False, repr=False)  # the example of the split the next call serves
    _loaders: Iterator[Callable[[], Episode]] | None = field(default=None, init=False, repr=False)
    _started: bool = field(default=False, init=False, repr=False)  # some example was reached: the end wraps

    def __post_init__(self) -> None:
        self._position = self.index

    def next(self) -> Episode:
        load = self._next_loader()
        self._position += 1  # also past a malformed example: its error is this call's
        return load()

    def _next_loader(self) -> Callable[[], Episode]:
        from gscan_ros.data.io import iter_episode_loaders

        try:
            if self._loaders is None:
                self._loaders = itertools.islice(iter_episode_loaders(self.path, [self.split]), self._position, None)
            load = next(self._loaders, None)
            if load is None and not self._started and self._position:
                raise DatasetFormatError(f"{self.path}: split {self.split!r} has no example {self._position} "
                                         f"(the index is past its end)")
            if load is None:  # past the end of the split: start over
                self._loaders, self._position = iter_episode_loaders(self.path, [self.split]), 0
                load = next(self._loaders, None)
                if load is None:
                    raise DatasetFormatError(f"{self.path}: split {self.split!r} has no examples")
        except Exception:
            self._loaders = None  # a failed stream is closed: the next call reopens it at the same example
            raise
        self._started = True
        return load

    def describe(self, episode: Episode) -> str:
        return f"{self.path} split {self.split!r} example {episode.example_id}"


@dataclass
class RandomSource:
    """One gSCAN command + situation per seed (`seed`, `seed + 1`, ...), drawn as the generator does.

    The command is uniform over the 675 commands, the target uniform over the objects
    it can refer to, the agent/target layout uniform over the generator's layouts; the
    gold actions come from the planner, so the command is always satisfiable.
    """

    seed: int = 0
    grid_size: int = GRID_SIZE

    def next(self) -> Episode:
        episode = sample_episode(self.seed, self.grid_size)
        self.seed += 1
        return episode

    def describe(self, episode: Episode) -> str:
        return f"random situation (seed {episode.meta['seed']})"


def sample_episode(seed: int, grid_size: int = GRID_SIZE, command: str | None = None) -> Episode:
    """The episode of `seed` on a `grid_size` grid (see RandomSource); `command` fixes the
    command (any paraphrase of one of the 675; CommandError otherwise) instead of drawing it."""
    from gscan_ros.data.commands import COMMANDS, parse_command
    from gscan_ros.data.sampling import possible_targets, sample_placements, sample_situations
    from gscan_ros.world import demonstrate

    rng = np.random.default_rng(seed)
    if command is not None:
        from gscan_ros.language.canonical import canonicalize

        command = parse_command(canonicalize(command).canonical)  # "push the small blue cylinder" too
    else:
        command = COMMANDS[rng.integers(len(COMMANDS))]
    targets = possible_targets(command)
    target = targets[rng.integers(len(targets))]
    if grid_size not in SUPPORTED_GRID_SIZES:
        raise DatasetFormatError(f"grid_size {grid_size} is not supported "
                                 f"({SUPPORTED_GRID_SIZES[0]} to {SUPPORTED_GRID_SIZES[-1]})")
    placements = sample_placements(rng, grid_size)
    placement = placements[rng.integers(len(placements))]
    situation = sample_situations(rng, command, target, (placement,), grid_size=grid_size)[0]
    actions = tuple(demonstrate(situation, command.text))
    return Episode(command.text, situation, actions, split="random", meta={"seed": seed})


def episode_source(dataset: str, split: str, index: int, seed: int,
                   grid_size: int = GRID_SIZE) -> DatasetSource | RandomSource:
    """The dataset source when `dataset` is set, else seeded sampling on a `grid_size` grid."""
    return DatasetSource(dataset, split, index) if dataset else RandomSource(seed, grid_size)
