"""Where the world simulator's situations come from: a dataset split, or seeded sampling.

Both sources are sequences: the node starts at `index` (or `seed`) and each
`reset_world` call moves to the next one, so a reset is reproducible from the
parameters alone. The data layer does the work (dataset/bag streaming, the generator's
command/target/layout sampling, the planner); this module only picks the item.
"""
from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from gscan_ros.data.episode import Episode
from gscan_ros.errors import DatasetFormatError


@dataclass
class DatasetSource:
    """Episodes `index`, `index + 1`, ... of one split of a dataset.txt or bag (wraps around).

    The file is streamed once, in order; it is reopened only when the split runs out.
    """

    path: str
    split: str
    index: int = 0
    _episodes: Iterator[Episode] | None = field(default=None, init=False, repr=False)

    def next(self) -> Episode:
        from gscan_ros.data.io import iter_episodes

        if self._episodes is None:
            self._episodes = itertools.islice(iter_episodes(self.path, splits=[self.split]), self.index, None)
        episode = next(self._episodes, None)
        if episode is None:  # past the end of the split: start over
            self._episodes = iter(iter_episodes(self.path, splits=[self.split]))
            episode = next(self._episodes, None)
            if episode is None:
                raise DatasetFormatError(f"{self.path}: split {self.split!r} has no examples")
        return episode

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

    def next(self) -> Episode:
        episode = sample_episode(self.seed)
        self.seed += 1
        return episode

    def describe(self, episode: Episode) -> str:
        return f"random situation (seed {episode.meta['seed']})"


def sample_episode(seed: int) -> Episode:
    """The episode of `seed` (see RandomSource)."""
    from gscan_ros.data.commands import COMMANDS
    from gscan_ros.data.sampling import possible_targets, sample_placements, sample_situations
    from gscan_ros.world import demonstrate

    rng = np.random.default_rng(seed)
    command = COMMANDS[rng.integers(len(COMMANDS))]
    targets = possible_targets(command)
    target = targets[rng.integers(len(targets))]
    placements = sample_placements(rng)
    placement = placements[rng.integers(len(placements))]
    situation = sample_situations(rng, command, target, (placement,))[0]
    actions = tuple(demonstrate(situation, command.text))
    return Episode(command.text, situation, actions, split="random", meta={"seed": seed})


def episode_source(dataset: str, split: str, index: int, seed: int) -> DatasetSource | RandomSource:
    """The dataset source when `dataset` is set, else seeded sampling."""
    return DatasetSource(dataset, split, index) if dataset else RandomSource(seed)
