"""Situation <-> gSCAN `situation` JSON: exact round trips, vectors, field-named errors."""
import copy
import json
from pathlib import Path

import pytest

from gscan_ros.errors import QUOTE_CHARS, SituationError
from gscan_ros.world import Heading, Position, Situation, World, WorldObject, check_object_vector, object_vector


def _obj(shape, color, size, row, col):
    return {
        "vector": object_vector(WorldObject(shape, color, size, Position(row, col))),
        "position": {"row": str(row), "column": str(col)},
        "object": {"shape": shape, "color": color, "size": str(size)},
    }


# The situation of the real compositional example in gSCAN's `example_prediction.json`
# ("push a green small square cautiously"), released vector strings written out literally.
REAL_SITUATION = json.loads((Path(__file__).parent / "fixtures" / "real_situation.json").read_text())

# A walk example built like the generator's "color only" form (target + 5 objects), SW target.
BUILT_SITUATION = {
    "grid_size": 6,
    "agent_position": {"row": "1", "column": "5"},
    "agent_direction": 0,
    "target_object": _obj("circle", "blue", 4, 4, 2),
    "distance_to_target": "6",
    "direction_to_target": "sw",
    "placed_objects": {
        "0": _obj("circle", "blue", 4, 4, 2),
        "1": _obj("circle", "red", 2, 0, 0),
        "2": _obj("square", "blue", 1, 5, 5),
        "3": _obj("cylinder", "green", 3, 2, 3),
        "4": _obj("square", "yellow", 2, 3, 0),
        "5": _obj("cylinder", "yellow", 4, 0, 4),
    },
    "carrying_object": None,
}


@pytest.mark.parametrize("d", [REAL_SITUATION, BUILT_SITUATION], ids=["real", "built"])
def test_round_trip_is_exact(d):
    s = Situation.from_json(copy.deepcopy(d))
    out = s.to_json()
    assert out == d
    assert list(out) == list(d)  # the original writer's key order
    assert json.dumps(out, sort_keys=False) == json.dumps(d, sort_keys=False)


def test_real_example_parses_to_typed_state():
    s = Situation.from_json(REAL_SITUATION)
    assert s.agent_position == Position(2, 0) and s.agent_direction is Heading.EAST
    assert s.target_object == WorldObject("square", "green", 1, Position(1, 1))
    assert s.distance_to_target == 2 and s.direction_to_target == "ne"
    assert len(s.placed_objects) == 12


def test_derived_fields_are_computed_for_new_situations():
    target = WorldObject("circle", "red", 2, Position(0, 5))
    s = Situation(Position(3, 1), Heading.EAST, (target,), target)
    assert (s.distance_to_target, s.direction_to_target) == (7, "ne")
    assert s.to_json()["distance_to_target"] == "7"


@pytest.mark.parametrize(
    "obj, vector",
    [
        (("square", "green", 1), "10001000100"),
        (("cylinder", "red", 3), "00100100010"),
        (("circle", "yellow", 3), "00100011000"),
        (("cylinder", "blue", 2), "01000100001"),
    ],
)
def test_spec_vector_strings(obj, vector):
    o = WorldObject(*obj, Position(0, 0))
    assert object_vector(o) == o.vector == vector
    grid = World(Situation(Position(5, 5), Heading.EAST, (o,))).encode()
    assert "".join(str(b) for b in grid[0, 0, :11]) == vector


def test_foreign_channel_order_is_rejected():
    d = copy.deepcopy(REAL_SITUATION)
    # Generator CLI default color order red, green, yellow, blue (quirk Q14): green -> bit 8 of 7..10 shifts.
    d["placed_objects"]["1"]["vector"] = "01000100100"
    with pytest.raises(SituationError, match=r"placed_objects\.1\.vector: .*another channel order"):
        Situation.from_json(d)
    with pytest.raises(SituationError, match="12 characters|11 '0'/'1'"):
        check_object_vector(WorldObject("square", "green", 1, Position(0, 0)), "1000100010")


def _set(d, path, value):
    *head, last = path
    for k in head:
        d = d[k]
    if value is KeyError:
        del d[last]
    else:
        d[last] = value


