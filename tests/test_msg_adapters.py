"""Round trips and layout checks of the adapters (domain value <-> CDR bytes), without ROS."""
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from gscan_ros import episode_status as es
from gscan_ros.data.sources import sample_episode
from gscan_ros.errors import GscanError, InvalidActionError
from gscan_ros.interface import EARLIER_OBSERVATION_TYPE, GRID_FRAME, OBSERVATION
from gscan_ros.language import get_parser
from gscan_ros.world.types import Action
from msg_adapters import (
    MessageFormatError,
    ObservationDecoder,
    action_to_cdr,
    attention_to_cdr,
    cdr_to_action,
    cdr_to_attention,
    cdr_to_episode_status,
    cdr_to_graph,
    cdr_to_image,
    cdr_to_msg,
    cdr_to_observation,
    cdr_to_reset,
    cdr_to_situation,
    cdr_to_string_bytes,
    cdr_to_text,
    episode_status_to_cdr,
    graph_to_cdr,
    grid_header,
    image_header,
    image_to_cdr,
    msg_to_cdr,
    observation_to_cdr,
    reset_to_cdr,
    situation_to_cdr,
    text_to_cdr,
    time_ns,
)

from bag_support import earlier_observation_cdr, uint8_multi_array

IMAGE = OBSERVATION.type
observations = arrays(np.uint8, (6, 6, 16), elements=st.integers(0, 1))


def edited(cdr: bytes, msg_type: str, **fields) -> bytes:
    """`cdr` re-serialized with some fields replaced (a message another publisher might send)."""
    return msg_to_cdr(replace(cdr_to_msg(cdr, msg_type), **fields))


@settings(max_examples=30)
@given(observations, st.integers(0, 2**62))
def test_observation_round_trips_through_cdr(obs, stamp_ns):
    data = observation_to_cdr(obs, header=grid_header(stamp_ns))
    assert np.array_equal(cdr_to_observation(data), obs)
    header = image_header(data)
    assert (time_ns(header.stamp), header.frame_id) == (stamp_ns, GRID_FRAME)


def test_observation_is_an_8uc16_image_with_one_pixel_per_cell():
    obs = np.zeros((6, 6, 16), np.uint8)
    obs[2, 5, 11] = 1  # the agent in row 2, column 5
    msg = cdr_to_msg(observation_to_cdr(obs), IMAGE)
    assert (msg.encoding, msg.height, msg.width, msg.step, len(msg.data)) == ("8UC16", 6, 6, 96, 576)
    assert msg.data[2 * msg.step + 5 * 16 + 11] == 1


def test_the_decoded_observation_is_a_read_only_view():
    observation = cdr_to_observation(observation_to_cdr(np.ones((6, 6, 16), np.uint8)))
    with pytest.raises(ValueError):
        observation[0, 0, 0] = 0


def _observation_image(**fields) -> bytes:
    return edited(observation_to_cdr(np.zeros((6, 6, 16), np.uint8)), IMAGE, **fields)


@pytest.mark.parametrize(
    "fields, problem",
    [
        ({"encoding": "16UC1"}, "encoding must be '8UC16'"),
        ({"encoding": "mono8"}, "encoding"),
        ({"height": 5}, r"sizes \[5, 6, 16\]"),
        ({"height": 3, "width": 3, "step": 48}, "square grid of 4 to 16"),
        ({"step": 100}, "step must be 16 \\* width = 96"),
        ({"step": 48}, "step must be 16"),
        ({"data": np.zeros(500, np.uint8)}, "500 bytes"),
    ],
)
def test_observation_image_refusals(fields, problem):
    with pytest.raises(MessageFormatError, match=problem):
        cdr_to_observation(_observation_image(**fields))


def test_observation_refuses_other_messages_and_types():
    with pytest.raises(MessageFormatError, match="malformed sensor_msgs/msg/Image"):
        cdr_to_observation(text_to_cdr("x"))
    with pytest.raises(MessageFormatError, match="not a std_msgs/msg/String"):
        cdr_to_observation(text_to_cdr("x"), "std_msgs/msg/String")


def test_an_earlier_bag_observation_still_reads():
    obs = np.zeros((6, 6, 16), np.uint8)
    obs[1, 2, 3] = 1
    np.testing.assert_array_equal(cdr_to_observation(earlier_observation_cdr(obs), EARLIER_OBSERVATION_TYPE), obs)


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
        cdr_to_observation(uint8_multi_array(dims, np.zeros(data_len, np.uint8)), EARLIER_OBSERVATION_TYPE)


