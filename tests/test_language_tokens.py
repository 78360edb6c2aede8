import difflib

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gscan_ros.errors import CommandError
from gscan_ros.language import MAX_TOKENS, VOCABULARY, tokenize
from gscan_ros.language import tokens as tokens_impl


def test_vocabulary_is_the_18_gscan_tokens():
    assert len(VOCABULARY) == len(set(VOCABULARY)) == 18
    assert {"while spinning", "while zigzagging", "to", "a"} <= set(VOCABULARY)


@pytest.mark.parametrize(
    "text, tokens",
    [
        ("walk to a red small circle while spinning",
         ("walk", "to", "a", "red", "small", "circle", "while spinning")),
        ("  Pull A Big Square, while   ZIGZAGGING!", ("pull", "a", "big", "square", "while zigzagging")),
        ("walk,to,a,circle,cautiously", ("walk", "to", "a", "circle", "cautiously")),  # dataset.txt form
        ("push a\tcylinder.\n", ("push", "a", "cylinder")),
        ("walk\u00a0to a\u2003circle", ("walk", "to", "a", "circle")),  # no-break and em spaces
    ],
)
def test_tokenize_is_case_space_and_punctuation_tolerant(text, tokens):
    assert tokenize(text) == tokens


@pytest.mark.parametrize(
    "text, message",
    [
        ("walk to a smal circle", r"unknown word 'smal'; closest known words: 'small'"),
        ("walk to a circle spining", r"unknown word 'spining'; closest known words: 'while spinning'"),
        ("walk to a circle while running", r"unknown word 'while running'; closest known words: 'while spinning'"),
        ("walk while", r"unknown word 'while'; closest known words: 'while spinning', 'while zigzagging'"),
        ("qqqq", r"unknown word 'qqqq'; known words: walk, push"),
        ("", "command is empty"),
        ("   \n", "command is empty"),
        ("?!,", "has no words"),
        ("walk\x00to a circle", "non-printable character 0x0000 at position 4"),
        ("walk to a red C\u0130RCLE", "unknown word 'ci\u0307rcle'; closest known words: 'circle'"),  # not 'ci'
        ("wal\u0308k to a circle", "unknown word 'wal\u0308k'"),  # a combining mark stays in its word
        ("walk " * (MAX_TOKENS + 1), f"more than {MAX_TOKENS} tokens"),
        ("while spinning " * (MAX_TOKENS + 1), f"more than {MAX_TOKENS} tokens"),
        ("walk " * 10**6, f"more than {MAX_TOKENS} tokens"),
    ],
)
def test_bad_input_raises_command_error_naming_the_problem(text, message):
    with pytest.raises(CommandError, match=message):
        tokenize(text)


def test_non_string_is_rejected():
    with pytest.raises(CommandError, match="must be a string, got int"):
        tokenize(42)


def test_exactly_max_tokens_is_accepted():
    assert len(tokenize("walk " * MAX_TOKENS)) == MAX_TOKENS
    assert len(tokenize("while spinning " * MAX_TOKENS)) == MAX_TOKENS


@given(st.lists(st.sampled_from(VOCABULARY), min_size=1, max_size=12), st.sampled_from([" ", ", ", "  ", " . "]))
def test_joined_vocabulary_tokens_round_trip(tokens, separator):
    assert tokenize(separator.join(t.upper() for t in tokens)) == tuple(tokens)


def test_a_long_unknown_word_is_named_clipped_and_costs_no_fuzzy_match(monkeypatch):
    monkeypatch.setattr(difflib, "get_close_matches", lambda *args, **kwargs: pytest.fail("difflib was called"))
    with pytest.raises(CommandError) as error:
        tokenize("walk to a " + "x" * 10_000)
    message = str(error.value)
    assert message.startswith("unknown word '" + "x" * 39 + "…'; known words: walk, push")
    assert len(message) < 300


@pytest.mark.parametrize("padding", [0, 5, 20, 21, 22, 23, 40])
@pytest.mark.parametrize("known", ["small", "while zigzagging"])
def test_skipping_difflib_for_long_words_changes_no_suggestion(known, padding):
    """The length bound is exact: past it difflib finds nothing, and at it the longest token still matches."""
    word = known + "q" * padding
    expected = difflib.get_close_matches(word, tokens_impl._HINTS, n=3, cutoff=tokens_impl._CUTOFF)
    assert ("closest known words" in tokens_impl.unknown_word_message(word)) == bool(expected)
    if known == "while zigzagging":  # the longest token: matches up to the bound, not beyond
        assert bool(expected) == (len(word) <= tokens_impl._MATCHABLE_LEN)


@pytest.mark.parametrize(
    "data, message",
    [
        (b"walk to a \xff circle", r"not valid UTF-8 \(byte 0xff at position 10\)"),
        ("walk to a \udcff circle", r"not valid UTF-8 \(byte 0xff at position 10\)"),  # argv's surrogateescape
        (b"walk\x00 to a circle", r"non-printable character 0x0000 at position 4"),
        ("walk\x00 to a circle", r"non-printable character 0x0000 at position 4"),
    ],
)
def test_command_text_rejects_bytes_and_str_alike(data, message):
    """One check for the CLI (str from argv) and parser_node (bytes off the wire)."""
    with pytest.raises(CommandError, match=message):
        tokens_impl.command_text(data)


def test_command_text_decodes_valid_utf8():
    assert tokens_impl.command_text("walk to a circle".encode()) == "walk to a circle"
    assert tokens_impl.command_text("walk to a circle") == "walk to a circle"


def test_cli_parse_rejects_invalid_utf8_with_the_shared_message(capsys):
    from gscan_ros.cli import main

    assert main(["parse", "--lexicon", "none", "walk to a \udcff circle"]) == 1
    err = capsys.readouterr().err
    assert "command is not valid UTF-8 (byte 0xff at position 10)" in err and err.count("\n") == 1
