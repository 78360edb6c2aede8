"""Episode: one command-following demonstration, the unit of training, bags and replay."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gscan_ros.world.types import Action, Situation


@dataclass(frozen=True)
class Episode:
    """A command, its initial situation and the gold actions (without EOS).

    Per-step observations are derived (`states()`): the initial encoding plus one
    after each gold action, T+1 in total, replayed with the one World physics.
    """

    command: str  # space-joined gSCAN tokens, e.g. "walk to a red small circle while spinning"
    situation: Situation
    actions: tuple[Action, ...]
    split: str = "train"
    example_id: int | None = None
    meta: dict = field(default_factory=dict, compare=False, hash=False, repr=False)

    def states(self) -> np.ndarray:
        """uint8[T+1, 6, 6, 16]: encoding of the initial state and after each action."""
        from gscan_ros.world.world import World

        world = World(self.situation)
        out = np.empty((len(self.actions) + 1, *world.encode().shape), dtype=np.uint8)
        out[0] = world.encode()
        for t, action in enumerate(self.actions, start=1):
            world.step(action)
            out[t] = world.encode()
        return out