@pytest.mark.parametrize("msg_type", [OBSERVATION.type, EARLIER_OBSERVATION_TYPE])
def test_the_decoder_of_a_bag_channel_reads_every_stamp_and_layout(msg_type):
    """The fast path keys on the bytes outside the stamp and the data: each message still decodes to its own data."""
    decode = ObservationDecoder(msg_type)
    rng = np.random.default_rng(0)
    for t in range(20):
        grid = (6, 12)[t % 2]
        obs = rng.integers(0, 2, (grid, grid, 16), dtype=np.uint8)
        data = observation_to_cdr(obs, header=grid_header(10**18 + t * 12345)) if msg_type == OBSERVATION.type \
            else earlier_observation_cdr(obs)
        np.testing.assert_array_equal(decode(data), obs)
    assert len(decode._layouts) == 2  # one per grid size: every later message took the fast path
    bad = _observation_image(encoding="mono8") if msg_type == OBSERVATION.type else \
        uint8_multi_array([("row", 6, 576)], np.zeros(576, np.uint8))
    with pytest.raises(MessageFormatError):
        decode(bad)


def test_observation_rejects_non_uint8_arrays():
    with pytest.raises(MessageFormatError):
        observation_to_cdr(np.zeros((6, 6, 16), np.float32))
    assert issubclass(MessageFormatError, GscanError)


@settings(max_examples=20)
@given(arrays(np.uint8, st.tuples(st.integers(1, 20), st.integers(1, 20), st.just(3))))
def test_rgb_image_round_trips(rgb):
    data = image_to_cdr(rgb)
    msg = cdr_to_msg(data, IMAGE)
    assert (msg.encoding, msg.height, msg.width, msg.step) == ("rgb8", rgb.shape[0], rgb.shape[1], 3 * rgb.shape[1])
    assert np.array_equal(cdr_to_image(data), rgb)


def test_rgb_image_with_row_padding_is_cropped():
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    padded = np.zeros((2, 12), np.uint8)
    padded[:, :9] = rgb.reshape(2, 9)
    assert np.array_equal(cdr_to_image(edited(image_to_cdr(rgb), IMAGE, step=12, data=padded.reshape(-1))), rgb)


