import json

import pytest

from gscan_ros.cli import main
from gscan_ros.language import BUILTIN_PARSERS


def test_parse_prints_an_indented_tree(capsys):
    assert main(["parse", "walk to a red small circle cautiously"]) == 0
    assert capsys.readouterr().out.splitlines() == [
        "cautiously [cautiously]",
        "  arg: walk [walk]",
        "    arg: red [red]",
        "      arg: small [big|small head 1]",
        "        arg: circle [circle]",
    ]


def test_parse_json_all_prints_one_graph_per_parser(capsys):
    assert main(["parse", "--all", "--json", "--lexicon", "none", "Pull", "a", "red", "circle", "hesitantly"]) == 0
    graphs = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert tuple(g["parser"] for g in graphs) == BUILTIN_PARSERS
    assert {g["command"] for g in graphs} == {"pull a red circle hesitantly"}


def test_parse_all_labels_each_tree(capsys):
    assert main(["parse", "--all", "push a circle"]) == 0
    out = capsys.readouterr().out
    assert "semantic:\npush [push]" in out and "constituency:\nVP [VP_2]" in out and "dependency:\npush [push_1]" in out


@pytest.mark.parametrize(
    "argv, message",
    [
        (["parse", "circle walk"], "not in the gSCAN command grammar"),
        (["parse", "walk to a smal circle"], "unknown word 'smal'; closest known words: 'small'"),
        (["parse", "--parser", "stanza", "walk to a circle"], "unknown parser 'stanza'"),
    ],
)
def test_parse_errors_are_one_line_and_exit_1(capsys, argv, message):
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_parse_says_what_a_paraphrase_was_understood_as(capsys):
    assert main(["parse", "Push", "the", "small", "blue", "cylinder"]) == 0
    assert capsys.readouterr().out.splitlines()[:4] == [
        "understood: push a blue small cylinder",
        "  the → a (determiner)",
        "  small blue → blue small (adjective order: color before size)",
        "",
    ]


def test_parse_json_of_a_paraphrase_is_the_canonical_graph_plus_the_typed_text(capsys):
    assert main(["parse", "--json", "walk to a large circle"]) == 0
    assert main(["parse", "--json", "walk to a big circle"]) == 0
    paraphrased, canonical = (json.loads(line) for line in capsys.readouterr().out.splitlines())
    assert paraphrased.pop("typed") == "walk to a large circle" and paraphrased == canonical
