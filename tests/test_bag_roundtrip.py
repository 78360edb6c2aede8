"""Bags written by write_bag / BagWriter read back as the same Episodes, in the documented
layout (format 2: the live topics with synthetic times); format-1 bags still read."""
import errno
import json
import random
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from no_ros_support import run_without_ros

from gscan_ros import interface
from gscan_ros.data.bag import (
    EPISODE_PERIOD_NS,
    STEP_NS,
    BagEpisodeReader,
    BagWriter,
    iter_bag_episodes,
    read_bag_info,
    write_bag,
)
from gscan_ros.data.bag_cache import load_episode_cache
from gscan_ros.data.bag_format import PROLOGUE_NS
from gscan_ros.errors import DatasetFormatError
from gscan_ros.interface import GRID_FRAME
from gscan_ros.language import get_parser
from gscan_ros.world.render import render
from gscan_ros.world.world import World
from msg_adapters import cdr_to_observation, text_to_cdr, time_ns

from bag_support import earlier_observation_cdr, legacy_bag, make_episodes, write_legacy_episode

MS = 1_000_000
S = 1000 * MS
FIXTURE_V1 = Path(__file__).parent / "fixtures" / "bag_v1"  # written by the format-1 writer


@pytest.fixture(scope="module")
def episodes():
    return make_episodes(30, seed=1)


@pytest.fixture(scope="module")
def bag(tmp_path_factory, episodes):
    bag_dir = tmp_path_factory.mktemp("bags") / "train"
    write_bag(bag_dir, episodes)
    return bag_dir


def _messages_per_episode(episode):
    """`/episode`, `/situation`, `/observation` 0, `/command`, ACTIVE, T+1 actions, T replies, the end."""
    return 2 * (len(episode.actions) + 1) + 5


