"""Planner: worked examples of the original planner
(github.com/LauraRuis/groundedSCAN), turn rules, manners, referents."""
import pytest

from gscan_ros.errors import CommandError, SituationError
from gscan_ros.world import (
    Action,
    CommandFrame,
    Heading,
    Position,
    Situation,
    World,
    WorldObject,
    demonstrate,
    resolve_target,
    split_command,
    turns,
)

P = Position
L, R, W, S = "turn left", "turn right", "walk", "stay"


def situation(agent, objects, target=0, heading=Heading.EAST):
    objs = tuple(WorldObject(shape, color, size, P(*pos)) for shape, color, size, pos in objects)
    return Situation(P(*agent), heading, objs, None if target is None else objs[target])


def plan(sit, command):
    return [a.token for a in demonstrate(sit, command)]


# ---- route and turns ------------------------------------------------------------------
def test_route_example_horizontal_first():
    s = situation((3, 3), [("circle", "red", 1, (1, 1))])
    assert plan(s, "walk to a circle") == [L, L, W, W, R, W, W]


@pytest.mark.parametrize(
    "start, goal, expected",
    [
        (Heading.EAST, Heading.SOUTH, (Action.TURN_RIGHT,)),
        (Heading.EAST, Heading.NORTH, (Action.TURN_LEFT,)),
        (Heading.NORTH, Heading.EAST, (Action.TURN_RIGHT,)),
        (Heading.NORTH, Heading.WEST, (Action.TURN_LEFT,)),
        (Heading.SOUTH, Heading.WEST, (Action.TURN_RIGHT,)),
        (Heading.SOUTH, Heading.EAST, (Action.TURN_LEFT,)),
        (Heading.WEST, Heading.NORTH, (Action.TURN_RIGHT,)),
        (Heading.WEST, Heading.SOUTH, (Action.TURN_LEFT,)),
        (Heading.EAST, Heading.WEST, (Action.TURN_LEFT, Action.TURN_LEFT)),
        (Heading.WEST, Heading.EAST, (Action.TURN_LEFT, Action.TURN_LEFT)),
        (Heading.NORTH, Heading.SOUTH, (Action.TURN_LEFT, Action.TURN_LEFT)),
        (Heading.SOUTH, Heading.NORTH, (Action.TURN_LEFT, Action.TURN_LEFT)),
        (Heading.SOUTH, Heading.SOUTH, ()),
    ],
)
def test_turn_rules(start, goal, expected):
    assert turns(start, goal) == expected


@pytest.mark.parametrize(
    "agent, heading, goal, expected",
    [
        ((0, 0), Heading.EAST, (0, 3), [W, W, W]),
        ((4, 4), Heading.SOUTH, (1, 4), [L, L, W, W, W]),
        ((4, 4), Heading.NORTH, (5, 2), [L, W, W, L, W]),
        ((0, 5), Heading.WEST, (2, 5), [L, W, W]),
    ],
)
def test_straight_routes(agent, heading, goal, expected):
    s = situation(agent, [("square", "blue", 2, goal)], heading=heading)
    assert plan(s, "walk to a square") == expected


# ---- push / pull table -------------------------------------------------------------------
@pytest.mark.parametrize(
    "command, objects, expected, final",
    [
        ("push a square", [("square", "red", 1, (2, 2))], [W, W] + ["push"] * 3, (2, 5)),
        ("push a square", [("square", "red", 3, (2, 2))], [W, W] + ["push"] * 6, (2, 5)),
        ("push a square", [("square", "red", 1, (2, 2)), ("circle", "red", 1, (2, 4))], [W, W, "push"], (2, 3)),
        ("pull a square", [("square", "red", 4, (2, 3))], [W, W, W] + ["pull"] * 6, (2, 0)),
    ],
    ids=["light", "heavy", "blocked-later", "pull-heavy"],
)
def test_push_table(command, objects, expected, final):
    s = situation((2, 0), objects)
    actions = demonstrate(s, command)
    assert [a.token for a in actions] == expected
    w = World(s)
    for a in actions:
        w.step(a)
    assert w.target.position == P(*final) == w.agent_position


def test_push_blocked_from_the_start_emits_no_primitive():
    s = situation((2, 0), [("square", "red", 1, (2, 2)), ("circle", "red", 1, (2, 3))])
    assert plan(s, "push a square") == [W, W]
    s = situation((2, 0), [("square", "red", 1, (2, 5))])  # at the wall
    assert plan(s, "push a square") == [W] * 5


def test_real_example_cautious_push_blocked_by_object_to_the_north(real_situation):
    """GS example_prediction.json: the push is blocked from the start, so no push at all."""
    s = Situation.from_json(real_situation)
    assert plan(s, "push a green small square cautiously") == [L, R, R, L, W, L, L, R, R, L, W]


def test_push_direction_is_the_last_move():
    s = situation((4, 0), [("circle", "green", 2, (2, 2))])
    actions = plan(s, "push a circle")
    assert actions == [W, W, L, W, W, "push", "push"]  # vertical leg last: pushed north to row 0


# ---- manners ---------------------------------------------------------------------------------
def test_spinning_example_30_actions():
    s = situation((2, 1), [("square", "yellow", 3, (2, 3))])
    actions = plan(s, "push a square while spinning")
    spin = [L] * 4
    assert actions == (spin + [W]) * 2 + (spin + ["push"]) * 4
    assert len(actions) == 30


def test_spinning_comes_before_the_orientation_turn():
    s = situation((2, 2), [("circle", "red", 1, (3, 2))])
    assert plan(s, "walk to a circle while spinning") == [L] * 4 + [R, W]


