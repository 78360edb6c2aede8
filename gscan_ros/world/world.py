"""The gSCAN world: mutable state and the one implementation of its physics.

`World.step` is used by the planner (demonstrations), by dataset replay, by
teacher-forced training states and by closed-loop evaluation (quirk Q17 in
docs/model.md: one physics for all of them).

Physics (as LauraRuis/groundedSCAN `world.py` and `gym_minigrid/minigrid.py`):
- `walk` moves one cell along the heading; a walk off the grid is a no-op.
  The agent may stand on any object.
- `turn left` / `turn right` rotate the heading; `stay` does nothing.
- `push` acts on the object under the agent along the heading; `pull` acts
  against the heading and the agent steps backwards without turning.
  Each object keeps a momentum counter: a light object (size 1-2) moves on every
  primitive, a heavy one (size 3-4) on every second. The agent moves with the
  object and stays on its cell.
- A push/pull is blocked when the destination cell is off the grid or holds
  another object; a blocked primitive (or one with no object under the agent)
  changes nothing, momentum included. (The original also counted momentum on
  blocked primitives; its planner never emits those, so demonstrations agree.)
- `<eos>` and unknown tokens raise `InvalidActionError` and leave the world as is.
"""
from __future__ import annotations

import numpy as np

from gscan_ros.errors import InvalidActionError, quoted
from gscan_ros.world.types import (
    AGENT_CHANNEL,
    HEADING_CHANNEL0,
    NUM_CHANNELS,
    WORLD_ACTIONS,
    Action,
    Heading,
    Position,
    Situation,
    WorldObject,
    object_channels,
)

# (d_row, d_col) per heading int, as a plain tuple for the hot path.
_DELTAS: tuple[tuple[int, int], ...] = tuple(Heading(h).delta for h in range(4))

# Accepted action spellings -> Action (IntEnum keys also match their plain ints).
_STEP_ACTIONS: dict = {a: a for a in WORLD_ACTIONS}
_STEP_ACTIONS.update({a.token: a for a in WORLD_ACTIONS})


def _invalid(action: object) -> InvalidActionError:
    if action is Action.EOS or action == Action.EOS.token:
        return InvalidActionError("'<eos>' ends an episode; it is not an action the world can execute")
    if isinstance(action, str):
        try:
            Action.from_token(action)
        except InvalidActionError as err:
            return err
    known = ", ".join(repr(a.token) for a in WORLD_ACTIONS)
    return InvalidActionError(f"unknown action {quoted(action)}; known actions: {known}")


