import pytest
from std_msgs.msg import String

from gscan_ros.errors import GraphError
from gscan_ros.language import BUILTIN_PARSERS, Lexicon, get_parser
from msg_adapters.command_graph import graph_to_msg, msg_to_graph
from msg_adapters.errors import MessageFormatError

BIG_SMALL = Lexicon.from_dict({"format": 1, "parts_of_speech": ["a", "s"],
                               "concepts": [{"words": ["big", "small"], "antonyms": [[0, 1]]}]})


@pytest.mark.parametrize("parser", BUILTIN_PARSERS)
@pytest.mark.parametrize("command", ["pull a red circle hesitantly", "walk to a yellow small square while spinning"])
def test_round_trip(parser, command):
    graph = get_parser(parser, BIG_SMALL).parse(command)
    msg = graph_to_msg(graph)
    assert isinstance(msg, String) and '"schema_version":1' in msg.data
    assert msg_to_graph(msg) == graph


def test_bad_json_raises_graph_error():
    with pytest.raises(GraphError, match="not valid JSON"):
        msg_to_graph(String(data="walk to a circle"))


def test_invalid_graph_raises_graph_error():
    msg = graph_to_msg(get_parser("semantic").parse("walk to a circle"))
    with pytest.raises(GraphError, match="root 7"):
        msg_to_graph(String(data=msg.data.replace('"root":0', '"root":7')))


def test_wrong_message_type():
    with pytest.raises(MessageFormatError, match="expected a std_msgs/String"):
        msg_to_graph(object())
