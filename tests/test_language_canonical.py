"""Paraphrases parse to exactly their canonical command's graph, under every parser."""
import json
import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gscan_ros.errors import CommandError, GraphError
from gscan_ros.language import BUILTIN_PARSERS, CommandGraph, Lexicon, all_commands, canonicalize, get_parser, tokenize
from gscan_ros.language.graph import MAX_COMMAND_CHARS
from gscan_ros.language.paraphrase import paraphrase

LEXICON = Lexicon.from_wordnet()

# typed -> canonical gSCAN command; the first three are docs/language.md's examples (the first is the paper's Fig. 1).
PARAPHRASES = {
    "Push the small blue cylinder": "push a blue small cylinder",
    "walk to a large circle": "walk to a big circle",
    "walk to the big red circle": "walk to a red big circle",
    "Walk to a RED circle!": "walk to a red circle",
    "  pull   an  ENORMOUS , crimson square carefully. ": "pull a red big square cautiously",
    "walk to the little yellow cylinder while zigzagging": "walk to a yellow small cylinder while zigzagging",
    "push a tiny greenish foursquare hesitatingly": "push a green small square hesitantly",
    "Pull the bluish circle.": "pull a blue circle",
}


def without_typed(graph: CommandGraph) -> dict:
    d = graph.to_dict()
    d.pop("typed", None)
    return d


@pytest.mark.parametrize("name", BUILTIN_PARSERS)
@pytest.mark.parametrize("typed, command", PARAPHRASES.items())
def test_paraphrase_gives_the_canonical_commands_graph(name, typed, command):
    parser = get_parser(name, LEXICON)
    graph, canonical = parser.parse(typed), parser.parse(command)
    assert canonical.typed is None and graph.typed == typed
    assert without_typed(graph) == canonical.to_dict() and graph == canonical
    assert graph.command == command


def test_each_rewrite_is_named():
    assert [str(m) for m in canonicalize("walk to a large circle").mappings] == [
        "large → big (WordNet synonym in large.a.01)"
    ]
    assert [str(m) for m in canonicalize("Push the small blue cylinder").mappings] == [
        "the → a (determiner)",
        "small blue → blue small (adjective order: color before size)",
    ]
    huge = canonicalize("walk to a huge circle")
    assert str(huge.mappings[0]) == "huge → big (WordNet huge.s.01, similar to large.a.01)"
    assert huge.explain() == (
        "understood 'walk to a huge circle' as 'walk to a big circle': "
        "huge → big (WordNet huge.s.01, similar to large.a.01)"
    )


def test_canonical_commands_are_left_as_they_are():
    for command in all_commands():
        canonical = canonicalize(command)
        assert canonical.tokens == tokenize(command) and canonical.mappings == ()


def test_case_and_punctuation_alone_are_no_rewrite():
    canonical = canonicalize("WALK, to a circle!")
    assert canonical.canonical == "walk to a circle" and canonical.mappings == ()
    assert canonical.typed == "WALK, to a circle!"


@pytest.mark.parametrize(
    "text, message",
    [
        ("walk to a purple circle", "unknown word 'purple'; closest known words: 'pull'"),
        ("draw a circle", "unknown word 'draw' (left out of the WordNet synonyms: 'draw a circle' means sketching"),
        ("force a circle", "unknown word 'force' (left out of the WordNet synonyms: ambiguous: in push.v.01"),
        ("walk to a microscopic circle", "microscopic.s.03: too small to see"),
        ("walk to a circle " + " " * MAX_COMMAND_CHARS, f"more than the maximum of {MAX_COMMAND_CHARS}"),
    ],
)
def test_words_wordnet_does_not_tie_to_a_trained_word_stay_errors(text, message):
    with pytest.raises(CommandError) as error:
        canonicalize(text)
    assert message in str(error.value) and "\n" not in str(error.value)


@pytest.mark.parametrize("name", BUILTIN_PARSERS)
def test_canonical_form_outside_the_grammar_is_still_rejected(name):
    """Two sizes stay in their order; "the circle" alone is no command."""
    for text in ("walk to a big small circle", "the circle"):
        with pytest.raises(CommandError, match="not in the gSCAN command grammar"):
            get_parser(name).parse(text)


@settings(max_examples=60, deadline=None)
@given(command=st.sampled_from(all_commands()), seed=st.integers(0, 2**32 - 1))
def test_random_paraphrases_parse_to_their_command_under_every_parser(command, seed):
    text = paraphrase(command, random.Random(seed))
    assert canonicalize(text).canonical == command
    for name in BUILTIN_PARSERS:
        parser = get_parser(name, LEXICON)
        assert without_typed(parser.parse(text)) == parser.parse(command).to_dict()


def test_typed_survives_json_and_old_json_still_loads():
    graph = get_parser("semantic").parse("walk to the big red circle")
    again = CommandGraph.from_json(graph.to_json())
    assert again.typed == "walk to the big red circle" and again == graph
    old = without_typed(graph)
    assert CommandGraph.from_dict(old).typed is None and "typed" not in CommandGraph.from_dict(old).to_dict()


@pytest.mark.parametrize(
    "typed, message", [(7, "typed: expected a string"), ("x" * (MAX_COMMAND_CHARS + 1), "typed has 1001 characters")]
)
def test_bad_typed_field_is_a_graph_error(typed, message):
    d = get_parser("semantic").parse("walk to a circle").to_dict() | {"typed": typed}
    with pytest.raises(GraphError, match=message):
        CommandGraph.from_json(json.dumps(d))