class World:
    """Mutable gSCAN world built from a `Situation`.

    State: agent cell and heading, the placed objects (their order never changes;
    the target keeps its index), one momentum counter per object. The object part
    of the encoding is built on the first `encode()` and then updated only when an
    object moves, so `step` + `encode` stay cheap for closed-loop evaluation.
    """

    __slots__ = ("grid_size", "_row", "_col", "_dir", "_objects", "_cells", "_momentum",
                 "_threshold", "_target", "_layer")

    def __init__(self, situation: Situation):
        n = situation.grid_size
        self.grid_size = n
        self._row, self._col = situation.agent_position
        self._dir = int(situation.agent_direction)
        self._objects: list[WorldObject] = list(situation.placed_objects)
        self._cells = [-1] * (n * n)  # cell (row * n + col) -> object index or -1
        for i, obj in enumerate(self._objects):
            self._cells[obj.position.row * n + obj.position.col] = i
        self._momentum = [0] * len(self._objects)
        self._threshold = [obj.momentum_threshold for obj in self._objects]
        target = situation.target_object
        self._target = -1 if target is None else self._objects.index(target)
        self._layer: np.ndarray | None = None

    # ---- queries -------------------------------------------------------------------
    @property
    def agent_position(self) -> Position:
        return Position(self._row, self._col)

    @property
    def agent_direction(self) -> Heading:
        return Heading(self._dir)

    @property
    def objects(self) -> tuple[WorldObject, ...]:
        """Current objects, in the order of the initial situation."""
        return tuple(self._objects)

    @property
    def target(self) -> WorldObject | None:
        """The situation's target object at its current cell (None if it had none)."""
        return None if self._target < 0 else self._objects[self._target]

    def object_at(self, pos: Position | tuple[int, int]) -> WorldObject | None:
        row, col = pos
        n = self.grid_size
        if not (0 <= row < n and 0 <= col < n):
            return None
        idx = self._cells[row * n + col]
        return None if idx < 0 else self._objects[idx]

    def object_can_move(self, action: Action) -> bool:
        """Would a `push`/`pull` now act on an object, i.e. is it not blocked?

        True when an object is under the agent and the cell in the motion direction
        is inside the grid and empty. The planner repeats the primitive while this
        holds (groundedSCAN `push_or_pull_object`), so planner and world share these rules.
        """
        return self._interaction(action) is not None

    # ---- dynamics ------------------------------------------------------------------
    def step(self, action: Action | str) -> None:
        """Execute one action (an `Action`, its int value or its dataset token)."""
        try:
            act = _STEP_ACTIONS[action]
        except (KeyError, TypeError):
            raise _invalid(action) from None
        if act is Action.WALK:
            dr, dc = _DELTAS[self._dir]
            row, col = self._row + dr, self._col + dc
            n = self.grid_size
            if 0 <= row < n and 0 <= col < n:
                self._row, self._col = row, col
        elif act is Action.TURN_LEFT:
            self._dir = (self._dir + 3) % 4
        elif act is Action.TURN_RIGHT:
            self._dir = (self._dir + 1) % 4
        elif act is not Action.STAY:
            self._push_or_pull(act)

    def _interaction(self, action: Action) -> tuple[int, int, int] | None:
        """(object index, destination row, col) of an unblocked push/pull, else None."""
        n = self.grid_size
        idx = self._cells[self._row * n + self._col]
        if idx < 0:
            return None
        heading = self._dir if action is Action.PUSH else (self._dir + 2) % 4
        dr, dc = _DELTAS[heading]
        row, col = self._row + dr, self._col + dc
        if not (0 <= row < n and 0 <= col < n) or self._cells[row * n + col] >= 0:
            return None
        return idx, row, col

    def _push_or_pull(self, action: Action) -> None:
        move = self._interaction(action)
        if move is None:
            return
        idx, row, col = move
        momentum = self._momentum[idx] + 1
        if momentum < self._threshold[idx]:
            self._momentum[idx] = momentum
            return
        self._momentum[idx] = 0
        obj = self._objects[idx]
        n = self.grid_size
        self._cells[obj.position.row * n + obj.position.col] = -1
        self._cells[row * n + col] = idx
        moved = WorldObject(obj.shape, obj.color, obj.size, Position(row, col))
        self._objects[idx] = moved
        self._row, self._col = row, col  # the agent follows; pull keeps the heading
        if self._layer is not None:
            self._layer[obj.position.row, obj.position.col] = 0
            self._paint(self._layer, moved)

    # ---- views ---------------------------------------------------------------------
    @staticmethod
    def _paint(layer: np.ndarray, obj: WorldObject) -> None:
        layer[obj.position.row, obj.position.col, object_channels(obj.shape, obj.color, obj.size)] = 1

    def encode(self) -> np.ndarray:
        """uint8[n, n, 16] in the released channel order (LauraRuis/groundedSCAN `Grid.encode`).

        Object bits and agent bits are both set when the agent stands on an object
        (as `Grid.encode` does; quirk Q11, docs/model.md). Returns a fresh array.
        """
        if self._layer is None:
            self._layer = np.zeros((self.grid_size, self.grid_size, NUM_CHANNELS), dtype=np.uint8)
            for obj in self._objects:
                self._paint(self._layer, obj)
        out = self._layer.copy()
        out[self._row, self._col, AGENT_CHANNEL] = 1
        out[self._row, self._col, HEADING_CHANNEL0 + self._dir] = 1
        return out

    def snapshot(self) -> Situation:
        """The current state as a `Situation` (momentum counters are not part of it)."""
        return Situation(
            agent_position=Position(self._row, self._col),
            agent_direction=Heading(self._dir),
            placed_objects=tuple(self._objects),
            target_object=self.target,
            grid_size=self.grid_size,
        )

    def copy(self) -> "World":
        """An independent copy (lists and the cached encoding are duplicated)."""
        new = World.__new__(World)
        new.grid_size = self.grid_size
        new._row, new._col, new._dir = self._row, self._col, self._dir
        new._objects = list(self._objects)
        new._cells = list(self._cells)
        new._momentum = list(self._momentum)
        new._threshold = self._threshold  # never mutated
        new._target = self._target
        new._layer = None if self._layer is None else self._layer.copy()
        return new

    def _state(self) -> tuple:
        return (self.grid_size, self._row, self._col, self._dir, tuple(self._objects),
                tuple(self._momentum), self._target)

    def __eq__(self, other: object) -> bool:
        """Same full state, momentum counters included."""
        return isinstance(other, World) and self._state() == other._state()

    __hash__ = None  # mutable

    def __repr__(self) -> str:
        return (f"World(agent={tuple(self.agent_position)}, heading={self.agent_direction.name}, "
                f"objects={len(self._objects)})")