@pytest.mark.parametrize(
    "path, value, message",
    [
        (("agent_position", "row"), "x", r"situation\.agent_position\.row: expected an integer string, got 'x'"),
        (("agent_position", "column"), 3, r"situation\.agent_position\.column: expected an integer string, got 3"),
        (("agent_position",), KeyError, r"situation\.agent_position: missing"),
        (("agent_direction",), "0", r"situation\.agent_direction: expected an integer 0-3"),
        (("agent_direction",), 4, r"situation\.agent_direction: expected an integer 0-3"),
        (("grid_size",), "6", r"situation\.grid_size: expected a positive integer"),
        (("grid_size",), 100_000, r"situation\.grid_size: 100000 is not supported \(supported: 4 to 16\)"),
        (("grid_size",), 3, r"situation\.grid_size: 3 is not supported"),
        (("distance_to_target",), 2, r"situation\.distance_to_target: expected an integer string"),
        (("distance_to_target",), "3", r"situation\.distance_to_target: 3 disagrees"),
        (("direction_to_target",), "up", r"situation\.direction_to_target: expected one of"),
        (("direction_to_target",), "sw", r"situation\.direction_to_target: 'sw' disagrees"),
        (("carrying_object",), {"shape": "circle"}, r"situation\.carrying_object: expected null"),
        (("placed_objects", "3", "object", "shape"), "cube", r"placed_objects\.3\.object\.shape: unknown shape 'cube'"),
        (("placed_objects", "3", "object", "color"), "pink", r"placed_objects\.3\.object\.color: unknown color"),
        (("placed_objects", "3", "object", "size"), "5", r"placed_objects\.3\.object\.size: expected 1-4"),
        (("placed_objects", "3", "position", "row"), "6", r"placed_objects\.3\.position: \(6, 4\) is outside"),
        (("placed_objects", "3", "position"), {"row": "0", "column": "3"},
         r"placed_objects\.3\.position: cell \(0, 3\) already holds placed object 1"),
        (("placed_objects", "3", "vector"), None, r"placed_objects\.3\.vector: expected a string of 11"),
        (("placed_objects", "13"), REAL_SITUATION["placed_objects"]["0"], r"placed_objects: keys must be"),
        (("placed_objects",), [], r"situation\.placed_objects: expected an object, got list"),
        (("target_object", "position", "column"), "2",
         r"situation\.target_object\.vector|not among the placed objects"),
        # numbers beyond any grid: quoted short, never converted whole (int() refuses 4,300 digits)
        pytest.param(("placed_objects", "3", "object", "size"), "9" * 5000,
                     r"placed_objects\.3\.object\.size: '9{80}'… \(5,000 characters\) has more than 9 digits",
                     id="size of 5000 digits"),
        pytest.param(("placed_objects", "3", "position", "row"), "9" * 400,
                     r"placed_objects\.3\.position\.row: '9{80}'… \(400 characters\) has more than 9 digits",
                     id="row of 400 digits"),
        pytest.param(("distance_to_target",), "9" * 400,
                     r"situation\.distance_to_target: '9{80}'… \(400 characters\)", id="distance of 400 digits"),
        pytest.param(("grid_size",), 10**400, r"situation\.grid_size: 10+\.\.\.0+ is not supported",
                     id="grid_size of 401 digits"),
    ],
)
def test_malformed_input_names_the_field(path, value, message):
    d = copy.deepcopy(REAL_SITUATION)
    _set(d, path, value)
    with pytest.raises(SituationError, match=message) as error:
        Situation.from_json(d)
    assert len(str(error.value)) < 4 * QUOTE_CHARS  # one short line, whatever the value's size


def test_non_dict_situation():
    with pytest.raises(SituationError, match="situation: expected an object, got list"):
        Situation.from_json([])


def test_unknown_keys_survive_the_round_trip():
    d = copy.deepcopy(BUILT_SITUATION)
    d["note"] = {"source": "test"}
    assert Situation.from_json(d).to_json() == d


def test_snapshot_round_trips_mid_episode():
    world = World(Situation.from_json(BUILT_SITUATION))
    for a in ["turn left", "turn left", "walk", "walk", "walk", "turn left", "walk", "walk", "walk", "pull"]:
        world.step(a)
    snap = world.snapshot()
    assert snap.agent_position == Position(4, 2)  # agent on the (heavy, not yet moved) target
    assert snap.distance_to_target == 0 and snap.direction_to_target is None
    assert Situation.from_json(snap.to_json()) == snap
    world.step("pull")  # second primitive: the heavy circle moves back (north) with the agent
    snap = world.snapshot()
    assert snap.target_object.position == Position(3, 2) == snap.agent_position
    assert Situation.from_json(snap.to_json()) == snap


def test_unsupported_grid_size_is_one_error_before_any_allocation():
    """A grid_size from a bad file must not reach World (which allocates grid_size^2 cells)."""
    from gscan_ros.world.types import SUPPORTED_GRID_SIZES

    assert list(SUPPORTED_GRID_SIZES) == list(range(4, 17))  # 6 (compositional) and 12 (split I) inside
    with pytest.raises(SituationError, match=r"situation\.grid_size: 100000 is not supported \(supported: 4 to 16\)"):
        Situation(Position(0, 0), Heading.EAST, (), grid_size=100_000)
