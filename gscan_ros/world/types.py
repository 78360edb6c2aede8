"""Constant tables and small immutable types of the gSCAN world (GSCAN_SPEC §1, §2, §4).

Everything here is pure data; the physics lives in `world.py`, the planner in
`planner.py`. Positions are (row, col) as in the dataset JSON (row 0 = north).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from typing import NamedTuple

GRID_SIZE = 6

# Released channel order of the 16-channel encoding (GSCAN_SPEC §4): sizes 1-4,
# shapes, colors, agent, heading E S W N. Pinned as constants (quirk Q14).
SIZES: tuple[int, ...] = (1, 2, 3, 4)
SHAPES: tuple[str, ...] = ("square", "cylinder", "circle")
COLORS: tuple[str, ...] = ("yellow", "green", "red", "blue")
NUM_OBJECT_CHANNELS = len(SIZES) + len(SHAPES) + len(COLORS)  # 11
AGENT_CHANNEL = NUM_OBJECT_CHANNELS  # 11
HEADING_CHANNEL0 = AGENT_CHANNEL + 1  # 12..15 = E, S, W, N
NUM_CHANNELS = NUM_OBJECT_CHANNELS + 1 + 4  # 16

# Weight classes: sizes 1-2 light (moves every primitive), 3-4 heavy (every second).
HEAVY_MIN_SIZE = 3

# Command vocabulary (GSCAN_SPEC §5). Two-word adverbs are single tokens.
INTRANSITIVE_VERBS: tuple[str, ...] = ("walk",)
TRANSITIVE_VERBS: tuple[str, ...] = ("push", "pull")
VERBS = INTRANSITIVE_VERBS + TRANSITIVE_VERBS
ADVERBS: tuple[str, ...] = ("cautiously", "while spinning", "hesitantly", "while zigzagging")
NOUNS: tuple[str, ...] = ("circle", "square", "cylinder")
COLOR_ADJECTIVES: tuple[str, ...] = ("red", "green", "yellow", "blue")
SIZE_ADJECTIVES: tuple[str, ...] = ("big", "small")
FUNCTION_WORDS: tuple[str, ...] = ("to", "a")


class Heading(IntEnum):
    """Agent heading; the integer is the dataset's `agent_direction` (0 = east)."""

    EAST = 0
    SOUTH = 1
    WEST = 2
    NORTH = 3

    @property
    def delta(self) -> tuple[int, int]:
        """(d_row, d_col) of one step along this heading."""
        return _HEADING_DELTA[self]


_HEADING_DELTA = {
    Heading.EAST: (0, 1),
    Heading.SOUTH: (1, 0),
    Heading.WEST: (0, -1),
    Heading.NORTH: (-1, 0),
}


class Action(IntEnum):
    """The six gSCAN target tokens, plus EOS which only models emit."""

    WALK = 0
    TURN_LEFT = 1
    TURN_RIGHT = 2
    PUSH = 3
    PULL = 4
    STAY = 5
    EOS = 6

    @property
    def token(self) -> str:
        return _ACTION_TOKENS[self]

    @classmethod
    def from_token(cls, token: str) -> "Action":
        """Parse a dataset token ("turn left", "<eos>", ...); raises InvalidActionError."""
        from gscan_ros.errors import InvalidActionError

        try:
            return _TOKEN_TO_ACTION[token.strip()]
        except (KeyError, AttributeError):
            known = ", ".join(repr(t) for t in _ACTION_TOKENS.values())
            raise InvalidActionError(f"unknown action {token!r}; known actions: {known}") from None


_ACTION_TOKENS = {
    Action.WALK: "walk",
    Action.TURN_LEFT: "turn left",
    Action.TURN_RIGHT: "turn right",
    Action.PUSH: "push",
    Action.PULL: "pull",
    Action.STAY: "stay",
    Action.EOS: "<eos>",
}
_TOKEN_TO_ACTION = {v: k for k, v in _ACTION_TOKENS.items()}
WORLD_ACTIONS: tuple[Action, ...] = tuple(a for a in Action if a is not Action.EOS)


class Position(NamedTuple):
    row: int
    col: int


@dataclass(frozen=True)
class WorldObject:
    """An object as placed in the world: shape, color, integer size 1-4, cell."""

    shape: str
    color: str
    size: int
    position: Position

    @property
    def heavy(self) -> bool:
        return self.size >= HEAVY_MIN_SIZE


@dataclass(frozen=True)
class Situation:
    """An initial world state in gSCAN terms (round-trips the dataset `situation` JSON).

    `placed_objects` keeps the JSON order (the target is usually first) but object
    order carries no meaning (quirk Q19); compare with `object_set()`.
    """

    agent_position: Position
    agent_direction: Heading
    placed_objects: tuple[WorldObject, ...]
    target_object: WorldObject | None = None
    grid_size: int = GRID_SIZE
    # Stored as in the JSON (derived, but kept so round-trips are exact).
    direction_to_target: str | None = None
    distance_to_target: int | None = None
    extra: dict = field(default_factory=dict, compare=False, hash=False, repr=False)

    def object_set(self) -> frozenset[WorldObject]:
        return frozenset(self.placed_objects)
