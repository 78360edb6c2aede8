"""episode_recorder_node: records the episodes of the live stack into a gscan_ros bag.

The bag is the dataset format (rosbag2 layout, MCAP, docs/bags.md), so a recorded
run can be replayed, evaluated or trained on like a generated dataset. Messages are
buffered with their DDS source timestamps (actions with their publisher's sequence
number); `episode_log` cuts them into lock-step episodes: complete at the episode's own
`<eos>`, aborted at a `world_reset`. Each goes to the data layer's BagWriter
(`write_recorded_episode`, the writer of generated datasets too, so the metadata agree)
and is flushed to disk at once: a killed recorder leaves a bag that is readable up to
its last written episode. All four parameters can be changed while recording.
"""
from __future__ import annotations

import time
from collections import deque

from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import Header, String, UInt8MultiArray

from gscan_ros import interface
from gscan_ros.data.bag import BagWriter
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
    OBSERVATION,
    SITUATION,
    WORLD_IMAGE,
    WORLD_RESET,
    StatusReporter,
    describe,
    guarded,
    qos_profile,
    quote,
    run,
    validated,
)
from msg_adapters import msg_to_action, msg_to_graph, msg_to_reset, msg_to_situation

READY_LOG = "world state received: recording episodes"


def _log_qos(endpoint):
    """Every sample of a topic, also the stored ones of a latched topic, queued while busy."""
    return qos_profile(endpoint, depth=interface.LOG_DEPTH)


class EpisodeRecorderNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("episode_recorder_node", **kwargs)
        self.declare_parameter(
            "bag_dir", "", describe("output bag directory; empty: gscan_episodes_<date>_<time> here (a change closes "
                                    "the bag and records the next episodes into a new one there)")
        )
        self.declare_parameter("include_images", False, describe("also record world_image"))
        self.declare_parameter("overwrite", False, describe("replace an existing bag at bag_dir (read when a bag "
                                                            "is opened)"))
        self.declare_parameter(
            "buffer_messages", 2000,
            describe("messages kept per topic while an episode runs (bounds memory; an rgb8 world_image is ~170 kB)",
                     int_range=(2, 1_000_000)),
        )
        self.status = StatusReporter(self)
        self._writer = self._open_bag({})
        self._next_writer: BagWriter | None = None  # opened by a bag_dir change, taken after the set
        include_images = self.get_parameter("include_images").value
        self._log = EpisodeLog(self.get_parameter("buffer_messages").value, images=include_images)
        self._pending_eos = None  # an <eos> whose episode waits for the world's last replies
        self._pending_resets: deque[int] = deque()  # resets waiting for the replies sent before them
        # Latched topics first: their stored samples arrive as soon as we match.
        self.create_subscription(Header, WORLD_RESET, self.on_world_reset, _log_qos(interface.WORLD_RESET))
        self.create_subscription(String, SITUATION, self.on_situation, _log_qos(interface.SITUATION))
        self.create_subscription(UInt8MultiArray, OBSERVATION, self.on_observation, _log_qos(interface.OBSERVATION))
        self.create_subscription(String, COMMAND_GRAPH, self.on_graph, _log_qos(interface.COMMAND_GRAPH))
        self._image_sub = None
        self._subscribe_images(include_images)
        self.create_subscription(String, ACTION, self.on_action, _log_qos(interface.ACTION))
        self.add_on_set_parameters_callback(validated(self._check_parameters))
        self.add_post_set_parameters_callback(self._apply_parameters)
        self.get_logger().info(f"recording episodes to {self._writer.bag_dir}")

    @property
    def bag_dir(self):
        return self._writer.bag_dir

    @property
    def episodes(self) -> int:
        """Episodes written to the current bag."""
        return self._writer.episodes_written

    @property
    def ready(self) -> bool:
        """True once the world state has arrived: episodes started from now on are recorded."""
        return bool(self._log.situations) and bool(self._log.observations)

    # -- parameters --------------------------------------------------------------------
    def _open_bag(self, changes: dict) -> BagWriter:
        bag_dir = changes.get("bag_dir", self.get_parameter("bag_dir").value)
        overwrite = changes.get("overwrite", self.get_parameter("overwrite").value)
        return BagWriter(bag_dir or time.strftime("gscan_episodes_%Y%m%d_%H%M%S"), overwrite=overwrite).open()

    def _check_parameters(self, changes: dict) -> None:
        """A new bag_dir is opened here, so a directory that cannot take a bag is refused with the reason."""
        self._next_writer = None
        if "bag_dir" in changes:
            self._next_writer = self._open_bag(changes)

    @guarded
    def _apply_parameters(self, parameters: list) -> None:
        names = {p.name for p in parameters}
        if self._next_writer is not None:
            old, self._writer, self._next_writer = self._writer, self._next_writer, None
            old.close()
            self.status.info(f"closed {old.bag_dir} ({old.episodes_written} episodes); recording to "
                             f"{self._writer.bag_dir}")
        if "buffer_messages" in names:
            self._log.resize(self.get_parameter("buffer_messages").value)
        if "include_images" in names:
            self._subscribe_images(self.get_parameter("include_images").value)

    def _subscribe_images(self, on: bool) -> None:
        """Record world_image from the next episode on (on), or stop (off)."""
        self._log.record_images(on)
        if on and self._image_sub is None:
            self._image_sub = self.create_subscription(Image, WORLD_IMAGE, self.on_image,
                                                       _log_qos(interface.WORLD_IMAGE))
        elif not on and self._image_sub is not None:
            self.destroy_subscription(self._image_sub)
            self._image_sub = None

    # -- topics ------------------------------------------------------------------------
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
        if self._log.images is not None:
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
        """Cut the episodes a reset or an `<eos>` ended once the observations they waited for
        have arrived (a reset first: a later `<eos>` belongs to the episode after it)."""
        while self._pending_resets and self._log.reset_settled(self._pending_resets[0]):
            self._abort(self._pending_resets.popleft())
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
        """The running episode ends aborted, cut when the world's state after the reset arrives."""
        self._pending_resets.append(msg_to_reset(msg))
        self._retry_pending()

    def _abort(self, reset_ns: int) -> None:
        try:
            record = self._log.add_reset(reset_ns)
        except IncompleteEpisode as exc:
            self.status.reject(f"episode aborted by the reset at {reset_ns} not recorded: {exc}")
            return
        if record is not None:
            self._write(record)

    def _write(self, record: EpisodeRecord) -> None:
        """Decode the episode's graph and situation and hand it to the bag writer (which flushes it)."""
        episode_id = self._writer.write_recorded_episode(
            record, msg_to_graph(record.graph.value), msg_to_situation(record.situation.value),
            recorded_by=self.get_fully_qualified_name(),
        )
        aborted = f" as aborted ({record.reason})" if record.outcome == ABORTED else ""
        left_out = f"; left out {record.left_out} actions of another chain" if record.left_out else ""
        self.status.info(f"recorded episode {episode_id}{aborted} ({len(record.actions)} actions{left_out})")

    def destroy_node(self) -> None:
        while self._pending_resets:  # the world's new state never came: keep what did
            self._abort(self._pending_resets.popleft())
        self._writer.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run(EpisodeRecorderNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
