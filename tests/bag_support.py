"""Episodes for the bag tests: random but valid (walk / turn / stay, never off the grid),
bags written by hand (format 1 as the writers before format 2 wrote it; a live stack as a
recorder logs it), and damaged copies of bags (truncated, edited bytes, killed writer)."""
from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import textwrap
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Iterator

import numpy as np
import yaml
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from gscan_ros import episode_status as es
from gscan_ros import interface
from gscan_ros.data.bag import EPISODE_PERIOD_NS, LIVE_SPLIT, STEP_NS, BagWriter, legacy_header
from gscan_ros.data.bag_metadata import EPISODE_FORMAT_VERSION
from gscan_ros.data.episode import Episode
from gscan_ros.language.graph import CommandGraph
from gscan_ros.world.types import COLORS, SHAPES, Action, Heading, Position, Situation, WorldObject
from gscan_ros.world.world import World
from msg_adapters import (
    action_to_cdr,
    cdr_to_episode_status,
    episode_status_to_cdr,
    graph_to_cdr,
    grid_header,
    message_class,
    msg_to_cdr,
    observation_to_cdr,
    situation_to_cdr,
    text_to_cdr,
)
from msg_adapters.episode_status import GoalID, GoalStatus
from msg_adapters.header import time_msg

SPLITS = ("train", "test", "visual")
TESTS = Path(__file__).parent


def _route(rng: random.Random, start: Position, heading: Heading, length: int) -> tuple[Action, ...]:
    row, col, actions = start.row, start.col, []
    for _ in range(length):
        action = rng.choice((Action.WALK, Action.WALK, Action.TURN_LEFT, Action.TURN_RIGHT, Action.STAY))
        if action is Action.WALK:
            d_row, d_col = heading.delta
            if not (0 <= row + d_row < 6 and 0 <= col + d_col < 6):
                action = Action.TURN_LEFT
            else:
                row, col = row + d_row, col + d_col
        if action is Action.TURN_LEFT:
            heading = Heading((heading - 1) % 4)
        elif action is Action.TURN_RIGHT:
            heading = Heading((heading + 1) % 4)
        actions.append(action)
    return tuple(actions)


def make_episode(rng: random.Random, index: int, max_len: int = 20) -> Episode:
    cells = rng.sample([Position(r, c) for r in range(6) for c in range(6)], 4)
    objects = tuple(
        WorldObject(shape, rng.choice(COLORS), rng.randint(1, 4), cell)
        for shape, cell in zip(SHAPES, cells[1:])
    )
    target = objects[0]
    situation = Situation(
        agent_position=cells[0],
        agent_direction=Heading.EAST,
        placed_objects=objects,
        target_object=target,
        direction_to_target=None,
        distance_to_target=abs(target.position.row - cells[0].row) + abs(target.position.col - cells[0].col),
    )
    actions = _route(rng, cells[0], Heading.EAST, rng.randint(0, max_len))
    command = f"walk to a {target.color} {target.shape}"
    return Episode(command, situation, actions, split=SPLITS[index % len(SPLITS)], example_id=index, meta={"n": index})


def make_episodes(count: int, seed: int = 0, max_len: int = 20) -> list[Episode]:
    rng = random.Random(seed)
    return [make_episode(rng, i, max_len) for i in range(count)]


def on_grid(episodes: list[Episode], grid_size: int) -> list[Episode]:
    """The same episodes on a larger grid (their cells and routes fit any grid of 6 or more)."""
    return [replace(e, situation=replace(e.situation, grid_size=grid_size)) for e in episodes]


