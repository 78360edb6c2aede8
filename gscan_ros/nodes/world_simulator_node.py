"""world_simulator_node: owns the gSCAN world, executes actions, publishes the state.

Lock-step contract with policy_node (docs/ros.md "Lock-step"): every action message
that is not `<eos>` and not stale gets exactly one `observation` in reply, also when
it is rejected (the world is then unchanged and the same state is sent again).
An action whose DDS source timestamp predates the last reset was meant for the old
world: it is reported on `status` and gets no reply.

Every (re)load first publishes `world_reset`, stamped with the load time, then the new
state: that message is how the policy and the recorder learn that a running episode
ended with its world (docs/ros.md "Resets"). The node counts the actions of the running
episode (`actions since reset`), from 0 at each load, each `<eos>` and each episode the
policy starts (`episode_status` ACTIVE: a preempted episode sends no `<eos>`). A new
situation source set while running (`ros2 param set`: dataset, split, index, seed,
grid_size) is served from the next reset, once it has been opened and its first example
read (a source that cannot be served is refused).
"""
from __future__ import annotations

import time
from pathlib import Path

from actionlib_msgs.msg import GoalStatus
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import Header, String
from std_srvs.srv import Trigger

from gscan_ros import episode_status as es
from gscan_ros import interface
from gscan_ros.data.episode import Episode
from gscan_ros.data.sources import episode_source
from gscan_ros.errors import DatasetFormatError, GscanError
from gscan_ros.nodes.common import (
    ACTION,
    EPISODE_STATUS,
    OBSERVATION,
    RESET_WORLD,
    SITUATION,
    WORLD_IMAGE,
    WORLD_RESET,
    StatusReporter,
    describe,
    guarded,
    guarded_trigger,
    qos_profile,
    quote,
    run,
    validated,
)
from gscan_ros.world.render import render
from gscan_ros.world.types import GRID_SIZE, SUPPORTED_GRID_SIZES, Action
from gscan_ros.world.world import World
from msg_adapters import (
    cdr_to_episode_status,
    cdr_to_text,
    grid_header,
    image_to_cdr,
    observation_to_cdr,
    reset_to_cdr,
    situation_to_cdr,
)

SOURCE_PARAMETERS = ("dataset", "split", "index", "seed", "grid_size")
MAX_INDEX = 2**31 - 1


class WorldSimulatorNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("world_simulator_node", **kwargs)
        self.declare_parameter(
            "dataset", "", describe("dataset.txt (or its directory) or a bag directory; empty: sample situations "
                                    "(a change applies at the next reset_world)")
        )
        self.declare_parameter("split", "test", describe("dataset split to serve (applies at the next reset_world)"))
        self.declare_parameter(
            "index", 0, describe("first example of the split; each reset takes the next (a change: the next "
                                 "reset_world loads this one)", int_range=(0, MAX_INDEX))
        )
        self.declare_parameter(
            "seed", 0, describe("first sampling seed when no dataset; each reset adds 1 (a change: the next "
                                "reset_world samples this one)", int_range=(0, MAX_INDEX))
        )
        grids = (SUPPORTED_GRID_SIZES[0], SUPPORTED_GRID_SIZES[-1])
        self.declare_parameter(
            "grid_size", GRID_SIZE, describe("grid side of sampled worlds when no dataset (applies at the next "
                                             "reset_world)", int_range=grids)
        )
        self.declare_parameter("publish_images", True, describe("render and publish world_image after every step"))
        self.status = StatusReporter(self, counters=lambda: {"actions since reset": self._actions})
        self._source = self._new_source()
        self._reset_pub = self.create_publisher(Header, WORLD_RESET, qos_profile(interface.WORLD_RESET))
        self._observation_pub = self.create_publisher(Image, OBSERVATION, qos_profile(interface.OBSERVATION))
        self._situation_pub = self.create_publisher(String, SITUATION, qos_profile(interface.SITUATION))
        self._image_pub = self.create_publisher(Image, WORLD_IMAGE, qos_profile(interface.WORLD_IMAGE))
        self._world: World | None = None
        self._reset_ns = 0
        self._state_ns = 0  # when the world reached its current state: its observation's stamp
        self._actions = 0  # actions applied in the running episode (since the last reset, <eos> or episode start)
        self._last_action_ns = 0  # DDS source timestamp of the newest action applied
        self.load(self._source.next())  # a bad dataset is a start-up error (run() reports it)
        self.create_subscription(String, ACTION, self.on_action, qos_profile(interface.ACTION), raw=True)
        self.create_subscription(GoalStatus, EPISODE_STATUS, self.on_episode_status,
                                 qos_profile(interface.EPISODE_STATUS), raw=True)
        self.create_service(Trigger, RESET_WORLD, self.on_reset_world)
        self.add_on_set_parameters_callback(validated(self._check_parameters))
        self.add_post_set_parameters_callback(self._apply_parameters)

    @property
    def world(self) -> World:
        """The simulated world (for in-process users: bringup, tests)."""
        return self._world

    @property
    def state_ns(self) -> int:
        """When the world reached its current state (ns since the epoch): the stamp of its observation."""
        return self._state_ns

    def _new_source(self):
        """The situation sequence the parameters describe (its first item: `index`, or `seed`)."""
        return episode_source(*(self.get_parameter(name).value for name in SOURCE_PARAMETERS))

    def _check_parameters(self, changes: dict) -> None:
        """Refuse a dataset source the next reset could not load from: the new dataset,
        split and index are opened here and their first example read, so a missing or
        malformed dataset, an unknown split or an index past its end is refused with the
        reason instead of failing every reset after it."""
        values = {name: changes.get(name, self.get_parameter(name).value) for name in SOURCE_PARAMETERS}
        dataset = values["dataset"]
        if not dataset or not {"dataset", "split", "index"} & changes.keys():
            return
        if not Path(dataset).exists():
            raise DatasetFormatError(f"dataset {dataset!r} does not exist")
        if not values["split"]:
            raise DatasetFormatError("split must not be empty when a dataset is served")
        try:
            episode_source(*values.values()).next()
        except GscanError as exc:
            raise DatasetFormatError(f"dataset {dataset!r}, split {values['split']!r}: {exc}") from None

    @guarded
    def _apply_parameters(self, parameters: list) -> None:
        """A new dataset, split, index, seed or grid size takes effect at the next reset."""
        if any(p.name in SOURCE_PARAMETERS for p in parameters):
            self._source = self._new_source()
            self.status.info("the next reset_world loads from the new source: "
                             + ", ".join(f"{p.name}={p.value!r}" for p in parameters if p.name in SOURCE_PARAMETERS))

    def load(self, episode: Episode) -> str:
        """Start over in `episode`'s situation and publish it; returns a one-line description."""
        self._world = World(episode.situation)
        self._reset_ns = time.time_ns()
        self._actions = 0
        self._reset_pub.publish(reset_to_cdr(self._reset_ns))
        self.publish_state(self._reset_ns)
        text = f"loaded {self._source.describe(episode)}; its command: {episode.command!r}"
        self.status.info(text)
        return text

    def publish_state(self, state_ns: int | None = None) -> None:
        """situation, then observation (what the policy waits for), then the slow image.

        Recorders pair an observation with the newest situation published before it. The
        observation and the image are stamped with `state_ns`, when the world reached
        the state (a load: its reset time; else now), in the grid frame (docs/ros.md
        "Frames and stamps").
        """
        self._state_ns = time.time_ns() if state_ns is None else state_ns
        header = grid_header(self._state_ns)
        self._situation_pub.publish(situation_to_cdr(self._world.snapshot()))
        self._observation_pub.publish(observation_to_cdr(self._world.encode(), header=header))
        if self.get_parameter("publish_images").value:
            self._image_pub.publish(image_to_cdr(render(self._world), header=header))

    @guarded
    def on_action(self, data: bytes, info: dict) -> None:
        """`data`: the serialized std_msgs/String (malformed bytes are rejected by `guarded`)."""
        token = cdr_to_text(data)
        if info["source_timestamp"] < self._reset_ns:
            self.status.reject(f"ignored action {quote(token)}: it was sent before the world was reset")
            return
        try:
            action = Action.from_token(token)
            if action is Action.EOS:
                self.status.info(f"episode ended after {self._actions} actions")
                self._actions = 0
                return
            self._world.step(action)
            self._actions += 1
            self._last_action_ns = info["source_timestamp"]
        except GscanError as exc:
            self.status.reject(f"rejected action {quote(token)}: {exc}")
        self.publish_state()

    @guarded
    def on_episode_status(self, data: bytes, info: dict) -> None:
        """A new episode counts its actions from 0. Topics are not ordered with each other, so
        its first action may have come before its ACTIVE report: then it counts."""
        if cdr_to_episode_status(data).outcome == es.ACTIVE:
            self._actions = int(self._last_action_ns > info["source_timestamp"])

    @guarded_trigger("reset failed, world unchanged")
    def on_reset_world(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.message = self.load(self._source.next())
        response.success = True
        return response


def main(args: list[str] | None = None) -> int:
    return run(WorldSimulatorNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