def test_cautious_look_comes_after_the_orientation_turn():
    s = situation((2, 2), [("circle", "red", 1, (3, 3))])
    assert plan(s, "walk to a circle cautiously") == [L, R, R, L, W, R, L, R, R, L, W]


def test_cautious_push_looks_before_every_primitive():
    s = situation((2, 4), [("cylinder", "red", 3, (2, 4))])
    assert plan(s, "push a cylinder cautiously") == [L, R, R, L, "push"] * 2


def test_hesitantly_stays_after_each_walk_and_primitive():
    s = situation((2, 1), [("square", "red", 3, (2, 2)), ("circle", "red", 1, (2, 5))])
    assert plan(s, "push a square hesitantly") == [W, S, "push", S, "push", S, "push", S, "push", S]


def test_hesitantly_pull():
    s = situation((0, 0), [("circle", "blue", 1, (1, 0))])
    assert plan(s, "pull a circle hesitantly") == [R, W, S, "pull", S]  # pulled north to row 0


def test_zigzag_examples():
    s = situation((0, 0), [("circle", "red", 1, (3, 3))])
    assert plan(s, "walk to a circle while zigzagging") == [W, R, W, L, W, R, W, L, W, R, W]
    s = situation((0, 0), [("circle", "red", 1, (1, 4))])
    assert plan(s, "walk to a circle while zigzagging") == [W, R, W, L, W, W, W]


@pytest.mark.parametrize(
    "goal, expected",
    [
        # from (3, 2) facing east; the first alternating turn is right for SE/NW, left for NE/SW;
        # once in line with the goal the rest is the straight route
        ((5, 4), [W, R, W, L, W, R, W]),  # se
        ((1, 5), [W, L, W, R, W, L, W, R, W]),  # ne
        ((5, 0), [L, L, W, L, W, R, W, L, W]),  # sw
        ((0, 0), [L, L, W, R, W, L, W, R, W, W]),  # nw
    ],
    ids=["se", "ne", "sw", "nw"],
)
def test_zigzag_from_every_diagonal(goal, expected):
    s = situation((3, 2), [("square", "green", 2, goal)])
    actions = plan(s, "walk to a square while zigzagging")
    assert actions == expected
    w = World(s)
    for a in actions:
        w.step(a)
    assert w.agent_position == P(*goal)


def test_zigzag_in_line_is_the_straight_route():
    s = situation((3, 2), [("square", "green", 2, (0, 2))])
    assert plan(s, "walk to a square while zigzagging") == [L, W, W, W]


def test_zigzag_has_no_effect_on_the_interaction():
    s = situation((0, 0), [("circle", "red", 1, (1, 1))])
    assert plan(s, "push a circle while zigzagging") == [W, R, W] + ["push"] * 4


# ---- referents -------------------------------------------------------------------------------
def test_relative_size_compares_objects_with_the_same_name(real_situation):
    s = Situation.from_json(real_situation)
    assert resolve_target(s, "push a green small square") == WorldObject("square", "green", 1, P(1, 1))
    # "small square" compares squares of every color: green 1 and yellow 1 tie -> ambiguous
    with pytest.raises(SituationError, match="ambiguous"):
        resolve_target(s, "walk to a small square")
    assert resolve_target(s, "walk to a big square") == WorldObject("square", "red", 4, P(3, 1))
    assert resolve_target(s, "walk to a red small square").size == 3
    assert resolve_target(s, "walk to a blue big cylinder").size == 2


def test_missing_or_ambiguous_referent_raises(real_situation):
    s = Situation.from_json(real_situation)
    with pytest.raises(SituationError, match="no object matches 'green circle'"):
        resolve_target(s, "walk to a green circle")
    with pytest.raises(SituationError, match="ambiguous"):
        resolve_target(s, "walk to a red cylinder")  # two red cylinders of size 3


def test_demonstrate_checks_the_situation_target(real_situation):
    s = Situation.from_json(real_situation)
    with pytest.raises(SituationError, match="target_object"):
        demonstrate(s, "walk to a yellow big circle")


def test_demonstrate_without_a_situation_target_resolves_it():
    s = situation((0, 0), [("circle", "red", 1, (0, 2)), ("circle", "red", 3, (2, 0))], target=None)
    assert plan(s, "walk to a big circle") == [R, W, W]


# ---- commands -----------------------------------------------------------------------------------
def test_split_command_joins_while_tokens():
    assert split_command("walk to a red small circle while spinning") == (
        "walk", "to", "a", "red", "small", "circle", "while spinning")
    assert split_command("push,a,square,while zigzagging") == ("push", "a", "square", "while zigzagging")
    assert split_command("  Pull a  Circle ") == ("pull", "a", "circle")


def test_command_frame_round_trip_and_fields():
    f = CommandFrame.parse("push a green small square cautiously")
    assert f == CommandFrame("push", "cautiously", "green", "small", "square")
    assert f.text == "push a green small square cautiously"
    assert f.referred_target == "small green square"
    assert CommandFrame.parse("walk to a circle").referred_target == "  circle"
    assert CommandFrame.parse(("walk", "to", "a", "red", "circle")).referred_target == " red circle"
    assert CommandFrame.parse("walk to a big cylinder while zigzagging").object_name == "cylinder"


@pytest.mark.parametrize(
    "text",
    ["", "run to a circle", "walk a circle", "push to a circle", "push a circle square", "push a small red circle",
     "walk to a red red circle", "walk to a circle quickly", "push a circle cautiously hesitantly", "push a"],
)
def test_bad_commands_raise_command_error(text):
    with pytest.raises(CommandError):
        CommandFrame.parse(text)
