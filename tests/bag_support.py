"""Episodes for the bag tests: random but valid (walk / turn / stay, never off the grid)."""
from __future__ import annotations

import random

from gscan_ros.data.episode import Episode
from gscan_ros.world.types import COLORS, SHAPES, Action, Heading, Position, Situation, WorldObject

SPLITS = ("train", "test", "visual")


def _route(rng: random.Random, start: Position, heading: Heading, length: int) -> tuple[Action, ...]:
    row, col, actions = start.row, start.col, []
    for _ in range(length):
        action = rng.choice((Action.WALK, Action.WALK, Action.TURN_LEFT, Action.TURN_RIGHT, Action.STAY))
        if action is Action.WALK:
            d_row, d_col = heading.delta
            if not (0 <= row + d_row < 6 and 0 <= col + d_col < 6):
                action = Action.TURN_LEFT
            else:
                row, col = row + d_row, col + d_col
        if action is Action.TURN_LEFT:
            heading = Heading((heading - 1) % 4)
        elif action is Action.TURN_RIGHT:
            heading = Heading((heading + 1) % 4)
        actions.append(action)
    return tuple(actions)


def make_episode(rng: random.Random, index: int, max_len: int = 20) -> Episode:
    cells = rng.sample([Position(r, c) for r in range(6) for c in range(6)], 4)
    objects = tuple(
        WorldObject(shape, rng.choice(COLORS), rng.randint(1, 4), cell)
        for shape, cell in zip(SHAPES, cells[1:])
    )
    target = objects[0]
    situation = Situation(
        agent_position=cells[0],
        agent_direction=Heading.EAST,
        placed_objects=objects,
        target_object=target,
        direction_to_target=None,
        distance_to_target=abs(target.position.row - cells[0].row) + abs(target.position.col - cells[0].col),
    )
    actions = _route(rng, cells[0], Heading.EAST, rng.randint(0, max_len))
    command = f"walk to a {target.color} {target.shape}"
    return Episode(command, situation, actions, split=SPLITS[index % len(SPLITS)], example_id=index, meta={"n": index})


def make_episodes(count: int, seed: int = 0, max_len: int = 20) -> list[Episode]:
    rng = random.Random(seed)
    return [make_episode(rng, i, max_len) for i in range(count)]
