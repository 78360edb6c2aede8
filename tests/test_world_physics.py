"""World.step physics, encoding layout and error behaviour (docs/world.md)."""
import numpy as np
import pytest

from gscan_ros.errors import InvalidActionError
from gscan_ros.world import Action, Heading, Position, Situation, World, WorldObject

P = Position


def world(agent=(2, 0), heading=Heading.EAST, objects=(), target=None):
    objs = tuple(WorldObject(shape, color, size, P(*pos)) for shape, color, size, pos in objects)
    return World(Situation(P(*agent), heading, objs, None if target is None else objs[target]))


def test_walk_and_turns():
    w = world(agent=(2, 2))
    w.step("walk")
    assert w.agent_position == P(2, 3)
    w.step(Action.TURN_LEFT)
    assert w.agent_direction is Heading.NORTH
    w.step("walk")
    assert w.agent_position == P(1, 3)
    w.step(Action.TURN_RIGHT)
    w.step(Action.TURN_RIGHT)
    assert w.agent_direction is Heading.SOUTH
    w.step("stay")
    assert (w.agent_position, w.agent_direction) == (P(1, 3), Heading.SOUTH)


@pytest.mark.parametrize("heading, agent", [(Heading.EAST, (0, 5)), (Heading.SOUTH, (5, 0)),
                                            (Heading.WEST, (3, 0)), (Heading.NORTH, (0, 3))])
def test_walk_off_grid_is_a_no_op(heading, agent):
    w = world(agent=agent, heading=heading)
    before = w.copy()
    w.step("walk")
    assert w == before


def test_agent_may_overlap_objects():
    w = world(objects=[("square", "red", 4, (2, 1))])
    w.step("walk")
    w.step("walk")
    assert w.agent_position == P(2, 2)
    assert w.object_at((2, 1)) == WorldObject("square", "red", 4, P(2, 1))


@pytest.mark.parametrize("bad", ["<eos>", Action.EOS, "jump", "run", "Walk", "", None, 7, 2.5, ["walk"]])
def test_invalid_actions_raise_and_leave_the_world_unchanged(bad):
    w = world(objects=[("circle", "blue", 1, (2, 0))])
    w.encode()
    before, grid = w.copy(), w.encode()
    with pytest.raises(InvalidActionError):
        w.step(bad)
    assert w == before
    np.testing.assert_array_equal(w.encode(), grid)


def test_eos_error_message_is_explicit():
    with pytest.raises(InvalidActionError, match="ends an episode"):
        world().step("<eos>")


def test_light_push_moves_every_primitive_until_the_wall():
    w = world(objects=[("square", "red", 1, (2, 2))])
    w.step("walk"), w.step("walk")
    for col in (3, 4, 5):
        assert w.object_can_move(Action.PUSH)
        w.step("push")
        assert w.object_at((2, col)).color == "red" and w.agent_position == P(2, col)
    assert not w.object_can_move(Action.PUSH)
    before = w.copy()
    w.step("push")  # against the wall: nothing happens
    assert w == before


def test_heavy_push_needs_two_primitives_per_cell():
    w = world(objects=[("cylinder", "green", 3, (2, 2))])
    w.step("walk"), w.step("walk")
    w.step("push")
    assert w.object_at((2, 2)).color == "green" and w.agent_position == P(2, 2)
    w.step("push")
    assert w.object_at((2, 3)).color == "green" and w.object_at((2, 2)) is None
    assert w.agent_position == P(2, 3)


def test_momentum_is_kept_per_object():
    w = world(objects=[("square", "red", 4, (2, 1)), ("square", "blue", 3, (4, 1))])
    w.step("walk")
    w.step("push")  # red: momentum 1, no move
    w.step("turn right"), w.step("walk"), w.step("walk")  # onto blue (4, 1), facing south
    w.step("turn left"), w.step("turn left"), w.step("walk"), w.step("walk")  # back to red, facing north
    w.step("pull")  # red's second primitive: moves south (opposite to the heading)
    assert w.object_at((3, 1)).color == "red"
    assert w.agent_position == P(3, 1) and w.agent_direction is Heading.NORTH


