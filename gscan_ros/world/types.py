"""Constant tables and small immutable types of the gSCAN world (as LauraRuis/groundedSCAN's
`world.py` and `gym_minigrid/minigrid.py` define them).

Pure data plus the invariants every `Situation` satisfies (checked on construction);
the physics lives in `world.py`, the planner in `planner.py`. Positions are (row, col) as in
the dataset JSON (row 0 = north).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from typing import NamedTuple

from gscan_ros.errors import SituationError, quoted

GRID_SIZE = 6  # the compositional splits' grid; split I is released on 12x12
# Grid sizes the project supports end to end (world, generator, model, nodes): a size
# from a bad file is one clear error, not a huge allocation.
SUPPORTED_GRID_SIZES = range(4, 17)

# Released channel order of the 16-channel encoding (groundedSCAN `Grid.encode`): sizes 1-4,
# shapes, colors, agent, heading E S W N. Pinned as constants (quirk Q14, docs/model.md).
SIZES: tuple[int, ...] = (1, 2, 3, 4)
SHAPES: tuple[str, ...] = ("square", "cylinder", "circle")
COLORS: tuple[str, ...] = ("yellow", "green", "red", "blue")
NUM_OBJECT_CHANNELS = len(SIZES) + len(SHAPES) + len(COLORS)  # 11
AGENT_CHANNEL = NUM_OBJECT_CHANNELS  # 11
HEADING_CHANNEL0 = AGENT_CHANNEL + 1  # 12..15 = E, S, W, N
NUM_CHANNELS = NUM_OBJECT_CHANNELS + 1 + 4  # 16

# Weight classes: sizes 1-2 light (moves every primitive), 3-4 heavy (every second).
HEAVY_MIN_SIZE = 3
LIGHT_MOMENTUM = 1
HEAVY_MOMENTUM = 2

# Command vocabulary (groundedSCAN `grammar.py`). Two-word adverbs are single tokens.
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
            raise InvalidActionError(f"unknown action {quoted(token)}; known actions: {known}") from None


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

    def __post_init__(self) -> None:
        if type(self.position) is not Position:
            object.__setattr__(self, "position", Position(*self.position))

    @property
    def heavy(self) -> bool:
        return self.size >= HEAVY_MIN_SIZE

    @property
    def momentum_threshold(self) -> int:
        """Push/pull primitives needed per cell of movement (groundedSCAN `WEIGHT_TO_MOMENTUM`)."""
        return HEAVY_MOMENTUM if self.heavy else LIGHT_MOMENTUM

    @property
    def vector(self) -> str:
        """The 11-character object `vector` string of the dataset, released channel order."""
        return object_vector(self)


@dataclass(frozen=True)
class Situation:
    """An initial world state in gSCAN terms (round-trips the dataset `situation` JSON).

    `placed_objects` keeps the JSON order (the target is usually first) but object
    order carries no meaning (quirk Q19, docs/model.md); compare with `object_set()`.

    Construction validates the state (cells inside the grid, one object per cell,
    known attributes, target among the placed objects) and fills the derived
    `distance_to_target` / `direction_to_target` when they are not given; when they
    are given they must agree with the positions. Violations raise `SituationError`.
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

    def __post_init__(self) -> None:
        _validate_situation(self)

    def object_set(self) -> frozenset[WorldObject]:
        return frozenset(self.placed_objects)

    @classmethod
    def from_json(cls, d: dict) -> "Situation":
        """Parse a gSCAN `situation` dict; raises SituationError naming the bad field."""
        from gscan_ros.world.serialization import situation_from_json

        return situation_from_json(d)

    def to_json(self) -> dict:
        """The gSCAN `situation` dict (strings where the dataset has strings)."""
        from gscan_ros.world.serialization import situation_to_json

        return situation_to_json(self)


# Object `vector` strings: one-hot size, shape, color blocks (groundedSCAN `generate_objects`).
_SIZE_INDEX = {s: i for i, s in enumerate(SIZES)}
_SHAPE_INDEX = {s: len(SIZES) + i for i, s in enumerate(SHAPES)}
_COLOR_INDEX = {c: len(SIZES) + len(SHAPES) + i for i, c in enumerate(COLORS)}


def object_channels(shape: str, color: str, size: int) -> tuple[int, int, int]:
    """The three object channels (size, shape, color) set for an object."""
    return _SIZE_INDEX[size], _SHAPE_INDEX[shape], _COLOR_INDEX[color]


