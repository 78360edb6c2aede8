"""episode_recorder_node: records the live stack into a bag, as `ros2 bag record` would.

Every message of the stack's topics (docs/ros.md) is written as it arrives, serialized as
it was sent, with its DDS source timestamp as the MCAP publish time; the bag is the
dataset format (docs/bags.md), read back by the same rule as any all-topics recording:
the policy's `episode_status` reports delimit episodes. What the recorder adds is an
`/episode` record per episode (split `live`, who recorded it), the episode counts in the
metadata, and a flush to disk when an episode ends: a killed recorder leaves a bag that
reads up to its last ended episode. Nothing is buffered beyond the MCAP chunk in
progress, so memory does not grow with what is published. All three parameters can be
changed while recording.

A bag counts the episodes whose ACTIVE report it holds. One that was running when the
bag began (the recorder joined late, or `bag_dir` changed) is in it only from there on:
its end is recorded but not counted, and readers take it as the bag's prologue. One still
running when the bag closes (a `bag_dir` change, the recorder's shutdown) gets a
PREEMPTED report from the recorder, "the recording stopped", so the bag holds no
episode without an end (docs/bags.md "Episodes").
"""
from __future__ import annotations

import json
import time
from pathlib import Path

from rclpy.node import Node

from gscan_ros import episode_status as es
from gscan_ros import interface
from gscan_ros.data.bag import LIVE_SPLIT, BagWriter
from gscan_ros.data.bag_metadata import EPISODE_FORMAT_VERSION
from gscan_ros.data.bag_schema import EPISODE, TOPICS
from gscan_ros.data.episode_assembly import RECORDING_STOPPED
from gscan_ros.errors import DatasetFormatError, GscanError
from gscan_ros.nodes.common import StatusReporter, describe, guarded, msg_class, qos_profile, run, validated
from msg_adapters import cdr_to_episode_status, episode_status_to_cdr, text_to_cdr

