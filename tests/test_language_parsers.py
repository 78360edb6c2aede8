from collections import defaultdict

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gscan_ros.errors import CommandError, GraphError
from gscan_ros.language import (
    BUILTIN_PARSERS,
    VOCABULARY,
    CommandGraph,
    Lexicon,
    Parser,
    all_commands,
    available_parsers,
    canonicalize,
    get_parser,
    graph_from_dependencies,
    register_parser,
    registry,
    tokenize,
)
from gscan_ros.language.grammar import gscan_grammar, parse_tree
from gscan_ros.language.graph import DUMMY_ROOT_WORD
from gscan_ros.language.semantic import CHAIN_ORDER

GSCAN = frozenset(all_commands())
BIG_SMALL = Lexicon.from_dict({"format": 1, "parts_of_speech": ["a", "s"],
                               "concepts": [{"words": ["big", "small"], "antonyms": [[0, 1]]}]})


def shape(graph: CommandGraph):
    """Nodes (id, word, module, arity, head), edges (parent, child, label, slot), root."""
    return (
        [(n.id, n.word, n.module, n.arity, n.head) for n in graph.nodes],
        [(e.parent, e.child, e.label, e.slot) for e in graph.edges],
        graph.root,
    )


@pytest.fixture(scope="module", params=BUILTIN_PARSERS)
def parser(request):
    return get_parser(request.param, BIG_SMALL)


def test_builtin_parsers_are_the_papers_three_and_registered():
    assert BUILTIN_PARSERS == ("semantic", "constituency", "dependency")  # the three of Kuo et al. (2021)
    assert set(BUILTIN_PARSERS) <= set(available_parsers())
    for name in BUILTIN_PARSERS:
        p = get_parser(name)
        assert isinstance(p, Parser) and p.name == name


def test_every_gscan_command_parses_with_one_arity_per_module_key(parser):
    arity_of: dict[str, set[int]] = defaultdict(set)
    for command in all_commands():
        graph = parser.parse(command)
        assert CommandGraph.from_json(graph.to_json()) == graph  # valid, and survives the wire
        assert graph.command == command and graph.parser == parser.name
        for node in graph.nodes:
            arity_of[node.module].add(node.arity)
    assert {k: a for k, a in arity_of.items() if len(a) > 1} == {}


def test_module_keys_are_stable(parser):
    keys = {m for c in all_commands() for m in parser.parse(c).modules()}
    expected = {
        "semantic": {"walk", "push", "pull", "circle", "square", "cylinder", "red", "green", "yellow", "blue",
                     "big|small", "cautiously", "hesitantly", "while spinning", "while zigzagging"},
        "constituency": {"VP_2", "VP_3", "NP_1", "NP_2", "NP_3", "walk", "push", "pull", "circle", "square",
                         "cylinder", "red", "green", "yellow", "blue", "big|small", "cautiously", "hesitantly",
                         "while spinning", "while zigzagging"},
        "dependency": {"walk_1", "walk_2", "push_1", "push_2", "pull_1", "pull_2"}
        | {f"{n}_{k}" for n in ("circle", "square", "cylinder") for k in (0, 1, 2)}
        | {f"{w}_0" for w in ("red", "green", "yellow", "blue", "big|small", "cautiously", "hesitantly",
                              "while spinning", "while zigzagging")},
    }[parser.name]
    assert keys == expected


# The paper's Fig. 2 ("Pull the red circle hesitantly.") in gSCAN words, one per formalism.
FIG2 = {
    "semantic": (
        [(0, "hesitantly", "hesitantly", 1, 0), (1, "pull", "pull", 1, 0), (2, "red", "red", 1, 0),
         (3, "circle", "circle", 0, 0)],
        [(0, 1, "arg", 0), (1, 2, "arg", 0), (2, 3, "arg", 0)],
        0,
    ),
    "constituency": (
        [(0, "VP", "VP_3", 3, 0), (1, "pull", "pull", 0, 0), (2, "NP", "NP_2", 2, 0), (3, "red", "red", 0, 0),
         (4, "circle", "circle", 0, 0), (5, "hesitantly", "hesitantly", 0, 0)],
        [(0, 1, "VB", 0), (0, 2, "NP", 1), (0, 5, "ADVP", 2), (2, 3, "JJ", 0), (2, 4, "NN", 1)],
        0,
    ),
    "dependency": (
        [(0, "pull", "pull_2", 2, 0), (1, "red", "red_0", 0, 0), (2, "circle", "circle_1", 1, 0),
         (3, "hesitantly", "hesitantly_0", 0, 0)],
        [(0, 2, "obj", 0), (0, 3, "advmod", 1), (2, 1, "amod", 0)],
        0,
    ),
}


