"""episode_recorder_node: records finished episodes of the live stack into a gscan_ros bag.

The bag is the dataset format (rosbag2 layout, MCAP, DESIGN.md "Bags"), so a recorded
run can be replayed, evaluated or trained on like a generated dataset. Messages are
buffered with their DDS source timestamps; at each `<eos>` the episode is assembled
in lock-step order (`episode_log`), written, and flushed to disk, so a killed
recorder leaves a bag that is readable up to its last finished episode.
"""
from __future__ import annotations

import json
import time

from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import String, UInt8MultiArray

from gscan_ros.data import bag_schema as bag_topics
from gscan_ros.data.bag import BagWriter, episode_header
from gscan_ros.data.episode import Episode
from gscan_ros.errors import GscanError
from gscan_ros.nodes.common import (
    ACTION,
    COMMAND_GRAPH,
    EVENT_QOS,
    LATCHED_LOG_QOS,
    OBSERVATION,
    SITUATION,
    WORLD_IMAGE,
    StatusReporter,
    describe,
    guarded,
    run,
)
from gscan_ros.data.episode_log import EpisodeRecord, IncompleteEpisode, StampedBuffer, assemble_episode
from gscan_ros.world.types import Action, Situation
from msg_adapters import action_to_msg, msg_to_action, msg_to_graph

LIVE_SPLIT = "live"
READY_LOG = "world state received: recording episodes"


class EpisodeRecorderNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("episode_recorder_node", **kwargs)
        bag_dir = self.declare_parameter(
            "bag_dir", "", describe("output bag directory; empty: gscan_episodes_<date>_<time> here")
        ).value
        include_images = self.declare_parameter("include_images", False, describe("also record world_image")).value
        overwrite = self.declare_parameter("overwrite", False, describe("replace an existing bag at bag_dir")).value
        capacity = self.declare_parameter(
            "buffer_messages",
            2000,
            describe("messages kept per topic while an episode runs (bounds memory; an rgb8 world_image is ~170 kB)"),
        ).value
        self.status = StatusReporter(self)
        self._writer = BagWriter(
            bag_dir or time.strftime("gscan_episodes_%Y%m%d_%H%M%S"), include_images=include_images, overwrite=overwrite
        ).open()
        self.episodes = 0
        self._graphs = StampedBuffer(capacity)
        self._actions: StampedBuffer[Action] = StampedBuffer(capacity)
        self._observations = StampedBuffer(capacity)
        self._situations = StampedBuffer(capacity)
        self._images = StampedBuffer(capacity) if include_images else None
        # Latched topics first: their stored samples arrive as soon as we match.
        self.create_subscription(String, SITUATION, self._stamped(self._situations), LATCHED_LOG_QOS)
        self.create_subscription(UInt8MultiArray, OBSERVATION, self._stamped(self._observations), LATCHED_LOG_QOS)
        self.create_subscription(String, COMMAND_GRAPH, self._stamped(self._graphs), LATCHED_LOG_QOS)
        if self._images is not None:
            self.create_subscription(Image, WORLD_IMAGE, self._stamped(self._images), LATCHED_LOG_QOS)
        self.create_subscription(String, ACTION, self.on_action, EVENT_QOS)
        self.get_logger().info(f"recording episodes to {self._writer.bag_dir}")

    @property
    def bag_dir(self):
        return self._writer.bag_dir

    @property
    def ready(self) -> bool:
        """True once the world state has arrived: episodes started from now on are recorded."""
        return bool(self._situations) and bool(self._observations)

    def _stamped(self, buffer: StampedBuffer):
        def keep(msg, info: dict) -> None:
            was_ready = self.ready
            buffer.add(info["source_timestamp"], msg)
            if not was_ready and self.ready:
                self.get_logger().info(READY_LOG)

        return keep

    @guarded
    def on_action(self, msg: String, info: dict) -> None:
        try:
            action = msg_to_action(msg)
        except GscanError:
            return  # the world simulator reports invalid actions; they are not part of an episode
        t_ns = info["source_timestamp"]
        self._actions.add(t_ns, action)
        if action is Action.EOS:
            self._record(t_ns)

    def _record(self, eos_ns: int) -> None:
        try:
            record = assemble_episode(
                eos_ns, self._graphs, self._actions, self._observations, self._situations, self._images
            )
        except IncompleteEpisode as exc:
            self.status.reject(f"episode ending at {eos_ns} not recorded: {exc}")
            return
        self._write(record)
        for buffer in (self._graphs, self._actions, self._observations, self._situations, self._images):
            if buffer is not None:
                buffer.drop_until(record.steps[-1].observation.t_ns)
        self.status.info(f"recorded episode {self.episodes - 1} ({len(record.actions)} actions)")

    def _write(self, record: EpisodeRecord) -> None:
        graph = msg_to_graph(record.graph.value)
        episode = Episode(
            command=graph.command,
            situation=Situation.from_json(json.loads(record.situation.value.data)),
            actions=record.actions,
            split=LIVE_SPLIT,
            meta={"parser": graph.parser, "recorded_by": self.get_fully_qualified_name()},
        )
        header = json.dumps(episode_header(episode, self.episodes), separators=(",", ":"))
        write = self._writer.write_message
        write(bag_topics.COMMAND.name, String(data=header), record.start_ns)
        write(bag_topics.COMMAND_GRAPH.name, record.graph.value, record.start_ns)
        for step in record.steps:
            write(bag_topics.OBSERVATION.name, step.observation.value, step.observation.t_ns)
            if step.image is not None:
                write(bag_topics.WORLD_IMAGE.name, step.image.value, step.image.t_ns)
            write(bag_topics.ACTION.name, action_to_msg(step.action.value), step.action.t_ns)
        self._writer.flush()
        self.episodes += 1

    def destroy_node(self) -> None:
        self._writer.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run(EpisodeRecorderNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
