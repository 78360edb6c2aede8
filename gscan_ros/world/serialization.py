"""gSCAN `situation` JSON <-> `Situation` (LauraRuis/groundedSCAN `Situation.to_representation`).

The dataset writes positions and sizes as strings, `agent_direction` as an int,
`distance_to_target` as a string and `placed_objects` as a dict keyed "0", "1", ...
Parsing is strict so that `situation_to_json(situation_from_json(d)) == d` holds
for every accepted `d`; every rejection is a `SituationError` naming the field,
e.g. ``situation.agent_position.row: expected an integer string, got 'x'``.

Object `vector` strings are checked against the released channel order: a file
written with another shape/color order (quirk Q14, docs/model.md) is rejected, not silently
re-interpreted.
"""
from __future__ import annotations

from typing import Any

from gscan_ros.errors import SituationError, quoted
from gscan_ros.world.types import (
    COLORS,
    DIRECTIONS_TO_TARGET,
    NUM_OBJECT_CHANNELS,
    SHAPES,
    SIZES,
    Heading,
    Position,
    Situation,
    WorldObject,
    object_vector,
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


def _int_string(value: Any, where: str) -> int:
    if not isinstance(value, str) or not value.isdigit() or not value.isascii():
        raise SituationError(f"{where}: expected an integer string, got {_describe(value)}")
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
        raise SituationError(f"{where}.object.size: expected 1-4, got {size}")
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