def test_blocked_push_is_a_no_op_including_momentum():
    w = world(objects=[("square", "red", 3, (2, 1)), ("circle", "blue", 1, (2, 2))])
    w.step("walk")
    before = w.copy()
    assert not w.object_can_move(Action.PUSH)
    w.step("push")
    assert w == before  # momentum unchanged, too
    w.step("turn right")
    w.step("push")
    assert w.object_at((2, 1)).color == "red"  # first primitive of a heavy object after the block
    w.step("push")
    assert w.object_at((3, 1)).color == "red"


def test_push_pull_without_an_object_is_a_no_op():
    w = world()
    before = w.copy()
    w.step("push"), w.step("pull")
    assert w == before
    assert not w.object_can_move(Action.PULL)


def test_pull_moves_the_object_backwards_with_the_agent():
    """Quirk Q17: one physics; pull moves against the heading, agent does not turn."""
    w = world(agent=(2, 3), objects=[("circle", "yellow", 2, (2, 3))])
    for col in (2, 1, 0):
        w.step("pull")
        assert w.object_at((2, col)).color == "yellow" and w.agent_position == P(2, col)
        assert w.agent_direction is Heading.EAST
    before = w.copy()
    w.step("pull")
    assert w == before


def test_pull_is_blocked_by_an_object_behind():
    w = world(agent=(2, 3), objects=[("circle", "yellow", 2, (2, 3)), ("square", "red", 1, (2, 2))])
    assert not w.object_can_move(Action.PULL)
    assert w.object_can_move(Action.PUSH)


def test_encode_layout_released_channel_order():
    w = world(agent=(1, 1), heading=Heading.SOUTH,
              objects=[("circle", "red", 2, (1, 1)), ("square", "blue", 4, (5, 0))])
    g = w.encode()
    assert g.shape == (6, 6, 16) and g.dtype == np.uint8
    # red circle size 2 + agent facing south on the same cell (both parts set, quirk Q11)
    assert np.flatnonzero(g[1, 1]).tolist() == [1, 6, 9, 11, 13]
    assert np.flatnonzero(g[5, 0]).tolist() == [3, 4, 10]  # blue square size 4
    assert g.sum() == 8
    w.step("turn left")  # -> east: channel 12
    assert np.flatnonzero(w.encode()[1, 1]).tolist() == [1, 6, 9, 11, 12]


def test_encode_returns_a_fresh_array_and_tracks_moves():
    w = world(objects=[("square", "green", 1, (2, 1))])
    g = w.encode()
    g[:] = 7
    w.step("walk"), w.step("push")
    expected = World(w.snapshot()).encode()
    np.testing.assert_array_equal(w.encode(), expected)
    assert expected[2, 2, 0] == 1 and expected[2, 1].sum() == 0


def test_snapshot_and_target_follow_the_pushed_target():
    w = world(objects=[("square", "green", 1, (2, 1)), ("circle", "red", 1, (0, 0))], target=0)
    w.step("walk"), w.step("push")
    assert w.target.position == P(2, 2)
    snap = w.snapshot()
    assert snap.target_object.position == P(2, 2) and snap.placed_objects[1].position == P(0, 0)


def test_copy_is_independent():
    w = world(objects=[("square", "green", 1, (2, 1))])
    w.encode()
    c = w.copy()
    c.step("walk"), c.step("push")
    assert w.object_at((2, 1)).color == "green" and w.agent_position == P(2, 0)
    assert w.encode()[2, 1, 0] == 1 and c.encode()[2, 2, 0] == 1
    assert w != c


def test_integer_actions_are_accepted():
    w = world()
    w.step(int(Action.TURN_RIGHT))
    assert w.agent_direction is Heading.SOUTH