def _stream(bag: Path):
    """(topic, log time, publish time, decoded message) of every message, in file order."""
    from mcap_ros2.decoder import DecoderFactory

    with open(bag / f"{bag.name}_0.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [(c.topic, m.log_time, m.publish_time, d) for _, c, m, d in reader.iter_decoded_messages()]


def _state(observation) -> np.ndarray:
    assert (observation.encoding, observation.step) == ("8UC16", 16 * observation.width)
    return np.frombuffer(bytes(observation.data), np.uint8).reshape(observation.height, observation.width, 16)


def _layout(episode, t0, graph=False):
    """(topic, time) of a generated episode's messages (docs/bags.md "Episodes")."""
    prologue = ["/episode", "/situation", "/observation", "/command", *(["/command_graph"] if graph else []),
                "/episode_status"]
    layout = [(topic, t0 + k * PROLOGUE_NS) for k, topic in enumerate(prologue)]
    for t in range(len(episode.actions) + 1):
        layout.append(("/action", t0 + (t + 1) * MS))
        if t < len(episode.actions):
            layout.append(("/observation", t0 + (t + 1) * MS + MS // 2))
    return layout + [("/episode_status", t0 + (len(episode.actions) + 1) * MS + MS // 2)]


def test_round_trip_gives_identical_episodes(bag, episodes):
    back = list(iter_bag_episodes(bag))
    assert back == episodes
    assert [e.meta["episode_id"] for e in back] == list(range(len(episodes)))
    assert [e.meta["n"] for e in back] == [e.meta["n"] for e in episodes]  # meta survives


def test_split_filter_keeps_bag_order(bag, episodes):
    back = list(iter_bag_episodes(bag, splits=["test", "visual"]))
    assert back == [e for e in episodes if e.split in ("test", "visual")]


def test_metadata_describes_the_bag(bag, episodes):
    info = read_bag_info(bag)
    assert info.version >= 5 and info.closed and info.format_version == 2
    assert [p.name for p in info.mcap_paths] == ["train_0.mcap"]
    steps = sum(len(e.actions) + 1 for e in episodes)
    assert {t: (i.msg_type, i.message_count) for t, i in info.topics.items()} == {
        "/episode": ("std_msgs/msg/String", len(episodes)),
        "/situation": ("std_msgs/msg/String", len(episodes)),
        "/observation": ("sensor_msgs/msg/Image", steps),
        "/command": ("std_msgs/msg/String", len(episodes)),
        "/episode_status": ("actionlib_msgs/msg/GoalStatus", 2 * len(episodes)),
        "/action": ("std_msgs/msg/String", steps),
    }
    assert info.message_count == sum(map(_messages_per_episode, episodes))
    assert info.episodes == len(episodes)
    assert info.splits == {"train": 10, "test": 10, "visual": 10}
    assert info.start_ns == 0
    last = episodes[-1]
    assert info.duration_ns == (len(episodes) - 1) * S + (len(last.actions) + 1) * MS + MS // 2


def test_mcap_profile_encodings_and_zstd_chunks(bag):
    with open(bag / "train_0.mcap", "rb") as f:
        reader = make_reader(f)
        header, summary = reader.get_header(), reader.get_summary()
    assert header.profile == "ros2"
    assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
    assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
    schemas = {s.name: s.data.decode() for s in summary.schemas.values()}
    assert "MSG: std_msgs/Header" in schemas["sensor_msgs/msg/Image"]
    assert "MSG: actionlib_msgs/GoalID" in schemas["actionlib_msgs/msg/GoalStatus"]
    assert "MSG: builtin_interfaces/Time" in schemas["actionlib_msgs/msg/GoalStatus"]
    assert summary.chunk_indexes and {c.compression for c in summary.chunk_indexes} == {"zstd"}
    latched = {c.topic: "transient_local" in c.metadata["offered_qos_profiles"] for c in summary.channels.values()}
    assert latched == {"/episode": False, "/situation": True, "/observation": True, "/command": False,
                       "/episode_status": False, "/action": False}


def test_offered_qos_is_what_the_live_stack_offers(bag):
    """metadata.yaml and the channels record the interface table's QoS (gscan_ros.interface)."""
    import yaml

    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    with open(bag / "train_0.mcap", "rb") as f:
        channels = {c.topic: c.metadata for c in make_reader(f).get_summary().channels.values()}
    assert len(info["topics_with_message_count"]) == len(channels) == 6
    for entry in info["topics_with_message_count"]:
        name, [qos] = entry["topic_metadata"]["name"], entry["topic_metadata"]["offered_qos_profiles"]
        offered = interface.endpoint_of(name).qos
        assert (qos["depth"], qos["reliability"], qos["durability"]) == (
            offered.depth, offered.reliability, offered.durability), name
        assert yaml.safe_load(channels[name]["offered_qos_profiles"]) == [qos]
    assert interface.COMMAND.qos.depth == interface.EPISODE_STATUS.qos.depth == 1000
    assert interface.OBSERVATION.qos == interface.SITUATION.qos == interface.Qos(1, durability="transient_local")


def test_deterministic_times_and_step_order(bag, episodes):
    stream = _stream(bag)
    times = [t for _, t, _, _ in stream]
    assert times == sorted(times) and len(set(times)) == len(times)
    assert all(log == publish for _, log, publish, _ in stream)
    first, second = episodes[:2]
    expected = _layout(first, 0)
    assert [(topic, t) for topic, t, _, _ in stream[: len(expected)]] == expected
    assert [(topic, t) for topic, t, _, _ in stream[len(expected) : len(expected) + 7]] == _layout(second, S)[:7]
    msgs = [d for _, _, _, d in stream[: len(expected)]]
    assert json.loads(msgs[0].data) == {"version": 2, "id": "0", "episode_id": 0, "split": first.split,
                                        "example_id": first.example_id, "command": first.command, "meta": {"n": 0}}
    assert json.loads(msgs[1].data) == first.situation.to_json()
    states = first.states()
    assert np.array_equal(_state(msgs[2]), states[0])
    assert msgs[3].data == first.command
    active, end = msgs[4], msgs[-1]
    assert (active.goal_id.id, active.status, end.goal_id.id, end.status) == ("0", 1, "0", 3)  # ACTIVE, SUCCEEDED
    assert active.goal_id.stamp == end.goal_id.stamp and active.goal_id.stamp.nanosec == 4 * PROLOGUE_NS
    tokens = [d.data for (topic, _), d in zip(expected, msgs) if topic == "/action"]
    assert tokens == [a.token for a in first.actions] + ["<eos>"]
    assert np.array_equal(np.stack([_state(d) for (topic, _), d in zip(expected, msgs) if topic == "/observation"]),
                          states)
    # Each state is stamped with the synthetic time the world reached it, in the grid frame.
    assert all((time_ns(d.header.stamp), d.header.frame_id) == (t, GRID_FRAME)
               for (topic, t), d in zip(expected, msgs) if topic == "/observation")
    assert json.loads(stream[len(expected)][3].data)["id"] == "1"


def test_writing_is_byte_for_byte_deterministic(tmp_path, episodes):
    write_bag(tmp_path / "a" / "bag", episodes[:5])
    write_bag(tmp_path / "b" / "bag", episodes[:5])
    assert (tmp_path / "a" / "bag" / "bag_0.mcap").read_bytes() == (tmp_path / "b" / "bag" / "bag_0.mcap").read_bytes()


def test_world_images_are_optional_and_ignored_by_the_reader(tmp_path, episodes):
    chosen = episodes[:3]
    write_bag(tmp_path / "img", chosen, include_images=True)
    info = read_bag_info(tmp_path / "img")
    assert info.topics["/world_image"].msg_type == "sensor_msgs/msg/Image"
    assert info.topics["/world_image"].message_count == sum(len(e.actions) + 1 for e in chosen)
    assert info.message_count == sum(_messages_per_episode(e) + len(e.actions) + 1 for e in chosen)
    assert list(iter_bag_episodes(tmp_path / "img")) == chosen
    stream = _stream(tmp_path / "img")
    # Each image follows the observation of the same state, at its time.
    assert [t for topic, t, _, _ in stream if topic == "/world_image"] == [
        t for topic, t, _, _ in stream if topic == "/observation"]
    image = next(d for topic, _, _, d in stream if topic == "/world_image")
    expected = render(World(chosen[0].situation))
    assert (image.encoding, image.height, image.width) == ("rgb8", *expected.shape[:2])
    assert np.array_equal(np.frombuffer(bytes(image.data), np.uint8).reshape(expected.shape), expected)


def test_writer_refuses_to_clobber_unless_told(tmp_path, episodes):
    write_bag(tmp_path / "bag", episodes[:2])
    with pytest.raises(DatasetFormatError, match="not empty"):
        write_bag(tmp_path / "bag", episodes[:1])
    write_bag(tmp_path / "bag", episodes[:1], overwrite=True)
    assert list(iter_bag_episodes(tmp_path / "bag")) == episodes[:1]
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("keep me")
    with pytest.raises(DatasetFormatError, match="not a bag"):
        write_bag(tmp_path / "other", episodes[:1], overwrite=True)


def test_many_random_episodes_round_trip(tmp_path):
    chosen = make_episodes(200, seed=random.Random(5).randint(0, 1000), max_len=40)
    write_bag(tmp_path / "many", chosen)
    assert list(iter_bag_episodes(tmp_path / "many")) == chosen


def test_command_graphs_are_recorded_and_restored(tmp_path, episodes):
    from gscan_ros.errors import GraphError

    parser = get_parser("semantic")
    chosen = episodes[:6]
    graphs = {e.command: parser.parse(e.command) for e in chosen}
    info = write_bag(tmp_path / "g", chosen, graphs=graphs)
    assert info.topics["/command_graph"].message_count == len(chosen)
    assert info.message_count == sum(_messages_per_episode(e) + 1 for e in chosen)
    expected = [m for i, e in enumerate(chosen) for m in _layout(e, i * S, graph=True)]
    stream = _stream(tmp_path / "g")
    assert [(topic, t) for topic, t, _, _ in stream] == expected
    assert [json.loads(d.data) for topic, _, _, d in stream if topic == "/command_graph"] == [
        json.loads(graphs[e.command].to_json()) for e in chosen]
    back = list(iter_bag_episodes(tmp_path / "g"))
    assert back == chosen
    assert [e.meta["command_graph"] for e in back] == [graphs[e.command] for e in chosen]
    with pytest.raises(GraphError, match="no command graph"):
        write_bag(tmp_path / "h", chosen, graphs={})


# -- format 1 ------------------------------------------------------------------------------
def test_a_format_1_bag_still_reads():
    """tests/fixtures/bag_v1: make_episodes(4, seed=3, max_len=7) with their semantic graphs,
    written by the format-1 writer (`/command` headers, no `/episode_status`)."""
    episodes = make_episodes(4, seed=3, max_len=7)
    assert read_bag_info(FIXTURE_V1).format_version == 1
    reader = BagEpisodeReader(FIXTURE_V1, decode_states=True)
    records = list(reader.records())
    assert [r.episode for r in records] == episodes
    assert [r.episode.meta["episode_id"] for r in records] == [0, 1, 2, 3]
    assert [r.episode.meta["n"] for r in records] == [0, 1, 2, 3]
    parser = get_parser("semantic")
    assert [r.episode.meta["command_graph"] for r in records] == [parser.parse(e.command) for e in episodes]
    for record, episode in zip(records, episodes):
        assert np.array_equal(record.states, episode.states())
    assert reader.report.complete and reader.report.episodes_read == 4 and reader.report.outcomes == {}
    assert list(iter_bag_episodes(FIXTURE_V1, splits=["train"])) == [e for e in episodes if e.split == "train"]


def _with_earlier_observations(bag: Path, out: Path, episodes) -> None:
    """A copy of `bag` as format-2 writers before the 8UC16 image wrote it: UInt8MultiArray observations."""
    with open(bag / f"{bag.name}_0.mcap", "rb") as f, BagWriter(out) as writer:
        for schema, channel, message in make_reader(f).iter_messages():
            msg_type, data = schema.name, message.data
            if channel.topic == "/observation":
                msg_type = interface.EARLIER_OBSERVATION_TYPE
                data = earlier_observation_cdr(cdr_to_observation(data))
            writer.add_record(writer.channel(channel.topic, msg_type), data, message.log_time, message.publish_time, 0)
        for episode in episodes:
            writer.count_episode(episode.split)


def test_a_format_2_bag_of_array_observations_still_reads(tmp_path, bag, episodes):
    earlier = tmp_path / "earlier"
    _with_earlier_observations(bag, earlier, episodes)
    assert read_bag_info(earlier).topics["/observation"].msg_type == "std_msgs/msg/UInt8MultiArray"
    reader = BagEpisodeReader(earlier, decode_states=True)
    records = list(reader.records())
    assert [r.episode for r in records] == episodes and reader.report.complete
    for record, episode in zip(records, episodes):
        assert np.array_equal(record.states, episode.states())
    cache = load_episode_cache(earlier)
    assert np.array_equal(cache.states(3), episodes[3].states())


def test_format_1_aborted_episode_reads_as_preempted(tmp_path, episodes):
    with legacy_bag(tmp_path / "v1") as writer:
        write_legacy_episode(writer, episodes[0], 0)
        write_legacy_episode(writer, episodes[1], 1, outcome="aborted")
        write_legacy_episode(writer, episodes[2], 2)
    reader = iter_bag_episodes(tmp_path / "v1")
    assert list(reader) == [episodes[0], episodes[2]]
    assert reader.report.outcomes == {"preempted": 1} and reader.report.complete
    records = list(BagEpisodeReader(tmp_path / "v1", include_incomplete=True).records())
    assert [(r.episode, r.outcome) for r in records] == [
        (episodes[0], "complete"), (episodes[1], "preempted"), (episodes[2], "complete")]


def test_format_1_bad_episodes_cost_themselves_not_the_bag(tmp_path, episodes):
    """Format 1 follows the rule of format 2: an episode with an unknown action token, an
    observation that is no image, a graph that is no graph or too few observations is
    dropped with its reason (the first bad message named with its episode); the episodes
    around it read."""
    cases = {
        "a bad /action message": dict(tokens=["jump"]),
        "its /observation count does not match its actions": dict(observations=False),
    }
    for reason, damage in cases.items():
        bag = tmp_path / reason.split()[-2].strip("/")
        with legacy_bag(bag) as writer:
            write_legacy_episode(writer, episodes[0], 0)
            write_legacy_episode(writer, episodes[1], 7, **damage)
            write_legacy_episode(writer, episodes[2], 2)
        reader = iter_bag_episodes(bag)
        assert list(reader) == [episodes[0], episodes[2]]
        assert reader.report.drop_reasons == {reason: 1} and not reader.report.complete
    assert reader.report.bad_messages == 0
    bag = tmp_path / "tok"
    with legacy_bag(bag) as writer:
        write_legacy_episode(writer, episodes[0], 7, tokens=["jump"])
    reader = iter_bag_episodes(bag)
    assert list(reader) == [] and reader.report.bad_messages == 1
    assert reader.report.first_bad_message.startswith("/action of episode 7: unknown action 'jump'")


def test_bags_are_written_read_and_repaired_without_ros(tmp_path):
    """A machine without ROS (a training box) writes bags, reads them back as Episodes and
    repairs a damaged one: the bag code needs no rclpy and no message package."""
    done = run_without_ros(
        f"""
        from pathlib import Path
        import numpy as np
        from gscan_ros.data.bag import BagEpisodeReader, iter_bag_episodes, repair_bag, write_bag
        from bag_support import data_end, make_episodes, truncated_copy

        tmp = Path({str(tmp_path)!r})
        episodes = make_episodes(8, seed=6)
        write_bag(tmp / "bag", episodes, include_images=True)
        assert list(iter_bag_episodes(tmp / "bag")) == episodes
        records = list(BagEpisodeReader(tmp / "bag", decode_states=True).records())
        assert all(np.array_equal(r.states, e.states()) for r, e in zip(records, episodes))
        cut = truncated_copy(tmp / "bag", tmp / "cut", int(data_end(tmp / "bag") * 0.6))
        repair_bag(cut, tmp / "repaired")
        repaired = list(iter_bag_episodes(tmp / "repaired"))
        assert 0 < len(repaired) < len(episodes) and repaired == episodes[:len(repaired)]
        print(len(repaired), "of", len(episodes), "episodes after repair;", "rclpy" in sys.modules)
        """
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.endswith("episodes after repair; False\n")


def test_format_1_plain_text_command_is_a_dropped_episode_not_a_recovered_one(tmp_path, episodes):
    """A command typed as plain text has no situation to follow it from: the report counts
    it as dropped, with the reason, never among the complete episodes read."""
    with legacy_bag(tmp_path / "v1") as writer:
        write_legacy_episode(writer, episodes[0], 0)
        t0 = 1 * EPISODE_PERIOD_NS
        writer.write_message("/command", interface.COMMAND.type, text_to_cdr("walk to a circle"), t0)
        for t, token in enumerate(("walk", "<eos>")):
            writer.write_message("/action", interface.ACTION.type, text_to_cdr(token), t0 + (t + 1) * STEP_NS)
        write_legacy_episode(writer, episodes[2], 2)
    reader = iter_bag_episodes(tmp_path / "v1")
    assert list(reader) == [episodes[0], episodes[2]]
    assert reader.report.episodes_read == 2 and reader.report.incomplete_episodes == 1
    assert reader.report.drop_reasons == {"a /command with no episode header": 1}


def test_a_close_whose_finish_fails_leaves_the_bag_unfinished(tmp_path, episodes, monkeypatch):
    """A full disk while the MCAP summary is written: metadata.yaml must not say closed."""
    def full_disk(self):
        raise OSError(errno.ENOSPC, "No space left on device")

    writer = BagWriter(tmp_path / "bag").open()
    writer.write_episode(episodes[0])
    monkeypatch.setattr(Writer, "finish", full_disk)
    with pytest.raises(OSError):
        writer.close()
    assert writer._file is None  # closed, not leaked
    info = read_bag_info(tmp_path / "bag")
    assert not info.closed