@pytest.mark.parametrize("name", BUILTIN_PARSERS)
def test_fig2_snapshot(name):
    assert shape(get_parser(name).parse("Pull a red circle hesitantly.")) == FIG2[name]


# "walk to a red small circle while spinning": the original's chain
# (github.com/ylkuo/compositional-gscan), shared big|small.
SPINNING = {
    "semantic": (
        [(0, "while spinning", "while spinning", 1, 0), (1, "walk", "walk", 1, 0), (2, "red", "red", 1, 0),
         (3, "small", "big|small", 1, 1), (4, "circle", "circle", 0, 0)],
        [(0, 1, "arg", 0), (1, 2, "arg", 0), (2, 3, "arg", 0), (3, 4, "arg", 0)],
        0,
    ),
    "constituency": (
        [(0, "VP", "VP_3", 3, 0), (1, "walk", "walk", 0, 0), (2, "NP", "NP_3", 3, 0), (3, "red", "red", 0, 0),
         (4, "small", "big|small", 0, 1), (5, "circle", "circle", 0, 0),
         (6, "while spinning", "while spinning", 0, 0)],
        [(0, 1, "VB", 0), (0, 2, "PP", 1), (0, 6, "SBAR", 2), (2, 3, "JJ", 0), (2, 4, "JJ", 1), (2, 5, "NN", 2)],
        0,
    ),
    "dependency": (
        [(0, "walk", "walk_2", 2, 0), (1, "red", "red_0", 0, 0), (2, "small", "big|small_0", 0, 1),
         (3, "circle", "circle_2", 2, 0), (4, "while spinning", "while spinning_0", 0, 0)],
        [(0, 3, "obl", 0), (0, 4, "advcl", 1), (3, 1, "amod", 0), (3, 2, "amod", 1)],
        0,
    ),
}


@pytest.mark.parametrize("name", BUILTIN_PARSERS)
def test_spinning_snapshot_with_shared_big_small(name):
    assert shape(get_parser(name, BIG_SMALL).parse("walk to a red small circle while spinning")) == SPINNING[name]


def test_semantic_big_uses_the_other_head_of_the_same_module():
    graph = get_parser("semantic", BIG_SMALL).parse("push a big cylinder")
    assert [(n.word, n.module, n.head) for n in graph.nodes] == [
        ("push", "push", 0), ("big", "big|small", 0), ("cylinder", "cylinder", 0)]


def test_dependency_argument_slots_follow_the_label_not_the_position():
    # The object precedes the adverb in every command; slots must come from the label order.
    words, heads, labels = ["cautiously", "walk", "circle"], [1, None, 1], ["advmod", "root", "obl"]
    graph = graph_from_dependencies("cautiously walk circle", "x", words, heads, labels)
    assert [(e.label, e.slot) for e in graph.edges] == [("obl", 0), ("advmod", 1)]


def test_dependency_multitree_gets_a_dummy_root():
    graph = graph_from_dependencies("walk . push", "spacy", ["walk", ".", "push"], [0, 0, 2],
                                    ["ROOT", "punct", "ROOT"])
    root = graph.node(graph.root)
    assert (root.word, root.module, root.arity) == (DUMMY_ROOT_WORD, f"{DUMMY_ROOT_WORD}_2", 2)
    assert [graph.node(c).module for c in graph.children(graph.root)] == ["walk_0", "push_0"]


def test_dependency_rejects_a_word_hanging_off_a_dropped_word():
    with pytest.raises(GraphError, match="depends on a dropped"):
        graph_from_dependencies("a red", "x", ["a", "red"], [None, 0], ["det", "amod"])


def test_unknown_parser_name():
    with pytest.raises(CommandError, match="unknown parser 'stanza'; available: semantic"):
        get_parser("stanza")


