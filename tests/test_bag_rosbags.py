"""Interoperability: the third-party `rosbags` reader opens our bags and decodes every message."""
import json

import numpy as np
import pytest
from actionlib_msgs.msg import GoalStatus
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from gscan_ros.data.bag import write_bag
from gscan_ros.data.bag_format import ACTION_DELAY_NS, EPISODE_PERIOD_NS, PROLOGUE_NS, STEP_NS
from gscan_ros.data.bag_schema import TOPICS, message_definition

from bag_support import make_episodes

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    episodes = make_episodes(6, seed=3)
    bag_dir = tmp_path_factory.mktemp("rosbags") / "bag"
    write_bag(bag_dir, episodes, include_images=True)
    return bag_dir, episodes


def test_rosbags_accepts_metadata_and_lists_topics(recorded):
    bag_dir, episodes = recorded
    steps = sum(len(e.actions) + 1 for e in episodes)
    with Reader(bag_dir) as reader:
        topics = {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
        assert reader.message_count == 5 * len(episodes) + 3 * steps
        assert all(c.msgdef.data for c in reader.connections)  # ros2msg schema text from the MCAP
        assert all(c.digest.startswith("RIHS01_") for c in reader.connections)
    assert topics == {
        "/episode": ("std_msgs/msg/String", len(episodes)),
        "/situation": ("std_msgs/msg/String", len(episodes)),
        "/observation": ("sensor_msgs/msg/Image", steps),
        "/world_image": ("sensor_msgs/msg/Image", steps),
        "/command": ("std_msgs/msg/String", len(episodes)),
        "/episode_status": ("actionlib_msgs/msg/GoalStatus", 2 * len(episodes)),
        "/action": ("std_msgs/msg/String", steps),
    }


def test_rosbags_decodes_the_recorded_values(recorded):
    """Every message, the policy's GoalStatus reports included, with the Jazzy typestore."""
    bag_dir, episodes = recorded
    records, situations, commands, reports, observations, actions, images = [], [], [], [], [], [], 0
    with Reader(bag_dir) as reader:
        for connection, t, raw in reader.messages():
            msg = TYPESTORE.deserialize_cdr(raw, connection.msgtype)
            if connection.topic == "/episode":
                records.append(json.loads(msg.data))
            elif connection.topic == "/situation":
                situations.append(json.loads(msg.data))
            elif connection.topic == "/command":
                commands.append(msg.data)
            elif connection.topic == "/episode_status":
                stamp = msg.goal_id.stamp.sec * 1_000_000_000 + msg.goal_id.stamp.nanosec
                reports.append((msg.goal_id.id, msg.status, stamp, t))
            elif connection.topic == "/observation":
                assert (msg.encoding, msg.height, msg.width, msg.step, msg.header.frame_id) == (
                    "8UC16", 6, 6, 96, "gscan_grid")
                assert msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec == t
                observations.append(np.asarray(msg.data, dtype=np.uint8).reshape(6, 6, 16))
            elif connection.topic == "/action":
                actions.append(msg.data)
            else:
                assert connection.topic == "/world_image"
                assert (msg.encoding, msg.step) == ("rgb8", 3 * msg.width)
                images += 1
    assert [(r["id"], r["split"], r["example_id"], r["command"]) for r in records] == [
        (str(i), e.split, e.example_id, e.command) for i, e in enumerate(episodes)]
    assert situations == [e.situation.to_json() for e in episodes]
    assert commands == [e.command for e in episodes]
    # ACTIVE after the prologue, SUCCEEDED after `<eos>`: both stamped with the episode's start.
    expected = []
    for i, e in enumerate(episodes):
        start = i * EPISODE_PERIOD_NS + 4 * PROLOGUE_NS
        end = i * EPISODE_PERIOD_NS + (len(e.actions) + 1) * STEP_NS + ACTION_DELAY_NS
        expected += [(str(i), GoalStatus.ACTIVE, start, start), (str(i), GoalStatus.SUCCEEDED, start, end)]
    assert reports == expected
    assert images == len(observations)
    assert np.array_equal(np.stack(observations), np.concatenate([e.states() for e in episodes]))
    assert actions == [tok for e in episodes for tok in [a.token for a in e.actions] + ["<eos>"]]


@pytest.mark.parametrize("topic", sorted(TOPICS))
def test_schema_text_matches_the_rosbags_type_definitions(topic):
    """Our ros2msg text (read from the installed .msg files) parses to the same types as rosbags'."""
    msg_type = TOPICS[topic].msg_type
    parsed = get_types_from_msg(message_definition(msg_type), msg_type)
    for name, (_consts, fields) in parsed.items():
        reference = TYPESTORE.fielddefs[name]
        assert [f[0] for f in fields] == [f[0] for f in reference[1]], name
