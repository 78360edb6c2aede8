"""The gSCAN world: types, JSON, physics (`World`), planner, rendering.

Public API (see docs/world.md):
- types: `Action`, `Heading`, `Position`, `WorldObject`, `Situation`, `object_vector`
- `Situation.from_json(d)` / `.to_json()`; `check_object_vector` for foreign files
- `World(situation)`: `.step(action)`, `.encode()`, `.snapshot()`; `render.render(world)` draws it
- `demonstrate(situation, command)`, `resolve_target`, `CommandFrame`, `split_command`
- rendering in `gscan_ros.world.render` (`render`, `render_frames`, `save_png`, `save_gif`),
  imported lazily because it needs Pillow.
"""
from gscan_ros.world.command import CommandFrame, split_command
from gscan_ros.world.planner import demonstrate, resolve_target, turns
from gscan_ros.world.types import (
    Action,
    Heading,
    Position,
    Situation,
    WorldObject,
    check_object_vector,
    object_vector,
)
from gscan_ros.world.world import World

__all__ = [
    "Action",
    "CommandFrame",
    "Heading",
    "Position",
    "Situation",
    "World",
    "WorldObject",
    "check_object_vector",
    "demonstrate",
    "object_vector",
    "resolve_target",
    "split_command",
    "turns",
]
