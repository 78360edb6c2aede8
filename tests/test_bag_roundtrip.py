"""Bags written by write_bag / BagWriter read back as the same Episodes, in the documented layout."""
import json
import random

import numpy as np
import pytest
from mcap.reader import make_reader
from std_msgs.msg import String

from gscan_ros.data.bag import BagWriter, iter_bag_episodes, read_bag_info, write_bag
from gscan_ros.errors import DatasetFormatError
from gscan_ros.world.world import World

from bag_support import make_episodes

MS = 1_000_000


@pytest.fixture(scope="module")
def episodes():
    return make_episodes(30, seed=1)


@pytest.fixture(scope="module")
def bag(tmp_path_factory, episodes):
    bag_dir = tmp_path_factory.mktemp("bags") / "train"
    write_bag(bag_dir, episodes)
    return bag_dir


def _expected_messages(episodes):
    return sum(1 + 2 * (len(e.actions) + 1) for e in episodes)


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
    assert info.version >= 5 and info.closed
    assert [p.name for p in info.mcap_paths] == ["train_0.mcap"]
    assert {t: (i.msg_type, i.message_count) for t, i in info.topics.items()} == {
        "/command": ("std_msgs/msg/String", len(episodes)),
        "/observation": ("std_msgs/msg/UInt8MultiArray", sum(len(e.actions) + 1 for e in episodes)),
        "/action": ("std_msgs/msg/String", sum(len(e.actions) + 1 for e in episodes)),
    }
    assert info.message_count == _expected_messages(episodes)
    assert info.episodes == len(episodes)
    assert info.splits == {"train": 10, "test": 10, "visual": 10}
    assert info.start_ns == 0
    last = episodes[-1]
    assert info.duration_ns == (len(episodes) - 1) * 1000 * MS + (len(last.actions) + 1) * MS + MS // 2


def test_mcap_profile_encodings_and_zstd_chunks(bag):
    with open(bag / "train_0.mcap", "rb") as f:
        reader = make_reader(f)
        header, summary = reader.get_header(), reader.get_summary()
    assert header.profile == "ros2"
    assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
    assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
    schema = next(s for s in summary.schemas.values() if s.name == "std_msgs/msg/UInt8MultiArray")
    text = schema.data.decode()
    assert "MSG: std_msgs/MultiArrayLayout" in text and "MSG: std_msgs/MultiArrayDimension" in text
    assert summary.chunk_indexes and {c.compression for c in summary.chunk_indexes} == {"zstd"}
    latched = {c.topic: "transient_local" in c.metadata["offered_qos_profiles"] for c in summary.channels.values()}
    assert latched == {"/command": False, "/observation": True, "/action": False}


def test_offered_qos_is_what_the_live_stack_offers(bag):
    """metadata.yaml and the channels record the interface table's QoS (gscan_ros.interface)."""
    import yaml

    from gscan_ros import interface

    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    with open(bag / "train_0.mcap", "rb") as f:
        channels = {c.topic: c.metadata for c in make_reader(f).get_summary().channels.values()}
    for entry in info["topics_with_message_count"]:
        name, [qos] = entry["topic_metadata"]["name"], entry["topic_metadata"]["offered_qos_profiles"]
        offered = interface.endpoint_of(name).qos
        assert (qos["depth"], qos["reliability"], qos["durability"]) == (
            offered.depth, offered.reliability, offered.durability), name
        assert yaml.safe_load(channels[name]["offered_qos_profiles"]) == [qos]
    assert interface.COMMAND.qos.depth == 1000 and interface.OBSERVATION.qos.depth == 64


