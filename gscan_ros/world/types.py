"""Constant tables and small immutable types of the gSCAN world (as LauraRuis/groundedSCAN's
`world.py` and `gym_minigrid/minigrid.py` define them).

Pure data plus the invariants every `Situation` satisfies (checked on construction);
the physics lives in `world.py`, the planner in `planner.py`. Positions are (row, col) as in
the dataset JSON (row 0 = north).

The gSCAN `situation` JSON (groundedSCAN `Situation.to_representation`) is read and written
here too. The dataset writes positions and sizes as strings, `agent_direction` as an int,
`distance_to_target` as a string and `placed_objects` as a dict keyed "0", "1", ... Parsing is
strict so that `situation_to_json(situation_from_json(d)) == d` holds for every accepted `d`;
every rejection is a `SituationError` naming the field, e.g.
``situation.agent_position.row: expected an integer string, got 'x'``. Object `vector` strings
are checked against the released channel order: a file written with another shape/color order
(quirk Q14, docs/model.md) is rejected, not silently re-interpreted.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any, NamedTuple

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
        return situation_from_json(d)

    def to_json(self) -> dict:
        """The gSCAN `situation` dict (strings where the dataset has strings)."""
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
        raise SituationError(f"{where}: {quoted(tuple(pos))} is outside the {n}x{n} grid")


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
        raise SituationError(f"situation.grid_size: {quoted(n)} is not supported ({_describe_grid_sizes()})")
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
            f"situation.distance_to_target: {quoted(s.distance_to_target)} disagrees with the agent-target "
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


# Key order of the original writer (`Situation.to_representation`); dict equality
# ignores order, but keeping it makes re-written files diff cleanly.
SITUATION_KEYS: tuple[str, ...] = (
    "grid_size",
    "agent_position",
    "agent_direction",
    "target_object",
    "distance_to_target",
    "direction_to_target",
    "placed_objects",
    "carrying_object",
)


def _describe(value: Any) -> str:
    return quoted(value) if isinstance(value, (str, int, float, bool)) or value is None else type(value).__name__


def _field(d: Any, key: str, where: str) -> Any:
    if not isinstance(d, dict):
        raise SituationError(f"{where}: expected an object, got {_describe(d)}")
    if key not in d:
        raise SituationError(f"{where}.{key}: missing")
    return d[key]


# Digits of an integer string in a situation: its coordinates, sizes and distances have two
# at most; a longer string is refused before int() (which refuses more than 4,300 digits).
MAX_INT_DIGITS = 9


def _int_string(value: Any, where: str) -> int:
    if not isinstance(value, str) or not value.isdigit() or not value.isascii():
        raise SituationError(f"{where}: expected an integer string, got {_describe(value)}")
    if len(value) > MAX_INT_DIGITS:
        raise SituationError(f"{where}: {quoted(value)} has more than {MAX_INT_DIGITS} digits; no grid is that large")
    return int(value)


def _position(d: Any, where: str) -> Position:
    return Position(
        _int_string(_field(d, "row", where), f"{where}.row"),
        _int_string(_field(d, "column", where), f"{where}.column"),
    )


def _object(d: Any, where: str) -> WorldObject:
    spec = _field(d, "object", where)
    shape = _field(spec, "shape", f"{where}.object")
    if shape not in SHAPES:
        raise SituationError(f"{where}.object.shape: unknown shape {_describe(shape)}; known: {', '.join(SHAPES)}")
    color = _field(spec, "color", f"{where}.object")
    if color not in COLORS:
        raise SituationError(f"{where}.object.color: unknown color {_describe(color)}; known: {', '.join(COLORS)}")
    size = _int_string(_field(spec, "size", f"{where}.object"), f"{where}.object.size")
    if size not in SIZES:
        raise SituationError(f"{where}.object.size: expected 1-4, got {quoted(size)}")
    obj = WorldObject(shape, color, size, _position(_field(d, "position", where), f"{where}.position"))
    check_object_vector(obj, _field(d, "vector", where), f"{where}.vector")
    return obj


def check_object_vector(obj: WorldObject, vector: Any, where: str = "vector") -> None:
    """Reject a `vector` string that disagrees with the released channel order (`types.py`).

    A foreign file generated with another shape/color order shows up here, because
    its vectors set different bits for the same named object.
    """
    if (
        not isinstance(vector, str)
        or len(vector) != NUM_OBJECT_CHANNELS
        or set(vector) - {"0", "1"}
    ):
        raise SituationError(
            f"{where}: expected a string of {NUM_OBJECT_CHANNELS} '0'/'1' characters, got {_describe(vector)}"
        )
    expected = object_vector(obj)
    if vector != expected:
        raise SituationError(
            f"{where}: {vector!r} does not encode a {obj.color} {obj.shape} of size {obj.size} in the "
            f"released channel order (expected {expected!r}: sizes 1-4, {'/'.join(SHAPES)}, "
            f"{'/'.join(COLORS)}); the file was written with another channel order"
        )


def situation_from_json(d: Any) -> Situation:
    """Parse one gSCAN `situation` dict (see module docstring)."""
    where = "situation"
    if not isinstance(d, dict):
        raise SituationError(f"{where}: expected an object, got {_describe(d)}")
    grid_size = _field(d, "grid_size", where)
    if isinstance(grid_size, bool) or not isinstance(grid_size, int) or grid_size < 1:
        raise SituationError(f"{where}.grid_size: expected a positive integer, got {_describe(grid_size)}")
    direction = _field(d, "agent_direction", where)
    if isinstance(direction, bool) or direction not in (0, 1, 2, 3) or not isinstance(direction, int):
        raise SituationError(
            f"{where}.agent_direction: expected an integer 0-3 (E, S, W, N), got {_describe(direction)}")

    placed = _field(d, "placed_objects", where)
    if not isinstance(placed, dict):
        raise SituationError(f"{where}.placed_objects: expected an object, got {_describe(placed)}")
    keys = list(placed)
    if keys != [str(i) for i in range(len(keys))]:
        raise SituationError(f"{where}.placed_objects: keys must be '0', '1', ... in order, got {keys[:12]}")
    objects = tuple(_object(v, f"{where}.placed_objects.{k}") for k, v in placed.items())

    target_json = _field(d, "target_object", where)
    target = None if target_json is None else _object(target_json, f"{where}.target_object")
    distance_json = _field(d, "distance_to_target", where)
    distance = None if distance_json is None else _int_string(distance_json, f"{where}.distance_to_target")
    direction_to_target = _field(d, "direction_to_target", where)
    if direction_to_target is not None and direction_to_target not in DIRECTIONS_TO_TARGET:
        raise SituationError(
            f"{where}.direction_to_target: expected one of {', '.join(DIRECTIONS_TO_TARGET)} or null, "
            f"got {_describe(direction_to_target)}"
        )
    if target is None and (distance is not None or direction_to_target is not None):
        raise SituationError(f"{where}.target_object: null, but distance/direction_to_target are set")
    if target is not None and (distance is None or (direction_to_target is None and distance != 0)):
        raise SituationError(
            f"{where}.distance_to_target: distance_to_target and direction_to_target must be set "
            "when target_object is"
        )
    carrying = _field(d, "carrying_object", where)
    if carrying is not None:
        raise SituationError(f"{where}.carrying_object: expected null (gSCAN never carries), got {_describe(carrying)}")

    return Situation(
        agent_position=_position(_field(d, "agent_position", where), f"{where}.agent_position"),
        agent_direction=Heading(direction),
        placed_objects=objects,
        target_object=target,
        grid_size=grid_size,
        direction_to_target=direction_to_target,
        distance_to_target=distance,
        extra={k: v for k, v in d.items() if k not in SITUATION_KEYS},
    )


def position_to_json(pos: Position) -> dict:
    return {"row": str(pos.row), "column": str(pos.col)}


def object_to_json(obj: WorldObject) -> dict:
    return {
        "vector": object_vector(obj),
        "position": position_to_json(obj.position),
        "object": {"shape": obj.shape, "color": obj.color, "size": str(obj.size)},
    }


def situation_to_json(s: Situation) -> dict:
    """The gSCAN `situation` dict of `s` (keys in the original writer's order)."""
    target = s.target_object
    out = {
        "grid_size": s.grid_size,
        "agent_position": position_to_json(s.agent_position),
        "agent_direction": int(s.agent_direction),
        "target_object": None if target is None else object_to_json(target),
        "distance_to_target": None if s.distance_to_target is None else str(s.distance_to_target),
        "direction_to_target": s.direction_to_target,
        "placed_objects": {str(i): object_to_json(o) for i, o in enumerate(s.placed_objects)},
        "carrying_object": None,
    }
    out.update(s.extra)
    return out