def test_image_rejects_wrong_encoding_and_size():
    data = image_to_cdr(np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(MessageFormatError, match="encoding"):
        cdr_to_image(edited(data, IMAGE, encoding="bgr8"))
    with pytest.raises(MessageFormatError, match="bytes"):
        cdr_to_image(edited(data, IMAGE, height=5))


@settings(max_examples=30)
@given(
    # No subnormals: a policy node built earlier in this process flushes them to zero
    # (torch.set_flush_denormal), and hypothesis then refuses to generate them.
    arrays(np.float32, (6, 6), elements=st.floats(0, 1, width=32, allow_subnormal=False)),
    st.integers(1, 12),
)
def test_attention_round_trip_is_max_normalized(weights, upsample):
    data = attention_to_cdr(weights, upsample=upsample)
    msg = cdr_to_msg(data, IMAGE)
    assert (msg.encoding, msg.height, msg.width) == ("mono8", 6 * upsample, 6 * upsample)
    back = cdr_to_attention(data)
    peak = weights.max()
    expected = weights / peak if peak > 0 else weights
    assert back.dtype == np.float32
    assert np.allclose(back, expected, atol=0.5 / 255 + 1e-6)


def test_attention_peak_is_white_and_blocks_are_constant():
    weights = np.zeros((6, 6), np.float32)
    weights[2, 3] = 0.25
    pixels = cdr_to_msg(attention_to_cdr(weights, upsample=4), IMAGE).data.reshape(24, 24)
    assert pixels[8:12, 12:16].min() == 255
    assert pixels.sum() == 255 * 16


@pytest.mark.parametrize(
    "weights, upsample",
    [(np.full((6, 6), -0.1), 2), (np.full((6, 6), np.nan), 2), (np.zeros((6, 6, 1)), 2), (np.zeros((6, 6)), 0)],
)
def test_attention_rejects_bad_input(weights, upsample):
    with pytest.raises(MessageFormatError):
        attention_to_cdr(weights, upsample=upsample)


def test_attention_rejects_non_square_image():
    data = edited(attention_to_cdr(np.ones((6, 6)), upsample=2), IMAGE, width=6, step=6, data=np.zeros(72, np.uint8))
    with pytest.raises(MessageFormatError, match="square"):
        cdr_to_attention(data)


@pytest.mark.parametrize("action", list(Action))
def test_action_round_trips(action):
    assert cdr_to_action(action_to_cdr(action)) is action


def test_eos_token_and_unknown_token():
    assert cdr_to_text(action_to_cdr(Action.EOS)) == "<eos>"
    with pytest.raises(InvalidActionError, match="jump"):
        cdr_to_action(text_to_cdr("jump"))


@pytest.mark.parametrize("text", ["", "walk to a circle", "größe ✓"])
def test_string_bytes_are_the_serialized_text(text):
    assert cdr_to_string_bytes(text_to_cdr(text)) == text.encode()
    assert cdr_to_text(text_to_cdr(text)) == text


def test_string_bytes_keep_what_a_strict_decoder_would_refuse():
    """Invalid UTF-8 and an embedded NUL reach the parser as sent; as text, invalid UTF-8 is replaced."""
    for payload in (b"walk \xff", b"walk\x00 to"):
        cdr = b"\x00\x01\x00\x00" + (len(payload) + 1).to_bytes(4, "little") + payload + b"\x00"
        assert cdr_to_string_bytes(cdr) == payload
        assert cdr_to_text(cdr) == payload.decode("utf-8", "replace")
    big_endian = b"\x00\x00\x00\x00" + (3).to_bytes(4, "big") + b"ab\x00"
    assert cdr_to_string_bytes(big_endian) == b"ab"


@pytest.mark.parametrize(
    "cdr", [b"", b"\x00\x01\x00\x00\xff\xff\xff\xffab\x00", b"\x00\x02\x00\x00\x01\x00\x00\x00\x00"]
)
def test_string_bytes_reject_malformed_cdr(cdr):
    with pytest.raises(MessageFormatError):
        cdr_to_string_bytes(cdr)


def test_world_reset_stamp_round_trips_through_cdr():
    t_ns = 1_796_007_930_739_793_393
    assert cdr_to_reset(reset_to_cdr(t_ns)) == t_ns
    with pytest.raises(MessageFormatError):
        cdr_to_reset(text_to_cdr("now"))


def test_situation_round_trips_and_bad_json_is_a_format_error():
    situation = sample_episode(0).situation
    assert cdr_to_situation(situation_to_cdr(situation)) == situation
    for bad in ("{not json", "[1, 2]"):
        with pytest.raises(MessageFormatError):
            cdr_to_situation(text_to_cdr(bad))


@pytest.mark.parametrize("outcome", [es.ACTIVE, es.COMPLETE, es.CUT, es.PREEMPTED, es.REJECTED])
def test_episode_status_round_trips(outcome):
    status = es.EpisodeStatus("/policy_node/3", 1_700_000_000_123_456_789, outcome, "walk to a circle")
    assert cdr_to_episode_status(episode_status_to_cdr(status)) == status


def test_episode_status_refuses_a_code_the_policy_never_sends():
    data = edited(episode_status_to_cdr(es.EpisodeStatus("e", 0, es.ACTIVE, "")), "actionlib_msgs/msg/GoalStatus",
                  status=9)  # LOST
    with pytest.raises(MessageFormatError, match="episode status 9 is not one the policy sends"):
        cdr_to_episode_status(data)


def test_command_graph_round_trips():
    graph = get_parser("semantic").parse("walk to a red circle while spinning")
    assert cdr_to_graph(graph_to_cdr(graph)) == graph


GOOD = {
    "action": (cdr_to_action, action_to_cdr(Action.WALK)),
    "text": (cdr_to_text, text_to_cdr("walk to a circle")),
    "episode status": (cdr_to_episode_status, episode_status_to_cdr(es.EpisodeStatus("e", 5, es.ACTIVE, "walk"))),
    "world reset": (cdr_to_reset, reset_to_cdr(5)),
    "observation": (cdr_to_observation, observation_to_cdr(np.zeros((6, 6, 16), np.uint8))),
    "image": (cdr_to_image, image_to_cdr(np.zeros((2, 2, 3), np.uint8))),
    "attention": (cdr_to_attention, attention_to_cdr(np.ones((6, 6)))),
}


@pytest.mark.parametrize("kind", sorted(GOOD))
@pytest.mark.parametrize("damage", ["empty", "truncated", "encapsulation"])
def test_malformed_bytes_are_one_line_format_errors(kind, damage):
    decode, good = GOOD[kind]
    bad = {"empty": b"", "truncated": good[: len(good) // 2], "encapsulation": b"\x00\x0a" + good[2:]}[damage]
    with pytest.raises(MessageFormatError) as caught:
        decode(bad)
    assert "\n" not in str(caught.value)


def test_invalid_utf8_in_a_status_text_is_a_format_error():
    """GoalStatus texts are decoded strictly (only String payloads are judged by their readers)."""
    good = episode_status_to_cdr(es.EpisodeStatus("e", 0, es.ACTIVE, "ab"))
    bad = good.replace(b"ab\x00", b"a\xff\x00")
    with pytest.raises(MessageFormatError, match="utf-8"):
        cdr_to_episode_status(bad)


def test_equal_values_give_equal_bytes_with_zeroed_padding():
    """CDR aligns fields; the padding between them is zero, so bags of equal episodes are equal
    byte for byte. Image: after the frame id and after is_bigendian; GoalStatus: after the status."""
    image = observation_to_cdr(np.zeros((1, 1, 16), np.uint8), header=grid_header(7))
    status = episode_status_to_cdr(es.EpisodeStatus("/policy_node/10", 7, es.ACTIVE, "walk"))
    for data, padding in ((image, [slice(27, 28), slice(47, 48)]), (status, [slice(33, 36)])):
        assert all(b == 0 for span in padding for b in data[span]), data
    assert image == observation_to_cdr(np.zeros((1, 1, 16), np.uint8), header=grid_header(7))
    assert status == episode_status_to_cdr(es.EpisodeStatus("/policy_node/10", 7, es.ACTIVE, "walk"))
