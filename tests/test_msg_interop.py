"""msg_adapters' bytes (rosbags' serializer) and rclpy's agree, for every message type the
stack sends: ours deserialize under rclpy to the expected fields, and rclpy's decode through
msg_adapters (padding as rclpy leaves it included)."""
import numpy as np
import pytest
from actionlib_msgs.msg import GoalID, GoalStatus
from builtin_interfaces.msg import Time
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image
from std_msgs.msg import Header, MultiArrayDimension, String, UInt8MultiArray

from gscan_ros import episode_status as es
from gscan_ros.data.sources import sample_episode
from gscan_ros.interface import EARLIER_OBSERVATION_TYPE, GRID_FRAME
from gscan_ros.language import get_parser
from gscan_ros.world import World
from gscan_ros.world.render import render
from gscan_ros.world.types import Action
from msg_adapters import (
    ObservationDecoder,
    action_to_cdr,
    attention_to_cdr,
    cdr_to_action,
    cdr_to_attention,
    cdr_to_episode_status,
    cdr_to_graph,
    cdr_to_image,
    cdr_to_observation,
    cdr_to_reset,
    cdr_to_situation,
    cdr_to_text,
    episode_status_to_cdr,
    graph_to_cdr,
    grid_header,
    image_header,
    image_to_cdr,
    observation_to_cdr,
    reset_to_cdr,
    situation_to_cdr,
    text_to_cdr,
)

T_NS = 1_796_007_930_739_793_393
STAMP = Time(sec=T_NS // 10**9, nanosec=T_NS % 10**9)


def ros_image(pixels: np.ndarray, encoding: str, frame_id: str = GRID_FRAME) -> Image:
    channels = 1 if pixels.ndim == 2 else pixels.shape[2]
    return Image(header=Header(stamp=STAMP, frame_id=frame_id), height=pixels.shape[0], width=pixels.shape[1],
                 encoding=encoding, step=pixels.shape[1] * channels, data=pixels.tobytes())


@pytest.mark.parametrize("text", ["", "walk to a red circle", "größe ✓ " * 50])
def test_strings_are_the_same_bytes(text):
    assert text_to_cdr(text) == serialize_message(String(data=text))
    assert deserialize_message(text_to_cdr(text), String).data == text
    assert cdr_to_text(serialize_message(String(data=text))) == text


def test_string_payloads_action_graph_situation():
    graph = get_parser("semantic").parse("walk to a red circle while spinning")
    situation = sample_episode(2).situation
    assert deserialize_message(action_to_cdr(Action.TURN_LEFT), String).data == "turn left"
    assert cdr_to_action(serialize_message(String(data="<eos>"))) is Action.EOS
    assert cdr_to_graph(serialize_message(String(data=deserialize_message(graph_to_cdr(graph), String).data))) == graph
    assert cdr_to_situation(serialize_message(deserialize_message(situation_to_cdr(situation), String))) == situation


def test_world_reset_header():
    msg = deserialize_message(reset_to_cdr(T_NS), Header)
    assert (msg.stamp.sec, msg.stamp.nanosec, msg.frame_id) == (STAMP.sec, STAMP.nanosec, "")
    assert cdr_to_reset(serialize_message(Header(stamp=STAMP))) == T_NS


@pytest.mark.parametrize("outcome, code", [(es.ACTIVE, GoalStatus.ACTIVE), (es.COMPLETE, GoalStatus.SUCCEEDED),
                                           (es.CUT, GoalStatus.ABORTED), (es.PREEMPTED, GoalStatus.PREEMPTED),
                                           (es.REJECTED, GoalStatus.REJECTED)])
def test_episode_status_goal_status(outcome, code):
    status = es.EpisodeStatus("/policy_node/7", T_NS, outcome, "walk to a circle")
    msg = deserialize_message(episode_status_to_cdr(status), GoalStatus)
    assert (msg.goal_id.id, msg.goal_id.stamp, msg.status, msg.text) == ("/policy_node/7", STAMP, code, status.text)
    ros = GoalStatus(goal_id=GoalID(stamp=STAMP, id="/policy_node/7"), status=code, text="walk to a circle")
    assert cdr_to_episode_status(serialize_message(ros)) == status


def test_observation_image():
    observation = World(sample_episode(4, 12).situation).encode()
    msg = deserialize_message(observation_to_cdr(observation, header=grid_header(T_NS)), Image)
    assert (msg.header.stamp, msg.header.frame_id, msg.encoding, msg.height, msg.width, msg.step, msg.is_bigendian) == (
        STAMP, GRID_FRAME, "8UC16", 12, 12, 192, 0)
    assert bytes(msg.data) == observation.tobytes()
    # Odd frame lengths put rclpy's (unzeroed) padding after the frame id and after is_bigendian.
    decode = ObservationDecoder()
    for frame_id in ("gscan_grid", "g", "grid_a"):
        data = serialize_message(ros_image(observation, "8UC16", frame_id))
        np.testing.assert_array_equal(cdr_to_observation(data), observation)
        np.testing.assert_array_equal(decode(data), observation)
        header = image_header(data)
        assert (header.stamp.sec, header.stamp.nanosec, header.frame_id) == (STAMP.sec, STAMP.nanosec, frame_id)


def test_earlier_uint8_multi_array_observation():
    observation = World(sample_episode(1).situation).encode()
    rows, cols, channels = observation.shape
    msg = UInt8MultiArray(data=observation.tobytes())
    msg.layout.dim = [MultiArrayDimension(label="row", size=rows, stride=rows * cols * channels),
                      MultiArrayDimension(label="col", size=cols, stride=cols * channels),
                      MultiArrayDimension(label="channel", size=channels, stride=channels)]
    data = serialize_message(msg)
    np.testing.assert_array_equal(cdr_to_observation(data, EARLIER_OBSERVATION_TYPE), observation)
    np.testing.assert_array_equal(ObservationDecoder(EARLIER_OBSERVATION_TYPE)(data), observation)


def test_world_image_and_attention_map():
    rgb = render(World(sample_episode(0).situation))
    msg = deserialize_message(image_to_cdr(rgb, header=grid_header(T_NS)), Image)
    assert (msg.encoding, msg.height, msg.width, msg.step, msg.header.stamp) == (
        "rgb8", *rgb.shape[:2], 3 * rgb.shape[1], STAMP)
    assert bytes(msg.data) == rgb.tobytes()
    np.testing.assert_array_equal(cdr_to_image(serialize_message(ros_image(rgb, "rgb8"))), rgb)
    weights = np.eye(6)
    msg = deserialize_message(attention_to_cdr(weights, upsample=3), Image)
    assert (msg.encoding, msg.height, msg.width, msg.step) == ("mono8", 18, 18, 18)
    pixels = np.frombuffer(bytes(msg.data), np.uint8).reshape(18, 18)
    np.testing.assert_array_equal(pixels[::3, ::3], 255 * weights)
    np.testing.assert_allclose(cdr_to_attention(serialize_message(ros_image(pixels, "mono8"))), weights)
