"""Situation sampling as the gSCAN generator does it (LauraRuis/groundedSCAN `dataset.py`).

Two stages, as in the original `generate_situations` / `initialize_world_from_spec`:

1. `sample_placements`: for every target object, agent/target layouts covering each
   relative direction (8) and Manhattan distance (1-5 straight, 2-10 diagonal), the
   inner distances resampled `num_resampling` times. The layouts of one target object
   are shared by every command that can refer to it.
2. `sample_situations`: per (command, target object), fill each layout with distractors
   that keep the referent unique: other objects of the referred shape (and color) are
   strictly larger for "small", strictly smaller for "big", and one such comparison
   object is obligatory; a fraction (0.5) of the remaining distractor groups is placed.

Everything iterates in fixed tuple orders (quirk Q18, docs/model.md) and draws from a numpy
Generator in whole blocks, so a seed alone fixes the output and sampling stays cheap.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

import numpy as np

from gscan_ros.data.commands import Command
from gscan_ros.world.types import COLORS, GRID_SIZE, SHAPES, SIZES, Heading, Position, Situation, WorldObject

STRAIGHT_DIRECTIONS = ("n", "e", "s", "w")
DIAGONAL_DIRECTIONS = ("ne", "se", "sw", "nw")
_STEP = {"n": (-1, 0), "e": (0, 1), "s": (1, 0), "w": (0, -1)}
OTHER_OBJECTS_SAMPLE_PERCENTAGE = 0.5


class ObjectSpec(NamedTuple):
    """An object without a position: integer size 1-4, color, shape."""

    size: int
    color: str
    shape: str


ALL_OBJECTS: tuple[ObjectSpec, ...] = tuple(
    ObjectSpec(size, color, shape) for shape, color, size in itertools.product(SHAPES, COLORS, SIZES)
)


@dataclass(frozen=True)
class Placement:
    """Agent and target cells of one situation layout, and how they relate."""

    agent: Position
    target: Position
    direction: str  # where the target lies seen from the agent: n, e, ..., nw
    distance: int  # Manhattan


def sample_placements(rng: np.random.Generator, grid_size: int = GRID_SIZE,
                      num_resampling: int = 5) -> tuple[Placement, ...]:
    """Layouts for one target object, in a fixed direction/distance order.

    Straight directions cover distances 1..g-1 and diagonal ones 2..2(g-1); the
    extreme distances (1 and g-1 straight, 2(g-1) diagonal) get one layout, all others
    `num_resampling`, as in the original generator (with g = 6 and 5 resamplings this
    gives 17 layouts per straight and 41 per diagonal direction, the per-direction
    counts that reproduce the released split sizes exactly).
    """
    out: list[Placement] = []
    for direction in STRAIGHT_DIRECTIONS:
        for distance in range(1, grid_size):
            repeats = num_resampling if 1 < distance < grid_size - 1 else 1
            out += [_place(rng, grid_size, ((direction, distance),), direction) for _ in range(repeats)]
    longest = 2 * (grid_size - 1)
    for direction in DIAGONAL_DIRECTIONS:
        for distance in range(2, longest + 1):
            repeats = num_resampling if distance < longest else 1
            for _ in range(repeats):
                # Split the distance over the two legs uniformly among feasible splits.
                first = int(rng.integers(max(1, distance - grid_size + 1), min(distance - 1, grid_size - 1) + 1))
                legs = ((direction[0], first), (direction[1], distance - first))
                out.append(_place(rng, grid_size, legs, direction))
    return tuple(out)


def agent_cells(grid_size: int, d_row: int, d_col: int) -> tuple[range, range]:
    """The rows and the columns an agent may stand on with its target (d_row, d_col) away on the grid."""
    return (range(max(0, -d_row), min(grid_size, grid_size - d_row)),
            range(max(0, -d_col), min(grid_size, grid_size - d_col)))


def _place(rng: np.random.Generator, grid_size: int, legs, direction: str) -> Placement:
    """An agent cell drawn uniformly among those from which the legs stay on the grid."""
    d_row = sum(_STEP[d][0] * k for d, k in legs)
    d_col = sum(_STEP[d][1] * k for d, k in legs)
    rows, cols = agent_cells(grid_size, d_row, d_col)
    agent = Position(rows[int(rng.integers(len(rows)))], cols[int(rng.integers(len(cols)))])
    target = Position(agent.row + d_row, agent.col + d_col)
    return Placement(agent, target, direction, abs(d_row) + abs(d_col))


def possible_targets(command: Command) -> tuple[ObjectSpec, ...]:
    """Objects the command can refer to: "small" targets have size 1-3, "big" ones 2-4."""
    sizes = {"small": SIZES[:-1], "big": SIZES[1:], "": SIZES}[command.size]
    colors = (command.color,) if command.color else COLORS
    return tuple(ObjectSpec(size, color, command.noun) for color in colors for size in sizes)


@dataclass(frozen=True)
class Template:
    """A distractor to draw: size and color uniformly from the given choices."""

    sizes: tuple[int, ...]
    colors: tuple[str, ...]
    shape: str


def distractors(command: Command, target: ObjectSpec) -> tuple[tuple[tuple[Template, ...], ...], tuple[Template, ...]]:
    """(groups, obligatory) of distractor templates keeping `target` the unique referent.

    A fraction of the groups is placed; obligatory templates always are.
    - bare noun: one object of random size and color per other shape;
    - color + noun: one object of random size per other (color, shape) pair;
    - size mentioned: two objects per other (color, shape) pair, where objects that
      compete for the referent (same shape, and same color if one is named) are
      strictly larger ("small") or smaller ("big"); one competitor of the target's
      color is obligatory, so "small"/"big" always compares something.
    """
    noun = command.noun
    if not command.size:
        if not command.color:
            return tuple((Template(SIZES, COLORS, shape),) for shape in SHAPES if shape != noun), ()
        return tuple(
            (Template(SIZES, (color,), shape),)
            for shape in SHAPES for color in COLORS if (shape, color) != (noun, command.color)
        ), ()
    if command.size == "small":
        competitor_sizes = tuple(s for s in SIZES if s > target.size)
    else:
        competitor_sizes = tuple(s for s in SIZES if s < target.size)
    groups = []
    for shape in SHAPES:
        for color in COLORS:
            competes = shape == noun and (not command.color or color == command.color)
            if color == target.color and shape == noun:
                continue  # the obligatory comparison object
            sizes = competitor_sizes if competes else SIZES
            groups.append((Template(sizes, (color,), shape),) * 2)
    return tuple(groups), (Template(competitor_sizes, (target.color,), noun),)


@lru_cache(maxsize=None)
def _world_object(shape: str, color: str, size: int, cell: tuple[int, int]) -> WorldObject:
    """Objects are immutable and few (48 kinds x 36 cells): build each once."""
    return WorldObject(shape, color, size, Position(*cell))


def sample_situations(rng: np.random.Generator, command: Command, target: ObjectSpec,
                      placements: tuple[Placement, ...], select: np.ndarray | None = None,
                      grid_size: int = GRID_SIZE,
                      sample_percentage: float = OTHER_OBJECTS_SAMPLE_PERCENTAGE) -> list[Situation]:
    """Situations for the placements (those where `select` is True): the target, then
    the obligatory and the sampled distractors.

    Every distractor lands on a uniformly drawn free cell (never the agent's). All
    random numbers of the block are drawn up front, whatever `select` says, so the
    cost is a few numpy calls per block and a situation does not depend on which
    others are built.
    """
    groups, obligatory = distractors(command, target)
    n_chosen = int(len(groups) * sample_percentage)
    n_objects = len(obligatory) + sum(len(g) for g in groups[:n_chosen])  # groups are equally sized
    n = len(placements)
    group_keys = rng.random((n, len(groups)))
    attributes = rng.random((n, n_objects, 2))
    cell_keys = rng.random((n, grid_size * grid_size))
    rows = np.arange(n)
    cell_keys[rows, [p.agent.row * grid_size + p.agent.col for p in placements]] = 2.0
    cell_keys[rows, [p.target.row * grid_size + p.target.col for p in placements]] = 2.0
    chosen_groups = np.argsort(group_keys, axis=1, kind="stable")[:, :n_chosen]
    cells = np.argsort(cell_keys, axis=1, kind="stable")[:, :n_objects]

    situations = []
    for i in range(n) if select is None else np.flatnonzero(select):
        placement = placements[i]
        target_object = _world_object(target.shape, target.color, target.size, tuple(placement.target))
        templates = obligatory + tuple(t for g in chosen_groups[i] for t in groups[g])
        objects = [target_object]
        for template, (u_size, u_color), cell in zip(templates, attributes[i].tolist(), cells[i].tolist()):
            objects.append(_world_object(
                template.shape,
                template.colors[int(u_color * len(template.colors))],
                template.sizes[int(u_size * len(template.sizes))],
                divmod(cell, grid_size),
            ))
        situations.append(Situation(
            agent_position=placement.agent,
            agent_direction=Heading.EAST,
            placed_objects=tuple(objects),
            target_object=target_object,
            grid_size=grid_size,
            direction_to_target=placement.direction,
            distance_to_target=placement.distance,
        ))
    return situations
