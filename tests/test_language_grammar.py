import itertools

import pytest
from nltk.parse.generate import generate

from gscan_ros.data.commands import ALL_COMMANDS as DATA_COMMANDS
from gscan_ros.errors import CommandError
from gscan_ros.language import all_commands, gscan_grammar, phrase_grammar, tokenize
from gscan_ros.language.grammar import parse_tree
from gscan_ros.world.types import ADVERBS, COLOR_ADJECTIVES, NOUNS, SIZE_ADJECTIVES, TRANSITIVE_VERBS, VERBS


def templated_commands() -> set[str]:
    """3 verbs x 3 nouns x 15 modifier combos (color before size) x 5 adverb options."""
    out = set()
    for verb, noun, color, size, adverb in itertools.product(
        VERBS, NOUNS, ("",) + COLOR_ADJECTIVES, ("",) + SIZE_ADJECTIVES, ("",) + ADVERBS
    ):
        words = [verb] + ([] if verb in TRANSITIVE_VERBS else ["to"]) + ["a", color, size, noun, adverb]
        out.add(" ".join(w for w in words if w))
    return out


def test_all_commands_are_the_675_gscan_commands():
    commands = all_commands()
    assert len(commands) == len(set(commands)) == 675
    assert set(commands) == templated_commands()


def test_all_commands_match_the_data_layer():
    assert set(DATA_COMMANDS) == set(all_commands())  # the generator's own enumeration


def test_language_package_exposes_all_commands():
    import gscan_ros.language as language

    assert language.ALL_COMMANDS == all_commands()


def test_phrase_grammar_covers_exactly_the_same_language():
    assert {" ".join(t) for t in generate(phrase_grammar())} == set(all_commands())


@pytest.mark.parametrize("grammar", [gscan_grammar, phrase_grammar], ids=["gscan", "phrase"])
@pytest.mark.parametrize(
    "command",
    [
        "circle walk",  # grammatical English fragments, all words known, not gSCAN
        "walk to a small red circle",  # size before color
        "push to a circle",
        "walk a circle",
        "walk to a red blue circle",
        "pull a circle cautiously hesitantly",  # two adverbs
        "walk to a circle walk to a circle",
    ],
)
def test_known_words_outside_the_grammar_are_rejected(grammar, command):
    with pytest.raises(CommandError, match="is not in the gSCAN command grammar"):
        parse_tree(grammar(), tokenize(command))


def test_gscan_tree_uses_gscan_categories():
    tree = parse_tree(gscan_grammar(), tokenize("push a green small square while zigzagging"))
    preterminals = [(t.label(), t[0]) for t in tree.subtrees(lambda t: isinstance(t[0], str) and len(t) == 1)]
    assert preterminals == [
        ("VV_trans", "push"), ("JJ_color", "green"), ("JJ_size", "small"), ("NN", "square"),
        ("RB", "while zigzagging"),
    ]