def uint8_multi_array(dims: list[tuple[str, int, int]], data: np.ndarray) -> bytes:
    """A serialized std_msgs/UInt8MultiArray of (label, size, stride) dims and uint8 `data`."""
    layout = message_class("std_msgs/msg/MultiArrayLayout")
    dimension = message_class("std_msgs/msg/MultiArrayDimension")
    array = message_class(interface.EARLIER_OBSERVATION_TYPE)
    return msg_to_cdr(array(layout=layout(dim=[dimension(label=label, size=size, stride=stride)
                                               for label, size, stride in dims], data_offset=0),
                            data=np.ascontiguousarray(data, dtype=np.uint8).reshape(-1)))


def earlier_observation_cdr(observation: np.ndarray) -> bytes:
    """An observation as bags before the 8UC16 image held it: a UInt8MultiArray, dims row, col, channel."""
    rows, cols, channels = observation.shape
    return uint8_multi_array([("row", rows, rows * cols * channels), ("col", cols, cols * channels),
                              ("channel", channels, channels)], observation)


# ------------------------------------------------------------------ format-1 bags by hand
@contextmanager
def legacy_bag(bag_dir: Path) -> Iterator[BagWriter]:
    """A BagWriter for a format-1 bag written by hand (`write_legacy_episode`): once closed,
    its metadata.yaml says format_version 1, as the writers before format 2 did."""
    with BagWriter(bag_dir) as writer:
        yield writer
    metadata = bag_dir / "metadata.yaml"
    stamp = f"gscan_ros.format_version: '{EPISODE_FORMAT_VERSION}'"
    text = metadata.read_text()
    assert text.count(stamp) == 1, text
    metadata.write_text(text.replace(stamp, "gscan_ros.format_version: '1'"))


