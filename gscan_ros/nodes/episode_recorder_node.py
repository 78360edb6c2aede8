"""episode_recorder_node: records the episodes of the live stack into a gscan_ros bag.

The bag is the dataset format (rosbag2 layout, MCAP, DESIGN.md "Bags"), so a recorded
run can be replayed, evaluated or trained on like a generated dataset. Messages are
buffered with their DDS source timestamps (actions with their publisher's sequence
number); `episode_log` cuts them into lock-step episodes: complete at the episode's own
`<eos>`, aborted at a `world_reset`. Each is written and flushed to disk at once, so a
killed recorder leaves a bag that is readable up to its last written episode.
"""
from __future__ import annotations

import json
import time

from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import Header, String, UInt8MultiArray

from gscan_ros.data import bag_schema as bag_topics
from gscan_ros.data.bag import OUTCOME_ABORTED, OUTCOME_COMPLETE, BagWriter, episode_header
from gscan_ros.data.episode import Episode
from gscan_ros.data.episode_log import (
    ABORTED,
    EpisodeLog,
    EpisodeRecord,
    IncompleteEpisode,
    StampedBuffer,
    UnpairedAction,
)
from gscan_ros.errors import GscanError
from gscan_ros.nodes.common import (
    ACTION,
    COMMAND_GRAPH,
    EVENT_QOS,
    LATCHED_LOG_QOS,
    OBSERVATION,
    SITUATION,
    WORLD_IMAGE,
    WORLD_RESET,
    StatusReporter,
    describe,
    guarded,
    quote,
    run,
)
from gscan_ros.world.types import Action, Situation
from msg_adapters import action_to_msg, msg_to_action, msg_to_graph, msg_to_reset

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
        self._log = EpisodeLog(capacity, images=include_images)
        self._pending_eos = None  # an <eos> whose episode waits for the world's last replies
        # Latched topics first: their stored samples arrive as soon as we match.
        self.create_subscription(Header, WORLD_RESET, self.on_world_reset, LATCHED_LOG_QOS)
        self.create_subscription(String, SITUATION, self.on_situation, LATCHED_LOG_QOS)
        self.create_subscription(UInt8MultiArray, OBSERVATION, self.on_observation, LATCHED_LOG_QOS)
        self.create_subscription(String, COMMAND_GRAPH, self.on_graph, LATCHED_LOG_QOS)
        if self._log.images is not None:
            self.create_subscription(Image, WORLD_IMAGE, self.on_image, LATCHED_LOG_QOS)
        self.create_subscription(String, ACTION, self.on_action, EVENT_QOS)
        self.get_logger().info(f"recording episodes to {self._writer.bag_dir}")

    @property
    def bag_dir(self):
        return self._writer.bag_dir

    @property
    def ready(self) -> bool:
        """True once the world state has arrived: episodes started from now on are recorded."""
        return bool(self._log.situations) and bool(self._log.observations)

    @guarded
    def on_situation(self, msg: String, info: dict) -> None:
        self._keep(self._log.situations, msg, info)

    @guarded
    def on_observation(self, msg: UInt8MultiArray, info: dict) -> None:
        self._keep(self._log.observations, msg, info)
        self._retry_pending()

    @guarded
    def on_graph(self, msg: String, info: dict) -> None:
        self._keep(self._log.graphs, msg, info)

    @guarded
    def on_image(self, msg: Image, info: dict) -> None:
        self._keep(self._log.images, msg, info)

    def _keep(self, buffer: StampedBuffer, msg, info: dict) -> None:
        was_ready = self.ready
        buffer.add(info["source_timestamp"], msg)
        if not was_ready and self.ready:
            self.get_logger().info(READY_LOG)

    @guarded
    def on_action(self, msg: String, info: dict) -> None:
        try:
            action = msg_to_action(msg)
        except GscanError:
            return  # the world simulator reports invalid actions; they are not part of an episode
        t_ns = info["source_timestamp"]
        try:
            record = self._log.add_action(t_ns, action, info.get("publication_sequence_number"))
        except UnpairedAction as exc:
            self.status.reject(f"ignored action {quote(msg.data)} sent at {t_ns}: {exc}")
            return
        except IncompleteEpisode:
            # the world's last replies may still be on their way (topics arrive independently)
            self._pending_eos = self._log.actions.latest_before(t_ns, inclusive=True)
            return
        if record is not None:
            self._write(record)

    def _retry_pending(self) -> None:
        """Close a pending `<eos>` once the observations it waited for have arrived."""
        eos = self._pending_eos
        if eos is None:
            return
        try:
            record = self._log.close(eos)
        except IncompleteEpisode as exc:
            if self._log.superseded(eos):
                self._pending_eos = None
                self.status.reject(f"episode ending at {eos.t_ns} not recorded: {exc}")
            return
        except UnpairedAction as exc:
            self._pending_eos = None
            self.status.reject(f"ignored action '<eos>' sent at {eos.t_ns}: {exc}")
            return
        self._pending_eos = None
        if record is not None:
            self._write(record)

    @guarded
    def on_world_reset(self, msg: Header, info: dict) -> None:
        reset_ns = msg_to_reset(msg)
        try:
            record = self._log.add_reset(reset_ns)
        except IncompleteEpisode as exc:
            self.status.reject(f"episode aborted by the reset at {reset_ns} not recorded: {exc}")
            return
        if record is not None:
            self._write(record)

    def _write(self, record: EpisodeRecord) -> None:
        graph = msg_to_graph(record.graph.value)
        meta = {"parser": graph.parser, "recorded_by": self.get_fully_qualified_name()}
        if graph.typed is not None:  # the header's "command" is the canonical one the policy followed
            meta["typed_command"] = graph.typed
        if record.outcome == ABORTED:
            meta["aborted_because"] = record.reason
        episode = Episode(
            command=graph.command,
            situation=Situation.from_json(json.loads(record.situation.value.data)),
            actions=record.actions,
            split=LIVE_SPLIT,
            meta=meta,
        )
        outcome = OUTCOME_ABORTED if record.outcome == ABORTED else OUTCOME_COMPLETE
        header = json.dumps(episode_header(episode, self.episodes, outcome), separators=(",", ":"))
        write = self._writer.write_message
        write(bag_topics.COMMAND.name, String(data=header), record.start_ns)
        write(bag_topics.COMMAND_GRAPH.name, record.graph.value, record.start_ns)
        for step in record.steps:
            write(bag_topics.OBSERVATION.name, step.observation.value, step.observation.t_ns)
            if step.image is not None:
                write(bag_topics.WORLD_IMAGE.name, step.image.value, step.image.t_ns)
            if step.action is not None:
                write(bag_topics.ACTION.name, action_to_msg(step.action.value), step.action.t_ns)
        if record.outcome == ABORTED:  # the bag's episode delimiter, stamped when the reset ended it
            write(bag_topics.ACTION.name, action_to_msg(Action.EOS), record.end_ns)
        self._writer.flush()
        self.episodes += 1
        aborted = f" as aborted ({record.reason})" if record.outcome == ABORTED else ""
        left_out = f"; left out {record.left_out} actions of another chain" if record.left_out else ""
        self.status.info(f"recorded episode {self.episodes - 1}{aborted} ({len(record.actions)} actions{left_out})")

    def destroy_node(self) -> None:
        self._writer.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run(EpisodeRecorderNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
