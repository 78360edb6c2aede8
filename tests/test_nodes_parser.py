"""parser_node in-process: graphs for good commands, one status line per bad one, never a crash."""
import pytest
from std_msgs.msg import String

from gscan_ros.errors import CheckpointError, CommandError
from gscan_ros.language import get_parser
from gscan_ros.nodes.common import EVENT_QOS, LATCHED_LOG_QOS
from gscan_ros.nodes.parser_node import ParserNode
from msg_adapters import cdr_to_graph, text_to_cdr

from ros_helpers import parameters


def cdr(text: str | bytes) -> bytes:
    """A serialized std_msgs/String, as the parser's raw subscription receives it (any bytes)."""
    if isinstance(text, str):
        return text_to_cdr(text)
    return b"\x00\x01\x00\x00" + (len(text) + 1).to_bytes(4, "little") + text + b"\x00"


@pytest.fixture
def parser(probe, checkpoint):
    node = ParserNode(context=probe.context, parameter_overrides=parameters(checkpoint=str(checkpoint)))
    probe.executor.add_node(node)
    return node


def test_command_becomes_the_checkpoint_parsers_graph(probe, parser):
    graphs = probe.record("command_graph", String, LATCHED_LOG_QOS, raw=True)
    parser.on_command(cdr("Walk to a RED circle while spinning"))
    probe.spin_until(lambda: graphs, what="a command graph")
    assert cdr_to_graph(graphs[0]) == get_parser("semantic").parse("walk to a red circle while spinning")


BAD = {
    "unknown word": ("walk to a purple circle", "unknown word 'purple'"),
    "empty": ("", "command is empty"),
    "10 kB": ("x" * 10_000, "longer than max_command_chars=1000"),
    "10 kB of words": ("walk " * 2_000, "longer than max_command_chars=1000"),
    "ungrammatical": ("circle a to walk", "not in the gSCAN command grammar"),
    "control characters": ("walk\x07 to a circle", "non-printable character 0x0007 at position 4"),
    # rclpy would decode these to 'walk to a \ufffd circle' and 'walk' (both accepted)
    "invalid UTF-8": (b"walk to a \xff circle", "not valid UTF-8 (byte 0xff at position 10)"),
    "embedded NUL": (b"walk\x00 to a circle", "non-printable character 0x0000 at position 4"),
}


def test_each_bad_command_gives_one_short_status_line(probe, parser):
    status = probe.record("status", String, EVENT_QOS)
    graphs = probe.record("command_graph", String, LATCHED_LOG_QOS, raw=True)
    for text, _ in BAD.values():
        parser.on_command(cdr(text))
    probe.spin_until(lambda: len(status) == len(BAD), what=f"{len(BAD)} status lines")
    for (name, (_, reason)), line in zip(BAD.items(), status):
        assert line.data.startswith("parser_node: rejected command"), name
        assert reason in line.data, name
        assert len(line.data) <= 320 and "\n" not in line.data, name
    assert graphs == []


def test_a_message_that_is_no_string_is_reported_rejected_on_episode_status(probe, parser):
    """A command whose bytes hold no std_msgs/String still gets its typed REJECTED report."""
    from actionlib_msgs.msg import GoalStatus

    from msg_adapters import cdr_to_episode_status

    reports = probe.record("episode_status", GoalStatus, EVENT_QOS, raw=True)
    parser.on_command(b"\x00\x01\x00\x00\xff\xff\x00\x00walk")  # a length field beyond the data
    probe.spin_until(lambda: reports, what="a report")
    report = cdr_to_episode_status(reports[0])
    assert report.outcome == "rejected" and report.text.startswith("rejected command (an unreadable std_msgs/String)")


def test_unknown_parser_or_missing_checkpoint_is_a_start_up_error(probe, checkpoint, tmp_path):
    with pytest.raises(CommandError):
        ParserNode(context=probe.context, parameter_overrides=parameters(checkpoint=str(checkpoint), parser="magic"))
    with pytest.raises(CheckpointError):
        ParserNode(context=probe.context, parameter_overrides=parameters(checkpoint=str(tmp_path / "none.pt")))


def test_invalid_utf8_published_on_the_topic_is_rejected(probe, parser):
    """Through DDS, not just the callback: the subscription must hand over the raw bytes."""
    status = probe.record("status", String, EVENT_QOS)
    commands = probe.node.create_publisher(String, "command", EVENT_QOS)
    probe.publish_when_matched(commands, cdr(b"walk to a \xff circle"))
    probe.spin_until(lambda: status, what="a rejection")
    assert "not valid UTF-8 (byte 0xff at position 10)" in status[0].data
    assert "\\xff" in status[0].data  # the bad byte is shown, not replaced


def test_paraphrase_becomes_its_canonical_graph_and_the_mapping_goes_on_status(probe, parser):
    status = probe.record("status", String, EVENT_QOS)
    graphs = probe.record("command_graph", String, LATCHED_LOG_QOS, raw=True)
    parser.on_command(cdr("Walk to the LARGE circle!"))
    probe.spin_until(lambda: graphs and status, what="a command graph and a status line")
    graph = cdr_to_graph(graphs[0])
    assert graph == get_parser("semantic").parse("walk to a big circle") and graph.typed == "Walk to the LARGE circle!"
    assert status[0].data == (
        "parser_node: understood 'Walk to the LARGE circle!' as 'walk to a big circle': "
        "the → a (determiner); large → big (WordNet synonym in large.a.01) (3 nodes)"
    )
