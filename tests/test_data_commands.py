"""The 675 gSCAN commands and their dataset strings (Ruis et al. 2020; docs/data.md)."""
import pytest

from gscan_ros.data.commands import ALL_COMMANDS, COMMANDS, grammar_string, parse_command
from gscan_ros.errors import CommandError
from gscan_ros.world.types import COLOR_ADJECTIVES, SIZE_ADJECTIVES


def test_exactly_675_distinct_commands_in_fixed_order():
    assert len(ALL_COMMANDS) == 675
    assert len(set(ALL_COMMANDS)) == 675
    assert ALL_COMMANDS[0] == "walk to a circle"
    assert ALL_COMMANDS == tuple(c.text for c in COMMANDS)


def test_color_before_size_and_no_repeated_category():
    for command in COMMANDS:
        adjectives = [t for t in command.tokens if t in COLOR_ADJECTIVES + SIZE_ADJECTIVES]
        assert len(adjectives) <= 2
        if len(adjectives) == 2:
            assert adjectives[0] in COLOR_ADJECTIVES and adjectives[1] in SIZE_ADJECTIVES
    assert "walk to a red small circle" in ALL_COMMANDS
    assert "walk to a small red circle" not in ALL_COMMANDS


def test_counts_per_slot():
    assert sum(1 for c in COMMANDS if not c.adverb) == 135
    assert sum(1 for c in COMMANDS if c.adverb == "while spinning") == 135
    assert sum(1 for c in COMMANDS if c.verb == "walk") == 225


def test_derivation_matches_released_example():
    # Real derivation from LauraRuis/groundedSCAN example_prediction.json.
    command = parse_command("push,a,green,small,square,cautiously")
    assert command.derivation == (
        "NP -> NN,NP -> JJ NP,NP -> JJ NP,DP -> 'a' NP,VP -> VV_trans DP,VP -> VP RB,ROOT -> VP;"
        "T:push,NT:VV_transitive -> push,T:a,T:green,NT:JJ -> small:JJ -> green,T:small,T:square,"
        "NT:NN -> square,T:cautiously,NT:RB -> cautiously"
    )


def test_derivation_of_intransitive_one_adjective():
    # The demo dataset's first example (GS documentation).
    assert parse_command("walk to a red circle").derivation == (
        "NP -> NN,NP -> JJ NP,DP -> 'a' NP,VP -> VV_intrans 'to' DP,ROOT -> VP;"
        "T:walk,NT:VV_intransitive -> walk,T:to,T:a,T:red,NT:JJ -> red,T:circle,NT:NN -> circle"
    )


@pytest.mark.parametrize("text, referred", [
    ("walk to a red circle", " red circle"),
    ("walk to a circle", "  circle"),
    ("pull a yellow small cylinder while spinning", "small yellow cylinder"),
    ("push a big square", "big  square"),
])
def test_referred_target_is_size_color_noun(text, referred):
    assert parse_command(text).referred_target == referred


def test_json_text_keeps_two_word_adverbs_as_one_token():
    command = parse_command("walk to a red small circle while spinning")
    assert command.json_text == "walk,to,a,red,small,circle,while spinning"
    assert parse_command(command.json_text) is command


def test_grammar_header_lists_rules_then_lexicon():
    text = grammar_string()
    assert text.startswith("ROOT -> VP;VP -> VP RB;")
    assert text.endswith("JJ -> big;JJ -> small;")


@pytest.mark.parametrize("bad", ["walk to a small red circle", "jump to a circle", "walk to a circle circle", ""])
def test_unknown_commands_raise(bad):
    with pytest.raises(CommandError):
        parse_command(bad)
