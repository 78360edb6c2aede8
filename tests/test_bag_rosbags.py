"""Interoperability: the third-party `rosbags` reader opens our bags and decodes every message,
and the schemas and type hashes our bags record are those of ROS's installed definitions."""
import importlib
import json
from pathlib import Path

import numpy as np
import pytest
from actionlib_msgs.msg import GoalStatus
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from gscan_ros.data.bag import write_bag
from gscan_ros.data.bag_format import ACTION_DELAY_NS, EPISODE_PERIOD_NS, PROLOGUE_NS, STEP_NS
from gscan_ros.data.bag_schema import TOPICS
from gscan_ros.interface import EARLIER_OBSERVATION_TYPE
from msg_adapters import message_definition, type_hash

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


BAG_TYPES = sorted({t.msg_type for t in TOPICS.values()} | {EARLIER_OBSERVATION_TYPE})


def installed_definition(msg_type: str, suffix: str) -> str:
    """The `.msg` (or `.json` type description) that ROS installs for "pkg/msg/Type", in
    <prefix>/share/<pkg>/msg beside <prefix>/lib/pythonX.Y/site-packages/<pkg>."""
    package, _, name = msg_type.split("/")
    prefix = Path(importlib.import_module(package).__file__).resolve().parents[4]
    return (prefix / "share" / package / "msg" / f"{name}{suffix}").read_text(encoding="utf-8")


@pytest.mark.parametrize("msg_type", BAG_TYPES)
def test_schema_text_has_the_fields_and_constants_of_the_installed_definitions(msg_type):
    """Our ros2msg text (rosbags' type store) parses to what ROS's own .msg files say, nested types included."""
    parsed = get_types_from_msg(message_definition(msg_type), msg_type)
    assert msg_type in parsed
    for name, definition in parsed.items():
        assert definition == get_types_from_msg(installed_definition(name, ".msg"), name)[name], name


@pytest.mark.parametrize("msg_type", BAG_TYPES)
def test_type_hash_is_the_installed_one(msg_type):
    description = json.loads(installed_definition(msg_type, ".json"))
    [expected] = [h["hash_string"] for h in description["type_hashes"] if h["type_name"] == msg_type]
    assert type_hash(msg_type) == expected