def _vector_string(shape: str, color: str, size: int) -> str:
    bits = ["0"] * NUM_OBJECT_CHANNELS
    for ch in object_channels(shape, color, size):
        bits[ch] = "1"
    return "".join(bits)


_VECTORS = {
    (shape, color, size): _vector_string(shape, color, size)
    for shape in SHAPES
    for color in COLORS
    for size in SIZES
}


def object_vector(obj: WorldObject) -> str:
    """11-character `vector` string of an object in the released channel order."""
    return _VECTORS[obj.shape, obj.color, obj.size]


# (sign of column offset, sign of northward offset) -> dataset direction string.
_DIRECTION_NAMES = {
    (1, 0): "e", (0, 1): "n", (-1, 0): "w", (0, -1): "s",
    (1, 1): "ne", (1, -1): "se", (-1, -1): "sw", (-1, 1): "nw",
}
DIRECTIONS_TO_TARGET: tuple[str, ...] = tuple(_DIRECTION_NAMES.values())


def _sign(x: int) -> int:
    return (x > 0) - (x < 0)


def direction_between(start: Position, goal: Position) -> str | None:
    """Compass direction (n, ne, ... ) from start to goal; None when they coincide."""
    return _DIRECTION_NAMES.get((_sign(goal.col - start.col), _sign(start.row - goal.row)))


def manhattan(a: Position, b: Position) -> int:
    return abs(a.row - b.row) + abs(a.col - b.col)


def _check_object(obj: WorldObject, where: str, n: int) -> None:
    if obj.shape not in SHAPES:
        raise SituationError(f"{where}.shape: unknown shape {quoted(obj.shape)}; known: {', '.join(SHAPES)}")
    if obj.color not in COLORS:
        raise SituationError(f"{where}.color: unknown color {quoted(obj.color)}; known: {', '.join(COLORS)}")
    if obj.size not in SIZES or isinstance(obj.size, bool):
        raise SituationError(f"{where}.size: expected an integer 1-4, got {quoted(obj.size)}")
    _check_position(obj.position, f"{where}.position", n)


def _check_position(pos: Position, where: str, n: int) -> None:
    if not (0 <= pos.row < n and 0 <= pos.col < n):
        raise SituationError(f"{where}: {tuple(pos)} is outside the {n}x{n} grid")


def _describe_grid_sizes() -> str:
    low, high = SUPPORTED_GRID_SIZES[0], SUPPORTED_GRID_SIZES[-1]
    return f"supported: {low}" if low == high else f"supported: {low} to {high}"


def _validate_situation(s: Situation) -> None:
    """Normalise field types and enforce the invariants listed on `Situation`."""
    setf = object.__setattr__
    n = s.grid_size
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise SituationError(f"situation.grid_size: expected a positive integer, got {quoted(n)}")
    if n not in SUPPORTED_GRID_SIZES:
        raise SituationError(f"situation.grid_size: {n} is not supported ({_describe_grid_sizes()})")
    setf(s, "agent_position", Position(*s.agent_position))
    _check_position(s.agent_position, "situation.agent_position", n)
    try:
        setf(s, "agent_direction", Heading(s.agent_direction))
    except ValueError:
        raise SituationError(
            f"situation.agent_direction: expected 0-3 (E, S, W, N), got {s.agent_direction!r}"
        ) from None
    setf(s, "placed_objects", tuple(s.placed_objects))
    occupied: dict[Position, int] = {}
    for i, obj in enumerate(s.placed_objects):
        where = f"situation.placed_objects.{i}"
        _check_object(obj, where, n)
        other = occupied.setdefault(obj.position, i)
        if other != i:
            raise SituationError(
                f"{where}.position: cell {tuple(obj.position)} already holds placed object {other}"
            )
    target = s.target_object
    if target is None:
        return
    if target not in s.placed_objects:
        raise SituationError(f"situation.target_object: {target} is not among the placed objects")
    distance = manhattan(s.agent_position, target.position)
    if s.distance_to_target is None:
        setf(s, "distance_to_target", distance)
    elif s.distance_to_target != distance:
        raise SituationError(
            f"situation.distance_to_target: {s.distance_to_target} disagrees with the agent-target "
            f"Manhattan distance {distance}"
        )
    direction = direction_between(s.agent_position, target.position)
    if s.direction_to_target is None:
        setf(s, "direction_to_target", direction)
    elif s.direction_to_target != direction:
        raise SituationError(
            f"situation.direction_to_target: {s.direction_to_target!r} disagrees with the agent and "
            f"target positions ({direction!r})"
        )
