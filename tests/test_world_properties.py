"""Hypothesis invariants of World physics, encoding and the planner over random situations."""
from collections import Counter

import numpy as np
from hypothesis import assume, given
from hypothesis import strategies as st

from gscan_ros.errors import InvalidActionError, SituationError
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
)
from gscan_ros.world.types import ADVERBS, COLORS, SHAPES, SIZES, WORLD_ACTIONS

N = 6
CELLS = [Position(r, c) for r in range(N) for c in range(N)]


@st.composite
def situations(draw, min_objects=0):
    cells = draw(st.lists(st.sampled_from(CELLS), min_size=min_objects + 1, max_size=13, unique=True))
    agent, *object_cells = cells
    objects = tuple(
        WorldObject(draw(st.sampled_from(SHAPES)), draw(st.sampled_from(COLORS)), draw(st.sampled_from(SIZES)), cell)
        for cell in object_cells
    )
    # Agents may start on an object in a snapshot; half the time put it on one.
    if objects and draw(st.booleans()):
        agent = draw(st.sampled_from(object_cells))
    target = draw(st.sampled_from(objects)) if objects and draw(st.booleans()) else None
    return Situation(agent, draw(st.sampled_from(list(Heading))), objects, target)


action_lists = st.lists(st.sampled_from(WORLD_ACTIONS), max_size=40)
invalid_actions = st.one_of(
    st.just(Action.EOS), st.just("<eos>"),
    st.text(max_size=12).filter(lambda t: t.strip() not in {a.token for a in Action}),
    st.integers().filter(lambda i: not 0 <= i <= 5),
)


def decode(grid):
    """Objects and agent read back from an encoding (test oracle, released order)."""
    objects = set()
    for r, c in zip(*np.nonzero(grid[:, :, :11].any(axis=2))):
        bits = grid[r, c]
        assert bits[:4].sum() == bits[4:7].sum() == bits[7:11].sum() == 1
        objects.add(WorldObject(SHAPES[bits[4:7].argmax()], COLORS[bits[7:11].argmax()],
                                SIZES[bits[:4].argmax()], Position(int(r), int(c))))
    (ar, ac), = zip(*np.nonzero(grid[:, :, 11]))
    assert grid[ar, ac, 12:].sum() == 1 and grid[:, :, 12:].sum() == 1
    return objects, Position(int(ar), int(ac)), Heading(int(grid[ar, ac, 12:].argmax()))


@given(situations(), action_lists, st.booleans())
def test_physics_invariants(situation, actions, encode_first):
    world = World(situation)
    if encode_first:
        world.encode()  # exercise the incrementally maintained layer
    kinds = Counter((o.shape, o.color, o.size) for o in situation.placed_objects)
    for action in actions:
        before = {o.position: o for o in world.objects}
        agent_before = world.agent_position
        world.step(action)
        after = {o.position: o for o in world.objects}
        assert len(after) == len(before) == len(situation.placed_objects)  # one object per cell
        assert all(0 <= p.row < N and 0 <= p.col < N for p in after)
        assert 0 <= world.agent_position.row < N and 0 <= world.agent_position.col < N
        moved = set(before) - set(after)
        if action not in (Action.PUSH, Action.PULL):
            assert not moved
        elif moved:
            (old,) = moved
            (new,) = set(after) - set(before)
            assert old == agent_before and world.agent_position == new
            assert abs(old.row - new.row) + abs(old.col - new.col) == 1  # never jumps over anything
            assert new not in before and after[new].shape == before[old].shape
        assert Counter((o.shape, o.color, o.size) for o in world.objects) == kinds
        grid = world.encode()
        objects, agent, heading = decode(grid)
        assert objects == set(world.objects)
        assert (agent, heading) == (world.agent_position, world.agent_direction)
        np.testing.assert_array_equal(grid, World(world.snapshot()).encode())


@given(situations(), action_lists, invalid_actions)
def test_invalid_action_leaves_world_unchanged(situation, actions, bad):
    world = World(situation)
    for a in actions:
        world.step(a)
    before, grid = world.copy(), world.encode()
    try:
        world.step(bad)
    except InvalidActionError:
        pass
    else:
        raise AssertionError(f"{bad!r} was accepted")
    assert world == before
    np.testing.assert_array_equal(world.encode(), grid)


@given(situations(), action_lists)
def test_snapshot_json_round_trip(situation, actions):
    world = World(situation)
    for a in actions:
        world.step(a)
    snap = world.snapshot()
    assert Situation.from_json(snap.to_json()) == snap
    assert snap.to_json() == Situation.from_json(snap.to_json()).to_json()


def _free_cells(world, heading):
    """Oracle: empty cells between the agent and the wall/next object along heading."""
    dr, dc = heading.delta
    r, c, count = world.agent_position.row + dr, world.agent_position.col + dc, 0
    while 0 <= r < N and 0 <= c < N and world.object_at((r, c)) is None:
        r, c, count = r + dr, c + dc, count + 1
    return count


@st.composite
def demonstrations(draw):
    situation = draw(situations(min_objects=1))
    assume(all(o.position != situation.agent_position for o in situation.placed_objects))
    target = draw(st.sampled_from(situation.placed_objects))
    verb = draw(st.sampled_from(["walk", "push", "pull"]))
    manner = draw(st.sampled_from((None,) + ADVERBS))
    for color, size in draw(st.permutations([(None, None), (target.color, None), (None, "small"), (None, "big"),
                                             (target.color, "small"), (target.color, "big")])):
        frame = CommandFrame(verb, manner, color, size, target.shape)
        try:
            if resolve_target(situation, frame) == target:
                return Situation(situation.agent_position, Heading.EAST, situation.placed_objects, target), frame
        except SituationError:
            pass
    assume(False)


@given(demonstrations())
def test_planner_reaches_the_target_and_interacts_to_the_wall(case):
    situation, frame = case
    actions = demonstrate(situation, frame)
    assert demonstrate(situation, frame.text) == actions
    world = World(situation)
    target = situation.target_object
    for i, a in enumerate(actions):
        if a in (Action.PUSH, Action.PULL):
            start = i
            break
        world.step(a)
    else:
        start = len(actions)
    assert world.agent_position == target.position
    walks = actions[:start].count(Action.WALK)
    start_cell, goal = situation.agent_position, target.position
    d = abs(start_cell.row - goal.row) + abs(start_cell.col - goal.col)
    assert walks == d  # the shortest route, whatever the manner
    prims = [a for a in actions if a in (Action.PUSH, Action.PULL)]
    if frame.verb == "walk":
        assert not prims
    else:
        verb = Action.PUSH if frame.verb == "push" else Action.PULL
        heading = world.agent_direction if verb is Action.PUSH else Heading((world.agent_direction + 2) % 4)
        threshold = 2 if target.size >= 3 else 1
        assert len(prims) == _free_cells(world, heading) * threshold
        assert set(prims) <= {verb}
        for a in actions[start:]:
            world.step(a)
        assert not world.object_can_move(verb)
        assert world.agent_position == world.target.position
    if frame.manner == "hesitantly":
        moving = [i for i, a in enumerate(actions) if a in (Action.WALK, Action.PUSH, Action.PULL)]
        assert all(actions[i + 1] is Action.STAY for i in moving)
        assert actions.count(Action.STAY) == len(moving)
    elif frame.manner == "while spinning":
        assert actions.count(Action.TURN_LEFT) >= 4 * (walks + len(prims))
    elif frame.manner == "cautiously":
        assert actions.count(Action.TURN_RIGHT) >= 2 * (walks + len(prims))
    if frame.manner != "hesitantly":
        assert Action.STAY not in actions
