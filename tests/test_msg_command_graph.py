import pytest

from gscan_ros.errors import GraphError
from gscan_ros.language import BUILTIN_PARSERS, Lexicon, get_parser
from msg_adapters import cdr_to_text, text_to_cdr
from msg_adapters.command_graph import cdr_to_graph, graph_to_cdr
from msg_adapters.errors import MessageFormatError

BIG_SMALL = Lexicon.from_dict({"format": 1, "parts_of_speech": ["a", "s"],
                               "concepts": [{"words": ["big", "small"], "antonyms": [[0, 1]]}]})


@pytest.mark.parametrize("parser", BUILTIN_PARSERS)
@pytest.mark.parametrize("command", ["pull a red circle hesitantly", "walk to a yellow small square while spinning"])
def test_round_trip(parser, command):
    graph = get_parser(parser, BIG_SMALL).parse(command)
    data = graph_to_cdr(graph)
    assert '"schema_version":1' in cdr_to_text(data)
    assert cdr_to_graph(data) == graph


def test_bad_json_raises_graph_error():
    with pytest.raises(GraphError, match="not valid JSON"):
        cdr_to_graph(text_to_cdr("walk to a circle"))


def test_invalid_graph_raises_graph_error():
    text = cdr_to_text(graph_to_cdr(get_parser("semantic").parse("walk to a circle")))
    with pytest.raises(GraphError, match="root 7"):
        cdr_to_graph(text_to_cdr(text.replace('"root":0', '"root":7')))


def test_bytes_that_are_no_string_message():
    with pytest.raises(MessageFormatError, match="std_msgs/String"):
        cdr_to_graph(b"\x00\x01\x00\x00")
