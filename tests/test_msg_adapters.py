"""Round trips and layout checks of the observation / image / attention / action adapters."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from sensor_msgs.msg import Image
from std_msgs.msg import MultiArrayDimension, String, UInt8MultiArray

from gscan_ros.errors import GscanError, InvalidActionError
from gscan_ros.interface import EARLIER_OBSERVATION_TYPE, GRID_FRAME, OBSERVATION
from gscan_ros.world.types import Action
from msg_adapters import (
    MessageFormatError,
    ObservationDecoder,
    action_to_msg,
    attention_to_msg,
    cdr_to_msg,
    cdr_to_observation,
    grid_header,
    image_to_msg,
    msg_to_action,
    msg_to_attention,
    msg_to_cdr,
    msg_to_image,
    msg_to_observation,
    observation_to_msg,
    time_ns,
)

from bag_support import earlier_observation_msg

observations = arrays(np.uint8, (6, 6, 16), elements=st.integers(0, 1))


@settings(max_examples=30)
@given(observations, st.integers(0, 2**62))
def test_observation_round_trips_through_cdr(obs, stamp_ns):
    msg = cdr_to_msg(msg_to_cdr(observation_to_msg(obs, header=grid_header(stamp_ns))), Image)
    assert np.array_equal(msg_to_observation(msg), obs)
    assert (time_ns(msg.header.stamp), msg.header.frame_id) == (stamp_ns, GRID_FRAME)


def test_observation_is_an_8uc16_image_with_one_pixel_per_cell():
    obs = np.zeros((6, 6, 16), np.uint8)
    obs[2, 5, 11] = 1  # the agent in row 2, column 5
    msg = observation_to_msg(obs)
    assert (msg.encoding, msg.height, msg.width, msg.step, len(msg.data)) == ("8UC16", 6, 6, 96, 576)
    assert msg.data[2 * msg.step + 5 * 16 + 11] == 1


def _observation_image(**fields):
    msg = observation_to_msg(np.zeros((6, 6, 16), np.uint8))
    for name, value in fields.items():
        setattr(msg, name, value)
    return msg


@pytest.mark.parametrize(
    "fields, problem",
    [
        ({"encoding": "16UC1"}, "encoding must be '8UC16'"),
        ({"encoding": "mono8"}, "encoding"),
        ({"height": 5}, r"sizes \[5, 6, 16\]"),
        ({"height": 3, "width": 3, "step": 48}, "square grid of 4 to 16"),
        ({"step": 100}, "step must be 16 \\* width = 96"),
        ({"step": 48}, "step must be 16"),
        ({"data": bytes(500)}, "500 bytes"),
    ],
)
def test_observation_image_refusals(fields, problem):
    with pytest.raises(MessageFormatError, match=problem):
        msg_to_observation(_observation_image(**fields))


def test_observation_refuses_other_messages_and_types():
    with pytest.raises(MessageFormatError, match="sensor_msgs/Image"):
        msg_to_observation(String(data="x"))
    with pytest.raises(MessageFormatError, match="not a std_msgs/msg/String"):
        cdr_to_observation(msg_to_cdr(String(data="x")), "std_msgs/msg/String")


def test_an_earlier_bag_observation_still_reads():
    obs = np.zeros((6, 6, 16), np.uint8)
    obs[1, 2, 3] = 1
    earlier = earlier_observation_msg(obs)
    np.testing.assert_array_equal(msg_to_observation(earlier), obs)
    np.testing.assert_array_equal(cdr_to_observation(msg_to_cdr(earlier), EARLIER_OBSERVATION_TYPE), obs)


def _with_dims(dims, data_len=576):
    msg = UInt8MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=label, size=s, stride=t) for label, s, t in dims]
    msg.data = bytes(data_len)
    return msg


@pytest.mark.parametrize(
    "dims, data_len, problem",
    [
        ([("col", 6, 576), ("row", 6, 96), ("channel", 16, 16)], 576, "labels"),
        ([("row", 6, 576), ("col", 6, 96)], 576, "labels"),
        ([("row", 5, 480), ("col", 6, 96), ("channel", 16, 16)], 480, "sizes"),
        ([("row", 6, 576), ("col", 6, 16), ("channel", 16, 1)], 576, "strides"),
        ([("row", 6, 576), ("col", 6, 96), ("channel", 16, 16)], 500, "bytes"),
    ],
)
def test_earlier_observation_rejects_wrong_layout(dims, data_len, problem):
    with pytest.raises(MessageFormatError, match=problem):
        msg_to_observation(_with_dims(dims, data_len))


@pytest.mark.parametrize("msg_type", [OBSERVATION.type, EARLIER_OBSERVATION_TYPE])
def test_the_decoder_of_a_bag_channel_reads_every_stamp_and_layout(msg_type):
    """The fast path keys on the bytes outside the stamp and the data: each message still decodes to its own data."""
    decode = ObservationDecoder(msg_type)
    rng = np.random.default_rng(0)
    for t in range(20):
        grid = (6, 12)[t % 2]
        obs = rng.integers(0, 2, (grid, grid, 16), dtype=np.uint8)
        msg = observation_to_msg(obs, header=grid_header(10**18 + t * 12345)) if msg_type == OBSERVATION.type \
            else earlier_observation_msg(obs)
        np.testing.assert_array_equal(decode(msg_to_cdr(msg)), obs)
    assert len(decode._layouts) == 2  # one per grid size: every later message took the fast path
    bad = _observation_image(encoding="mono8") if msg_type == OBSERVATION.type else _with_dims([("row", 6, 576)])
    with pytest.raises(MessageFormatError):
        decode(msg_to_cdr(bad))


def test_observation_rejects_non_uint8_arrays():
    with pytest.raises(MessageFormatError):
        observation_to_msg(np.zeros((6, 6, 16), np.float32))
    assert issubclass(MessageFormatError, GscanError)


@settings(max_examples=20)
@given(arrays(np.uint8, st.tuples(st.integers(1, 20), st.integers(1, 20), st.just(3))))
def test_rgb_image_round_trips(rgb):
    msg = cdr_to_msg(msg_to_cdr(image_to_msg(rgb)), Image)
    assert (msg.encoding, msg.height, msg.width, msg.step) == ("rgb8", rgb.shape[0], rgb.shape[1], 3 * rgb.shape[1])
    assert np.array_equal(msg_to_image(msg), rgb)


def test_rgb_image_with_row_padding_is_cropped():
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    msg = image_to_msg(rgb)
    padded = np.zeros((2, 12), np.uint8)
    padded[:, :9] = rgb.reshape(2, 9)
    msg.step, msg.data = 12, padded.tobytes()
    assert np.array_equal(msg_to_image(msg), rgb)


def test_image_rejects_wrong_encoding_and_size():
    msg = image_to_msg(np.zeros((4, 4, 3), np.uint8))
    msg.encoding = "bgr8"
    with pytest.raises(MessageFormatError, match="encoding"):
        msg_to_image(msg)
    msg = image_to_msg(np.zeros((4, 4, 3), np.uint8))
    msg.height = 5
    with pytest.raises(MessageFormatError, match="bytes"):
        msg_to_image(msg)


@settings(max_examples=30)
@given(
    # No subnormals: a policy node built earlier in this process flushes them to zero
    # (torch.set_flush_denormal), and hypothesis then refuses to generate them.
    arrays(np.float32, (6, 6), elements=st.floats(0, 1, width=32, allow_subnormal=False)),
    st.integers(1, 12),
)
def test_attention_round_trip_is_max_normalized(weights, upsample):
    msg = attention_to_msg(weights, upsample=upsample)
    assert (msg.encoding, msg.height, msg.width) == ("mono8", 6 * upsample, 6 * upsample)
    back = msg_to_attention(cdr_to_msg(msg_to_cdr(msg), Image))
    peak = weights.max()
    expected = weights / peak if peak > 0 else weights
    assert back.dtype == np.float32
    assert np.allclose(back, expected, atol=0.5 / 255 + 1e-6)


def test_attention_peak_is_white_and_blocks_are_constant():
    weights = np.zeros((6, 6), np.float32)
    weights[2, 3] = 0.25
    pixels = np.frombuffer(attention_to_msg(weights, upsample=4).data, np.uint8).reshape(24, 24)
    assert pixels[8:12, 12:16].min() == 255
    assert pixels.sum() == 255 * 16


@pytest.mark.parametrize(
    "weights, upsample",
    [(np.full((6, 6), -0.1), 2), (np.full((6, 6), np.nan), 2), (np.zeros((6, 6, 1)), 2), (np.zeros((6, 6)), 0)],
)
def test_attention_rejects_bad_input(weights, upsample):
    with pytest.raises(MessageFormatError):
        attention_to_msg(weights, upsample=upsample)


def test_attention_rejects_non_square_image():
    msg = attention_to_msg(np.ones((6, 6)), upsample=2)
    msg.width, msg.step, msg.data = 6, 6, bytes(72)
    with pytest.raises(MessageFormatError, match="square"):
        msg_to_attention(msg)


@pytest.mark.parametrize("action", list(Action))
def test_action_round_trips(action):
    msg = cdr_to_msg(msg_to_cdr(action_to_msg(action)), String)
    assert msg_to_action(msg) is action


def test_eos_token_and_unknown_token():
    assert action_to_msg(Action.EOS).data == "<eos>"
    with pytest.raises(InvalidActionError, match="jump"):
        msg_to_action(String(data="jump"))


def test_cdr_round_trip_matches_rclpy_serialization():
    from rclpy.serialization import serialize_message as rclpy_serialize

    msg = action_to_msg(Action.PULL)
    assert msg_to_cdr(msg) == rclpy_serialize(msg)
    assert cdr_to_msg(msg_to_cdr(msg), String).data == "pull"


@pytest.mark.parametrize("text", ["", "walk to a circle", "größe ✓"])
def test_string_bytes_are_the_serialized_text(text):
    from msg_adapters import cdr_to_string_bytes

    assert cdr_to_string_bytes(msg_to_cdr(String(data=text))) == text.encode()


def test_string_bytes_keep_what_rclpy_would_replace_or_cut():
    """rclpy decodes b'\\xff' to U+FFFD and stops at NUL; the raw bytes show both."""
    from msg_adapters import cdr_to_string_bytes

    for payload in (b"walk \xff", b"walk\x00 to"):
        cdr = b"\x00\x01\x00\x00" + (len(payload) + 1).to_bytes(4, "little") + payload + b"\x00"
        assert cdr_to_string_bytes(cdr) == payload
    big_endian = b"\x00\x00\x00\x00" + (3).to_bytes(4, "big") + b"ab\x00"
    assert cdr_to_string_bytes(big_endian) == b"ab"


@pytest.mark.parametrize(
    "cdr", [b"", b"\x00\x01\x00\x00\xff\xff\xff\xffab\x00", b"\x00\x02\x00\x00\x01\x00\x00\x00\x00"]
)
def test_string_bytes_reject_malformed_cdr(cdr):
    from msg_adapters import cdr_to_string_bytes

    with pytest.raises(MessageFormatError):
        cdr_to_string_bytes(cdr)


def test_world_reset_stamp_round_trips_through_cdr():
    from std_msgs.msg import Header

    from msg_adapters import msg_to_reset, reset_to_msg

    t_ns = 1_796_007_930_739_793_393
    assert msg_to_reset(cdr_to_msg(msg_to_cdr(reset_to_msg(t_ns)), Header)) == t_ns
    with pytest.raises(MessageFormatError):
        msg_to_reset(String(data="now"))


def test_situation_round_trips_and_bad_json_is_a_format_error():
    from gscan_ros.data.sources import sample_episode
    from msg_adapters import msg_to_situation, situation_to_msg

    situation = sample_episode(0).situation
    assert msg_to_situation(situation_to_msg(situation)) == situation
    for bad in ("{not json", "[1, 2]"):
        with pytest.raises(MessageFormatError):
            msg_to_situation(String(data=bad))


def test_typed_cdr_decoders_of_the_bag_code():
    from msg_adapters import cdr_to_action, cdr_to_text, text_to_msg

    observation = np.zeros((6, 6, 16), np.uint8)
    observation[1, 2, 3] = 1
    np.testing.assert_array_equal(cdr_to_observation(msg_to_cdr(observation_to_msg(observation))), observation)
    assert cdr_to_action(msg_to_cdr(action_to_msg(Action.PUSH))) is Action.PUSH
    assert cdr_to_text(msg_to_cdr(text_to_msg('{"episode_id": 0, "command": "walk"}'))).startswith('{"episode_id"')


def test_cdr_padding_is_zeroed_so_equal_messages_give_equal_bytes():
    """The serializer leaves CDR alignment padding as it found the memory: bags would differ
    run to run. Image (after the frame id and is_bigendian) and GoalStatus (after the status)."""
    from actionlib_msgs.msg import GoalID, GoalStatus
    from sensor_msgs.msg import Image
    from std_msgs.msg import Header

    from msg_adapters import cdr_to_msg, msg_to_cdr

    image = Image(header=Header(frame_id="gscan_grid"), height=1, width=1, encoding="8UC16", step=16,
                  data=bytes(16))
    status = GoalStatus(goal_id=GoalID(id="/policy_node/10"), status=GoalStatus.ACTIVE, text="walk")
    for msg, padding in ((image, [slice(27, 28), slice(47, 48)]), (status, [slice(33, 36)])):
        data = msg_to_cdr(msg)
        assert all(b == 0 for span in padding for b in data[span]), data
        assert cdr_to_msg(data, type(msg)) == msg
