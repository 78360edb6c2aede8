"""Ground-truth demonstrations (LauraRuis/groundedSCAN `world.py`: route, manners, push/pull), executed through `World`.

The planner decides *which* action comes next (route, manners); every action is
executed in a private `World`, and the push/pull phase repeats the primitive
while `World.object_can_move` says it is not blocked. So there is one physics:
the momentum of heavy objects, blocking and the backwards motion of `pull`
(quirk Q17, docs/model.md) come from `World.step`, never from a second copy of the rules.
"""
from __future__ import annotations

from typing import Sequence

from gscan_ros.errors import SituationError, quoted
from gscan_ros.world.command import CommandFrame
from gscan_ros.world.types import Action, Heading, Position, Situation, WorldObject
from gscan_ros.world.world import World

WALK, LEFT, RIGHT, STAY = Action.WALK, Action.TURN_LEFT, Action.TURN_RIGHT, Action.STAY
SPIN: tuple[Action, ...] = (LEFT,) * 4
# Left first, as the original's `look_left_and_right` and its released data (its README says right first).
LOOK: tuple[Action, ...] = (LEFT, RIGHT, RIGHT, LEFT)

# Turn(s) from heading a to heading b, indexed (b - a) % 4: a 180° turn is two lefts.
_TURNS: tuple[tuple[Action, ...], ...] = ((), (RIGHT,), (LEFT, LEFT), (LEFT,))


def turns(start: Heading, goal: Heading) -> tuple[Action, ...]:
    """The turn actions that face `goal` from `start`: the minimal 90° turn, or two lefts for 180°."""
    return _TURNS[(goal - start) % 4]


def resolve_target(situation: Situation, command: CommandFrame | str | Sequence[str]) -> WorldObject:
    """The object a command refers to (the original's `World.object_positions`); raises SituationError unless unique.

    Candidates share the command's name (noun, or color + noun); "small"/"big"
    then keep those of the smallest/largest size among the candidates.
    """
    frame = command if isinstance(command, CommandFrame) else CommandFrame.parse(command)
    candidates = [
        o for o in situation.placed_objects
        if o.shape == frame.shape and (frame.color is None or o.color == frame.color)
    ]
    if frame.size is not None and candidates:
        pick = min if frame.size == "small" else max
        extreme = pick(o.size for o in candidates)
        candidates = [o for o in candidates if o.size == extreme]
    referent = " ".join(w for w in (frame.color, frame.size, frame.shape) if w)
    if not candidates:
        raise SituationError(f"situation.placed_objects: no object matches {quoted(referent)}")
    if len(candidates) > 1:
        cells = ", ".join(str(tuple(o.position)) for o in candidates)
        raise SituationError(
            f"situation.placed_objects: {quoted(referent)} is ambiguous ({len(candidates)} objects at {cells})")
    return candidates[0]


class _Demonstration:
    """Executes actions in a private World and records them."""

    __slots__ = ("world", "actions")

    def __init__(self, situation: Situation):
        self.world = World(situation)
        self.actions: list[Action] = []

    def do(self, *actions: Action) -> None:
        step = self.world.step
        for action in actions:
            step(action)
        self.actions.extend(actions)

    def face(self, heading: Heading) -> None:
        self.do(*turns(self.world.agent_direction, heading))

    def walk_straight(self, goal: Position, manner: str | None) -> None:
        """Horizontal legs first, then vertical, one manner unit per cell (the original's `go_to_position`)."""
        here = self.world.agent_position
        dc, dr = goal.col - here.col, goal.row - here.row
        legs = ((Heading.WEST if dc < 0 else Heading.EAST, abs(dc)),
                (Heading.NORTH if dr < 0 else Heading.SOUTH, abs(dr)))
        for heading, cells in legs:
            for _ in range(cells):
                if manner == "while spinning":
                    self.do(*SPIN)
                self.face(heading)
                if manner == "cautiously":
                    self.do(*LOOK)
                self.do(WALK)
                if manner == "hesitantly":
                    self.do(STAY)

    def zigzag(self, goal: Position) -> None:
        """Zigzag as the original's `go_to_position`: horizontal step, then alternate turn + walk until in line."""
        here = self.world.agent_position
        if here.row == goal.row or here.col == goal.col:
            return
        east, south = goal.col > here.col, goal.row > here.row
        self.face(Heading.EAST if east else Heading.WEST)
        self.do(WALK)
        turn = RIGHT if east == south else LEFT  # right for SE/NW, left for NE/SW
        while True:
            here = self.world.agent_position
            if here.row == goal.row or here.col == goal.col:
                return
            self.do(turn, WALK)
            turn = LEFT if turn is RIGHT else RIGHT

    def interact(self, verb: Action, manner: str | None) -> None:
        """Repeat push/pull while the world says the object can move (the original's `move_object_to_wall`)."""
        can_move = self.world.object_can_move
        while can_move(verb):
            if manner == "while spinning":
                self.do(*SPIN)
            elif manner == "cautiously":
                self.do(*LOOK)
            self.do(verb)
            if manner == "hesitantly":
                self.do(STAY)


def demonstrate(situation: Situation, command: CommandFrame | str | Sequence[str]) -> list[Action]:
    """The gSCAN target action sequence (without EOS) for `command` in `situation`.

    The referent is resolved with `resolve_target`; when the situation names a
    target it must be that object (else SituationError).
    """
    frame = command if isinstance(command, CommandFrame) else CommandFrame.parse(command)
    target = resolve_target(situation, frame)
    if situation.target_object is not None and situation.target_object != target:
        raise SituationError(
            f"situation.target_object: {situation.target_object} is not the object the command "
            f"refers to ({target})"
        )
    demo = _Demonstration(situation)
    if frame.manner == "while zigzagging":
        demo.zigzag(target.position)
        demo.walk_straight(target.position, None)
    else:
        demo.walk_straight(target.position, frame.manner)
    if frame.verb != "walk":
        demo.interact(Action.PUSH if frame.verb == "push" else Action.PULL, frame.manner)
    return demo.actions