def write_legacy_episode(writer: BagWriter, episode: Episode, episode_id: int, *, tokens: list[str] | None = None,
                         outcome: str | None = None, observations: bool = True) -> None:
    """One episode as format 1 laid it out: its `/command` header at `episode_id` s, then
    `/observation` t and `/action` t (half a step later) at +(t+1) ms; `tokens` default to
    its actions and `<eos>`, `outcome` ("aborted") goes into the header."""
    header = legacy_header(episode, episode_id)
    if outcome is not None:
        header["outcome"] = outcome
    t0 = episode_id * EPISODE_PERIOD_NS
    writer.write_message("/command", interface.COMMAND.type, text_to_cdr(json.dumps(header)), t0)
    states = episode.states()
    for t, token in enumerate(tokens if tokens is not None else [*(a.token for a in episode.actions), "<eos>"]):
        if observations and t < len(states):
            writer.write_message("/observation", interface.EARLIER_OBSERVATION_TYPE, earlier_observation_cdr(states[t]),
                                 t0 + (t + 1) * STEP_NS)
        writer.write_message("/action", interface.ACTION.type, text_to_cdr(token),
                             t0 + (t + 1) * STEP_NS + STEP_NS // 2)


# ------------------------------------------------------------ a live stack, recorded
class LiveStack:
    """The messages of a running stack, for bags recorded by hand: the world's state after
    every step, the typed command and its graph, the policy's reports and actions, each
    published `step_ns` after the one before (real times); `record` logs them as a recorder
    does: in the order they arrive."""

    def __init__(self, situation: Situation, *, t0_ns: int = 1_700_000_000 * 10**9, step_ns: int = 1_000,
                 namespace: str = "", policy: str = "/policy_node"):
        self.world = World(situation)
        self.now = t0_ns
        self.step_ns = step_ns
        self.namespace = namespace
        self.policy = policy
        self.episodes = 0
        # (topic, its type, CDR bytes, publish ns, log delay)
        self.messages: list[tuple[str, str, bytes, int, int]] = []

    def publish(self, topic: str, data: bytes, *, late_ns: int = 0) -> None:
        """Serialized `data` on the stack's `topic` (relative name), of the interface table's type."""
        self.now += self.step_ns
        self.messages.append((f"{self.namespace}/{topic}", interface.endpoint_of(topic).type, data, self.now, late_ns))

    def route(self, rng: random.Random, length: int) -> tuple[Action, ...]:
        """Random actions the world can take from where it is (walks stay on the grid)."""
        now = self.world.snapshot()
        return _route(rng, now.agent_position, now.agent_direction, length)

    def state(self, *, situation: bool = True) -> None:
        """The world's state: its situation (unless the recorder missed it), then its observation."""
        if situation:
            self.publish("situation", situation_to_cdr(self.world.snapshot()))
        header = grid_header(self.now + self.step_ns)  # stamped as published
        self.publish("observation", observation_to_cdr(self.world.encode(), header=header))

    def command(self, typed: str, graph: CommandGraph | None = None) -> None:
        """A command typed as plain text, and the graph the parser made of it."""
        self.publish("command", text_to_cdr(typed))
        if graph is not None:
            self.publish("command_graph", graph_to_cdr(graph))

    def start(self, command: str = "") -> es.EpisodeStatus:
        """The policy's ACTIVE report; policy_node names the `command` it took."""
        self.episodes += 1
        report = es.EpisodeStatus(f"{self.policy}/{self.episodes}", self.now + self.step_ns, es.ACTIVE, command)
        self.publish("episode_status", episode_status_to_cdr(report))
        return report

    def act(self, action: Action, *, situation: bool = True, late_ns: int = 0) -> None:
        """The policy's action and, but for `<eos>`, the world's new state."""
        self.publish("action", action_to_cdr(action), late_ns=late_ns)
        if action is not Action.EOS:
            self.world.step(action)
            self.state(situation=situation)

    def end(self, report: es.EpisodeStatus, outcome: str) -> None:
        self.publish("episode_status", episode_status_to_cdr(replace(report, outcome=outcome)))

    def reject(self) -> None:
        """The policy refuses the newest command graph: no episode starts."""
        self.episodes += 1
        report = es.EpisodeStatus(f"{self.policy}/{self.episodes}", self.now + self.step_ns, es.REJECTED, "refused")
        self.publish("episode_status", episode_status_to_cdr(report))

    def episode(self, actions, outcome: str = es.COMPLETE, *, situations: bool = True) -> es.EpisodeStatus:
        """The policy follows the newest command: ACTIVE, the actions, `<eos>` unless
        preempted (forced at max_steps when cut), and how it ended."""
        report = self.start()
        for action in actions:
            self.act(action, situation=situations)
        if outcome in (es.COMPLETE, es.CUT):
            self.act(Action.EOS)
        self.end(report, outcome)
        return report

    def record(self, writer: BagWriter, *, recorder: bool = True) -> None:
        """Write what a recorder logs: each message when it arrives (`late_ns` after its
        publication), with its publish time; as our recorder does (an `/episode` record when
        an episode starts, the ended ones counted), or as an all-topics recorder (`ros2 bag
        record -a`) does (`recorder=False`)."""
        arrivals = sorted((publish_ns + late_ns, publish_ns, topic, msg_type, data)
                          for topic, msg_type, data, publish_ns, late_ns in self.messages)
        for log_ns, publish_ns, topic, msg_type, data in arrivals:
            writer.write_message(topic, msg_type, data, log_ns, publish_ns)
            if not recorder or not topic.endswith("/episode_status"):
                continue
            report = cdr_to_episode_status(data)
            if report.outcome != es.ACTIVE:
                writer.count_episode(LIVE_SPLIT if report.outcome == es.COMPLETE else None)
            else:
                record = {"version": EPISODE_FORMAT_VERSION, "id": report.episode_id, "split": LIVE_SPLIT,
                          "meta": {"recorded_by": "/episode_recorder_node"}}
                writer.write_message("/episode", interface.EPISODE.type, text_to_cdr(json.dumps(record)), log_ns + 1,
                                     publish_ns)


# Messages no reader can read, by topic: (CDR bytes, what the reader says of them).
BAD_MESSAGES = {
    "action": (text_to_cdr("jump"), "unknown action 'jump'"),
    "situation": (text_to_cdr("{not json"), "situation is not JSON"),
    "episode": (text_to_cdr("{not json"), "/episode record is not JSON"),
    "observation": (text_to_cdr("jump"), "malformed sensor_msgs/msg/Image"),
    "episode_status": (msg_to_cdr(GoalStatus(goal_id=GoalID(stamp=time_msg(0), id="?"), status=9, text="")),
                       "episode status 9 is not one the policy sends"),
}


def recording_with_a_bad_message(bag: Path, topic: str, *, stray: bool = False) -> tuple[list[Episode], int]:
    """`ros2 bag record -a` of three complete episodes on one world with one bad message on
    `topic` (BAD_MESSAGES): in the second episode (for a situation, the newest before its
    ACTIVE report: the one it would start from) or, `stray`, between the second and the
    third. Returns the episodes its reader gives (all but the second, or all when `stray`)
    and the bad message's publish time."""
    rng = random.Random(6)
    stack = LiveStack(make_episodes(1, seed=6)[0].situation)
    stack.state()
    data = BAD_MESSAGES[topic][0]
    episodes, bad_ns = [], 0
    for i, command in enumerate(("walk to a red circle", "walk to a blue circle", "walk to a red circle")):
        situation, actions = stack.world.snapshot(), stack.route(rng, 4)
        stack.command(command)
        inside = i == 1 and not stray
        if inside and topic == "situation":
            stack.publish(topic, data)
            bad_ns = stack.now
        report = stack.start()
        for t, action in enumerate((*actions, Action.EOS)):
            stack.act(action)
            if inside and t == 0 and topic != "situation":
                stack.publish(topic, data)
                bad_ns = stack.now
        stack.end(report, es.COMPLETE)
        if i == 1 and stray:
            stack.publish(topic, data)
            bad_ns = stack.now
        if not inside:
            episodes.append(Episode(command, situation, actions, split=LIVE_SPLIT, example_id=None))
    with BagWriter(bag) as writer:
        stack.record(writer, recorder=False)
    return episodes, bad_ns


# ---------------------------------------------------------- bags as `ros2 bag record` writes them
ROSBAG2_NAME = "rosbag2_2025_01_01-00_00_00"


def rosbag2_copy(src: Path, dst: Path, files: int) -> list[Path]:
    """`src`'s messages as `ros2 bag record -a` stores them: split into `files` MCAP files
    `<name>_<n>.mcap` (each with its own schemas and channels, library rosbag2) and a
    metadata.yaml without our custom data (no episode count). Returns the files."""
    with open(mcap_file(src), "rb") as f:
        messages = list(make_reader(f).iter_messages(log_time_order=False))
    dst.mkdir(parents=True)
    per_file = -(-len(messages) // files)
    paths, entries = [], []
    for n in range(files):
        part = messages[n * per_file:(n + 1) * per_file]
        path = dst / f"{ROSBAG2_NAME}_{n}.mcap"
        with open(path, "wb") as f:
            writer = Writer(f, compression=CompressionType.ZSTD, chunk_size=4096)
            writer.start(profile="ros2", library="rosbag2")
            schemas, channels = {}, {}
            for schema, channel, message in part:
                if schema.id not in schemas:
                    schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
                if channel.id not in channels:
                    channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                                   schemas[schema.id], channel.metadata)
                writer.add_message(channels[channel.id], message.log_time, message.data, message.publish_time,
                                   message.sequence)
            writer.finish()
        paths.append(path)
        entries.append({"path": path.name, "starting_time": {"nanoseconds_since_epoch": part[0][2].log_time},
                        "duration": {"nanoseconds": part[-1][2].log_time - part[0][2].log_time},
                        "message_count": len(part)})
    metadata = yaml.safe_load((src / "metadata.yaml").read_text())
    info = metadata["rosbag2_bagfile_information"]
    info.update(relative_file_paths=[p.name for p in paths], files=entries, custom_data=None)
    (dst / "metadata.yaml").write_text(yaml.safe_dump(metadata, sort_keys=False))
    return paths


# ------------------------------------------------------------------------ damaged bags
def mcap_file(bag: Path) -> Path:
    return bag / f"{bag.name}_0.mcap"


def copy_bag(src: Path, dst: Path, content: bytes) -> Path:
    """Bag `dst` with `src`'s metadata.yaml and `content` as its MCAP file."""
    dst.mkdir(parents=True)
    (dst / "metadata.yaml").write_text(
        (src / "metadata.yaml").read_text().replace(mcap_file(src).name, mcap_file(dst).name)
    )
    mcap_file(dst).write_bytes(content)
    return dst


def messages_of(episode: Episode) -> int:
    """A generated episode's messages: `/episode`, `/situation`, `/observation` 0, `/command`,
    ACTIVE, its T+1 actions, the world's T replies and the end report."""
    return 2 * (len(episode.actions) + 1) + 5


def write_message_chunks(bag: Path, episodes: list[Episode]) -> Path:
    """A closed bag of `episodes`, one message per chunk: damage costs exactly one message (`message_lost`)."""
    with BagWriter(bag, chunk_size=1) as writer:
        for episode in episodes:
            writer.write_episode(episode)
    return bag


def message_lost(src: Path, dst: Path, t_ns: int) -> Path:
    """A copy of `src` (one message per chunk: `chunk_size=1`) whose chunk holding the message
    at `t_ns` is damaged."""
    with open(mcap_file(src), "rb") as f:
        [chunk] = [c for c in make_reader(f).get_summary().chunk_indexes if c.message_start_time == t_ns]

    def flip(data):
        data[chunk.chunk_start_offset + chunk.chunk_length // 2] ^= 0xFF

    return damaged_copy(src, dst, flip)


def truncated_copy(src: Path, dst: Path, keep: int) -> Path:
    return copy_bag(src, dst, mcap_file(src).read_bytes()[:keep])


def damaged_copy(src: Path, dst: Path, edit) -> Path:
    """A copy whose MCAP bytes went through `edit(bytearray)`."""
    data = bytearray(mcap_file(src).read_bytes())
    edit(data)
    return copy_bag(src, dst, bytes(data))


def data_end(bag: Path) -> int:
    """File offset after the last chunk (its message indexes and the summary follow)."""
    with open(mcap_file(bag), "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    return max(c.chunk_start_offset + c.chunk_length for c in chunks)


WRITER = textwrap.dedent(
    """
    import sys
    sys.path.insert(0, {tests!r})
    import itertools, random, time
    from bag_support import make_episode
    from gscan_ros.data.bag import BagWriter

    writer = BagWriter({bag!r}, chunk_size=2048).open()
    rng = random.Random({seed})
    for i in itertools.count():  # until killed
        writer.write_episode(make_episode(rng, i))
        if i + 1 == {flush_at}:
            writer.flush()
        if i + 1 == {flush_at} + {extra}:  # some more chunks are out, one is being filled
            print("flushed", {flush_at}, flush=True)
            time.sleep(600)
    """
)


def kill_writer(bag: Path, seed: int = 11, flush_at: int = 41, extra: int = 9) -> int:
    """Write make_episodes(…, seed) into `bag` in a child process, flush after `flush_at`
    episodes, write `extra` more and SIGKILL it (a chunk in progress, no summary,
    metadata.yaml still `recording`); returns the number of episodes flushed."""
    child = subprocess.Popen(
        [sys.executable, "-c",
         WRITER.format(tests=str(TESTS), bag=str(bag), seed=seed, flush_at=flush_at, extra=extra)],
        stdout=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        line = child.stdout.readline()
        assert line.startswith("flushed"), line
        os.killpg(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait(timeout=30)
    return int(line.split()[1])