def test_user_parser_can_be_registered(monkeypatch):
    monkeypatch.setattr(registry, "_FACTORIES", dict(registry._FACTORIES))  # keep the registry clean
    class Flat:
        name = "flat"

        def __init__(self, lexicon):
            self.lexicon = lexicon

        def parse(self, command):
            words = command.split()
            return graph_from_dependencies(command, self.name, words, [None] * len(words),
                                           ["root"] * len(words), self.lexicon)

    register_parser("flat", Flat)
    graph = get_parser("flat", BIG_SMALL).parse("walk small")
    assert graph.node(graph.root).word == DUMMY_ROOT_WORD
    assert graph.node(1).module == "big|small_0" and graph.node(1).head == 1


def test_parser_cache_serves_equivalent_text_without_a_new_parse():
    p = get_parser("semantic")
    first = p.parse("walk to a circle")
    again = p.parse("WALK, to the circle!")
    assert again == first and again.typed == "WALK, to the circle!" and first.typed is None
    assert p._cached_outcome.cache_info().hits == 1


@pytest.mark.parametrize("name", BUILTIN_PARSERS)
@given(text=st.text(max_size=80))
def test_fuzz_any_text_parses_or_raises_command_error(name, text):
    try:
        graph = get_parser(name).parse(text)
    except CommandError:
        return
    assert graph.command in all_commands()


@pytest.mark.parametrize("name", BUILTIN_PARSERS)
@given(words=st.lists(st.sampled_from(VOCABULARY + ("while", "the", "large", "Circle", "!")), min_size=1, max_size=9))
def test_fuzz_vocabulary_sequences_parse_iff_their_canonical_form_is_gscan(name, words):
    text = " ".join(words)
    try:
        normalized = canonicalize(text).canonical
    except CommandError:  # a stray "while"
        with pytest.raises(CommandError):
            get_parser(name).parse(text)
        return
    if normalized in GSCAN:
        assert get_parser(name).parse(text).command == normalized
    else:
        with pytest.raises(CommandError, match="not in the gSCAN command grammar"):
            get_parser(name).parse(text)


@given(command=st.sampled_from(sorted(GSCAN)), separator=st.sampled_from([",", " ", " , "]), upper=st.booleans())
def test_gscan_commands_in_any_surface_form_parse_to_the_normalized_command(command, separator, upper):
    text = separator.join(command.upper().split() if upper else command.split()) + "."
    for name in BUILTIN_PARSERS:
        assert get_parser(name).parse(text).command == command


@pytest.mark.parametrize("name", BUILTIN_PARSERS)
def test_parse_failures_are_cached_per_token_tuple(name):
    p = get_parser(name)
    with pytest.raises(CommandError, match="not in the gSCAN command grammar") as first:
        p.parse("circle a to walk")
    calls = []
    p._graph = lambda tokens: calls.append(tokens)  # any parse from here on would be recorded
    with pytest.raises(CommandError) as again:
        p.parse("Circle, a to WALK!")
    assert str(again.value) == str(first.value) and again.value is not first.value
    assert calls == []
    assert p._cached_outcome.cache_info().maxsize == 2048


def test_semantic_chain_is_the_grammar_trees_content_words_by_category():
    """The set lookup + category sort gives what the chart parse of gscan_grammar() gives."""
    rank = {category: i for i, category in enumerate(CHAIN_ORDER)}
    p = get_parser("semantic")
    for command in all_commands():
        tokens = tokenize(command)
        tree = parse_tree(gscan_grammar(), tokens)
        preterminals = [t for t in tree.subtrees() if t.label() in rank]
        expected = [t[0] for t in sorted(preterminals, key=lambda t: rank[t.label()])]
        assert [n.word for n in p.parse(command).nodes] == expected


def test_every_gscan_word_has_one_preterminal_category():
    categories = defaultdict(set)
    for production in gscan_grammar().productions():
        if len(production.rhs()) == 1 and isinstance(production.rhs()[0], str):
            categories[production.rhs()[0]].add(production.lhs().symbol())
    assert set(categories) == set(VOCABULARY) - {"to", "a"}
    assert all(len(c) == 1 for c in categories.values())