def test_deterministic_times_and_step_order(bag, episodes):
    with open(bag / "train_0.mcap", "rb") as f:
        stream = [(c.topic, m.log_time, d) for _, c, m, d in _decoded(f)]
    times = [t for _, t, _ in stream]
    assert times == sorted(times) and len(set(times)) == len(times)
    first = episodes[0]
    expected = [("/command", 0)]
    for t in range(len(first.actions) + 1):
        expected += [("/observation", (t + 1) * MS), ("/action", (t + 1) * MS + MS // 2)]
    assert [(topic, t) for topic, t, _ in stream[: len(expected)]] == expected
    second = stream[len(expected)]
    assert second[:2] == ("/command", 1000 * MS)
    assert json.loads(second[2].data)["episode_id"] == 1
    tokens = [d.data for topic, _, d in stream[: len(expected)] if topic == "/action"]
    assert tokens == [a.token for a in first.actions] + ["<eos>"]


def _decoded(f):
    from mcap_ros2.decoder import DecoderFactory

    return make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()


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
    assert list(iter_bag_episodes(tmp_path / "img")) == chosen
    with open(tmp_path / "img" / "img_0.mcap", "rb") as f:
        image = next(d for _, c, _, d in _decoded(f) if c.topic == "/world_image")
    expected = World(chosen[0].situation).render()
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


def test_live_recording_with_real_times(tmp_path, episodes):
    """A recorder writes message by message; a plain-text command (no header) is not an episode."""
    from gscan_ros.data.bag import episode_header
    from msg_adapters import action_to_msg, observation_to_msg

    episode = episodes[4]
    t = 1_700_000_000 * 10**9
    with BagWriter(tmp_path / "live") as writer:
        writer.write_message("/command", String(data="walk to a red circle"), t)
        first = action_to_msg(episode.actions[0]) if episode.actions else String(data="stay")
        writer.write_message("/action", first, t + 1)
        header = json.dumps(episode_header(episode, 0))
        writer.write_message("/command", String(data=header), t + 10)
        for k, (state, action) in enumerate(zip(episode.states(), (*episode.actions, None))):
            writer.write_message("/observation", observation_to_msg(state), t + 11 + 2 * k)
            msg = action_to_msg(action) if action is not None else String(data="<eos>")
            writer.write_message("/action", msg, t + 12 + 2 * k)
            writer.write_message("/status", String(data="stepping"), t + 12 + 2 * k)
        writer.flush()
    reader = iter_bag_episodes(tmp_path / "live")
    assert list(reader) == [episode]
    assert reader.report.incomplete_episodes == 1 and reader.report.discarded_messages == 2
    info = read_bag_info(tmp_path / "live")
    assert info.start_ns == t and info.topics["/status"].msg_type == "std_msgs/msg/String"


def test_observation_count_mismatch_is_a_format_error(tmp_path, episodes):
    from gscan_ros.data.bag import episode_header
    from msg_adapters import action_to_msg

    episode = episodes[0]
    with BagWriter(tmp_path / "bad") as writer:
        writer.write_message("/command", String(data=json.dumps(episode_header(episode, 0))), 0)
        for k, action in enumerate((*episode.actions, None)):
            msg = action_to_msg(action) if action is not None else String(data="<eos>")
            writer.write_message("/action", msg, k + 1)
    with pytest.raises(DatasetFormatError, match="bad_0.mcap: episode 0: 0 observations"):
        list(iter_bag_episodes(tmp_path / "bad"))


def test_unknown_action_token_names_file_and_episode(tmp_path, episodes):
    from gscan_ros.data.bag import episode_header

    with BagWriter(tmp_path / "tok") as writer:
        writer.write_message("/command", String(data=json.dumps(episode_header(episodes[0], 7))), 0)
        writer.write_message("/action", String(data="jump"), 1)
    with pytest.raises(DatasetFormatError, match=r"tok_0.mcap: episode 7: unknown action 'jump'"):
        list(iter_bag_episodes(tmp_path / "tok"))


def test_many_random_episodes_round_trip(tmp_path):
    chosen = make_episodes(200, seed=random.Random(5).randint(0, 1000), max_len=40)
    write_bag(tmp_path / "many", chosen)
    assert list(iter_bag_episodes(tmp_path / "many")) == chosen


def test_command_graphs_are_recorded_and_restored(tmp_path, episodes):
    from gscan_ros.errors import GraphError
    from gscan_ros.language import get_parser

    parser = get_parser("semantic")
    chosen = episodes[:6]
    graphs = {e.command: parser.parse(e.command) for e in chosen}
    info = write_bag(tmp_path / "g", chosen, graphs=graphs)
    assert info.topics["/command_graph"].message_count == len(chosen)
    back = list(iter_bag_episodes(tmp_path / "g"))
    assert back == chosen
    assert [e.meta["command_graph"] for e in back] == [graphs[e.command] for e in chosen]
    with pytest.raises(GraphError, match="no command graph"):
        write_bag(tmp_path / "h", chosen, graphs={})