READY_LOG = "world state received: recording episodes"
# The stack's topics the recorder takes (`episode` is its own to write).
RECORDED = tuple(e for e in interface.RECORDED if e is not interface.EPISODE)


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
        self.status = StatusReporter(self, counters=lambda: {"episodes recorded": self.episodes})
        self._running: dict[str, es.EpisodeStatus] = {}  # ACTIVE reports in the current bag whose end has not come
        self._failed: str | None = None  # why the current bag could not be written: nothing is recorded into it
        self._writer = self._open_bag(self._bag_path({}), {})
        self._next_writer: BagWriter | None = None  # opened by a bag_dir change, taken after the set
        self._seen: set[str] = set()  # topics heard from (ready once the world state is among them)
        # The newest message of each latched topic: a new bag starts with the current state,
        # as a new subscriber would get it.
        self._latched: dict[str, tuple[interface.Endpoint, bytes, dict]] = {}
        self._recording = {}
        for endpoint in RECORDED:
            if endpoint is not interface.WORLD_IMAGE:
                self._subscribe(endpoint)
        self._record_images(self.get_parameter("include_images").value)
        self.add_on_set_parameters_callback(validated(self._check_parameters))
        self.add_post_set_parameters_callback(self._apply_parameters)
        self.get_logger().info(f"recording episodes to {self._writer.bag_dir}")

    @property
    def bag_dir(self):
        return self._writer.bag_dir

    @property
    def episodes(self) -> int:
        """Episodes that ended in the current bag (every outcome)."""
        return self._writer.episodes_written

    @property
    def ready(self) -> bool:
        """True once the world state has arrived: episodes started from now on are recorded."""
        return {interface.SITUATION.name, interface.OBSERVATION.name} <= self._seen

    # -- parameters --------------------------------------------------------------------
    def _open_bag(self, bag_dir: Path, changes: dict) -> BagWriter:
        overwrite = changes.get("overwrite", self.get_parameter("overwrite").value)
        return BagWriter(bag_dir, overwrite=overwrite, overwrite_flag="the overwrite parameter").open()

    def _bag_path(self, changes: dict) -> Path:
        bag_dir = changes.get("bag_dir", self.get_parameter("bag_dir").value)
        return Path(bag_dir or time.strftime("gscan_episodes_%Y%m%d_%H%M%S"))

    def _check_parameters(self, changes: dict) -> None:
        """A new bag_dir is opened here, so a directory that cannot take a bag is refused with the
        reason; so is the bag being recorded (opening it again would wipe it under its writer)."""
        self._next_writer = None
        if "bag_dir" in changes:
            bag_dir = self._bag_path(changes)
            if bag_dir.resolve() == self._writer.bag_dir.resolve():
                raise DatasetFormatError(f"{self._writer.bag_dir} is the bag being recorded")
            self._next_writer = self._open_bag(bag_dir, changes)

    @guarded
    def _apply_parameters(self, parameters: list) -> None:
        names = {p.name for p in parameters}
        if "include_images" in names:
            self._record_images(self.get_parameter("include_images").value)
        if self._next_writer is not None:
            old, self._writer, self._next_writer = self._writer, self._next_writer, None
            if self._failed is None:
                self._stop_running(old, f"the recording moved to {self._writer.bag_dir}")
                old.close()
            self._failed = None
            try:
                self._write_latched()
            except OSError as exc:
                self._fail(exc)
            self.status.info(f"closed {old.bag_dir} ({old.episodes_written} episodes); recording to "
                             f"{self._writer.bag_dir}")

    def _write_latched(self) -> None:
        """Start a new bag with the current state as a subscriber joining now gets it:
        received now, in the order it was published (images only when recorded)."""
        now = time.time_ns()
        latched = sorted(self._latched.values(), key=lambda sample: sample[2]["source_timestamp"])
        for endpoint, data, info in latched:
            if endpoint.name in self._recording:
                self._write(endpoint, data, {**info, "received_timestamp": now})

    def _record_images(self, on: bool) -> None:
        if on and interface.WORLD_IMAGE.name not in self._recording:
            self._subscribe(interface.WORLD_IMAGE)
        elif not on and interface.WORLD_IMAGE.name in self._recording:
            self.destroy_subscription(self._recording.pop(interface.WORLD_IMAGE.name))

    # -- recording ---------------------------------------------------------------------
    def _subscribe(self, endpoint: interface.Endpoint) -> None:
        """Serialized messages as sent; every sample, the stored ones of a latched topic too, queued while busy."""
        self._recording[endpoint.name] = self.create_subscription(
            msg_class(endpoint.type), endpoint.name, lambda data, info: self._record(endpoint, data, info),
            qos_profile(endpoint, depth=interface.LOG_DEPTH), raw=True)

    @guarded
    def _record(self, endpoint: interface.Endpoint, data: bytes, info: dict) -> None:
        if endpoint.latched:  # kept also while nothing is written: a new bag starts with it
            self._latched[endpoint.name] = (endpoint, data, info)
        if self._failed is not None:  # the bag cannot be written: nothing until bag_dir changes
            return
        try:
            self._write(endpoint, data, info)
            self._take(endpoint, data, info)
        except OSError as exc:
            self._fail(exc)

    def _fail(self, exc: OSError) -> None:
        """The disk refused a write (full, gone, read-only): the bag stops where it is, read
        back as a killed recorder's, and the error is reported once, not once per message
        (its own status line would be the next message to fail)."""
        self._failed = f"{exc.strerror or exc}"
        self._running.clear()
        try:
            self._writer.abandon()
        except OSError:
            pass  # its file is closed all the same
        self.status.error(f"recording stopped: {self._writer.bag_dir} cannot be written ({self._failed}); what it "
                          f"holds reads back up to its last ended episode; set bag_dir to record again")

    def _take(self, endpoint: interface.Endpoint, data: bytes, info: dict) -> None:
        """What a recorded message tells the recorder: the world state is there, an episode
        started or ended."""
        if endpoint.name not in self._seen:
            was_ready = self.ready
            self._seen.add(endpoint.name)
            if not was_ready and self.ready:
                self.get_logger().info(READY_LOG)
        if endpoint is interface.EPISODE_STATUS:
            self._on_report(data, info["source_timestamp"])

    def _write(self, endpoint: interface.Endpoint, data: bytes, info: dict) -> None:
        topic = endpoint.bag_topic
        channel = self._writer.channel(topic, TOPICS[topic].msg_type)
        self._writer.add_record(channel, data, info["received_timestamp"], info["source_timestamp"], 0)

    def _on_report(self, data: bytes, publish_ns: int) -> None:
        try:
            report = cdr_to_episode_status(data)
        except GscanError as exc:
            self.status.reject(f"unreadable episode report: {exc}")
            return
        if report.outcome == es.ACTIVE:
            earlier = self._running.get(report.episode_id)
            if earlier is not None and earlier.start_ns != report.start_ns:
                # The same id started again: its policy restarted without ending the earlier
                # one, which ends just before the new one's start (readers order by publish time).
                self._preempt(self._writer, earlier, f"{report.episode_id} started again (its node restarted)",
                              publish_ns - 1)
            self._running[report.episode_id] = report
            record = {"version": EPISODE_FORMAT_VERSION, "id": report.episode_id, "split": LIVE_SPLIT,
                      "meta": {"recorded_by": self.get_fully_qualified_name()}}
            self._writer.write_message(EPISODE.name, EPISODE.msg_type, text_to_cdr(json.dumps(record)), time.time_ns(),
                                       publish_ns)
            return
        started = self._running.pop(report.episode_id, None)
        if started is None and report.outcome != es.REJECTED:  # a refused command has no ACTIVE report
            self.status.info(f"not counting episode {report.episode_id} ({report.outcome}): it started before "
                             f"{self._writer.bag_dir} did")
            return
        number = self._writer.episodes_written
        self._writer.count_episode(LIVE_SPLIT if report.outcome == es.COMPLETE else None)
        self._writer.flush()
        self.status.info(f"recorded episode {number} ({report.episode_id}: {report.outcome})")

    def _stop_running(self, writer: BagWriter, why: str) -> None:
        """End the episodes still running in `writer`'s bag, which closes now, as preempted."""
        for active in list(self._running.values()):
            self._preempt(writer, active, why)

    def _preempt(self, writer: BagWriter, active: es.EpisodeStatus, why: str, publish_ns: int | None = None) -> None:
        """End `active` in `writer`'s bag with the recorder's own PREEMPTED report, published
        at `publish_ns` (default: after everything written so far), and count it."""
        self._running.pop(active.episode_id, None)
        report = es.EpisodeStatus(active.episode_id, active.start_ns, es.PREEMPTED, f"{active.text!r}: {why}")
        now = time.time_ns()
        writer.write_message(interface.EPISODE_STATUS.bag_topic, interface.EPISODE_STATUS.type,
                             episode_status_to_cdr(report), now,
                             max(now, writer.last_publish_ns + 1) if publish_ns is None else publish_ns)
        number = writer.episodes_written
        writer.count_episode(None)
        self.status.info(f"recorded episode {number} ({active.episode_id}: {es.PREEMPTED}, {why})")

    def destroy_node(self) -> None:
        try:
            if self._failed is None:
                self._stop_running(self._writer, RECORDING_STOPPED)
        finally:
            self._writer.close()  # nothing to do for a bag given up (`_fail`)
            super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run(EpisodeRecorderNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
