"""Command text -> gSCAN tokens, with one-line errors for anything that is not gSCAN.

gSCAN has 18 tokens (Ruis et al. 2020); the two-word adverbs "while spinning" and
"while zigzagging" are single tokens. The tokenizer is tolerant of case, punctuation
and the dataset's comma separators ("Walk, to a RED circle!" works), but strict about
words: an unknown word is reported with its closest known words. `canonical.canonicalize`
builds on it to read natural paraphrases (determiners, WordNet synonyms, adjective order).
"""
from __future__ import annotations

import difflib
import itertools
import re

from gscan_ros.errors import CommandError
from gscan_ros.world.command import split_command
from gscan_ros.world.types import (
    ADVERBS,
    COLOR_ADJECTIVES,
    FUNCTION_WORDS,
    INTRANSITIVE_VERBS,
    NOUNS,
    SIZE_ADJECTIVES,
    TRANSITIVE_VERBS,
)

MAX_TOKENS = 64

# Content words by grammatical category (the parsers' lexical categories).
CONTENT_WORDS: tuple[str, ...] = (
    INTRANSITIVE_VERBS + TRANSITIVE_VERBS + NOUNS + COLOR_ADJECTIVES + SIZE_ADJECTIVES + ADVERBS
)
VOCABULARY: tuple[str, ...] = CONTENT_WORDS + FUNCTION_WORDS

# Runs of letters/digits, with the combining marks inside them (so that "CİRCLE", whose
# lower case is "ci\u0307rcle", is one unknown word, not 'ci'); everything else (spaces,
# commas, punctuation, '_') separates words. The words are then joined into gSCAN tokens by
# the world's `split_command` (one rule for "while X"); this module adds the checks and the
# user-facing errors.
_WORD = re.compile(r"[^\W_](?:[^\W_]|[\u0300-\u036f\u1ab0-\u1aff\u1dc0-\u1dff\u20d0-\u20ff\ufe20-\ufe2f])*")


def _hint_table() -> dict[str, tuple[str, ...]]:
    """Every token, and every word of a multiword token -> the tokens a user may have meant."""
    table: dict[str, list[str]] = {}
    for token in VOCABULARY:
        for key in dict.fromkeys((token, *token.split())):
            table.setdefault(key, []).append(token)
    return {key: tuple(tokens) for key, tokens in table.items()}


_HINTS = _hint_table()
_KNOWN = frozenset(VOCABULARY)
_CUTOFF = 0.6  # difflib similarity a suggestion needs
# difflib's ratio is 2 * matches / (len(word) + len(key)) <= 2 * len(key) / (len(word) + len(key)),
# so a word longer than this reaches the cutoff with no key.
_MATCHABLE_LEN = int(max(map(len, _HINTS)) * (2 / _CUTOFF - 1))


def command_text(data: str | bytes) -> str:
    """The command as text, or CommandError for invalid UTF-8, NUL or control characters.

    The one input check for every way a command arrives, so each is accepted or rejected
    alike: bytes as received from the wire (parser_node decodes nothing itself, because
    rclpy replaces invalid UTF-8 and cuts at NUL), str from argv, where Python keeps
    invalid UTF-8 as lone surrogates (`surrogateescape`).
    """
    if isinstance(data, (bytes, bytearray)):
        try:
            return _printable(bytes(data).decode("utf-8"))
        except UnicodeDecodeError as exc:
            raise CommandError(_not_utf8(exc.object[exc.start], exc.start)) from None
    if not isinstance(data, str):
        raise CommandError(f"command must be a string, got {type(data).__name__}")
    try:
        data.encode("utf-8")
    except UnicodeEncodeError as exc:  # a lone surrogate: an undecodable argv byte
        code = ord(data[exc.start])
        if 0xDC80 <= code <= 0xDCFF:
            raise CommandError(_not_utf8(code - 0xDC00, exc.start)) from None
        raise CommandError(f"command is not valid UTF-8 (lone surrogate {code:#06x} at position {exc.start})") from None
    return _printable(data)


def _not_utf8(byte: int, position: int) -> str:
    return f"command is not valid UTF-8 (byte {byte:#04x} at position {position})"


def _printable(text: str) -> str:
    if not text.isprintable():  # fast path in C; find the culprit only when needed
        for i, char in enumerate(text):
            if not (char.isprintable() or char.isspace()):  # a no-break space separates words too
                raise CommandError(f"command contains a non-printable character {ord(char):#06x} at position {i}")
    return text


def tokenize(text: str) -> tuple[str, ...]:
    """gSCAN tokens of `text`, lower-cased; raises CommandError naming the problem."""
    tokens = command_words(command_text(text))
    for token in tokens:
        if token not in _KNOWN:
            raise CommandError(unknown_word_message(token))
    return tokens


def is_known(token: str) -> bool:
    """True for the 18 gSCAN tokens."""
    return token in _KNOWN


def command_words(text: str) -> tuple[str, ...]:
    """The words of checked text, lower-cased, "while X" joined, not yet checked against
    the vocabulary; CommandError when there are none or more than MAX_TOKENS."""
    # A token spans at most two words, so stop reading after 2 * MAX_TOKENS + 1 words.
    words = [m.group() for m in itertools.islice(_WORD.finditer(text.lower()), 2 * MAX_TOKENS + 1)]
    if not words:
        raise CommandError("command is empty" if not text.strip() else f"command {_clip(text)!r} has no words")
    tokens = split_command(" ".join(words))
    if len(tokens) > MAX_TOKENS:
        raise CommandError(f"command has more than {MAX_TOKENS} tokens")
    return tokens


def unknown_word_message(word: str, why: str = "") -> str:
    """`unknown word 'smal'{why}; closest known words: 'small'` (all known words when none is close)."""
    # Only words up to _MATCHABLE_LEN can have close matches: skipping difflib for longer
    # ones changes no message and keeps a 10 kB word from costing milliseconds.
    close = difflib.get_close_matches(word, _HINTS, n=3, cutoff=_CUTOFF) if len(word) <= _MATCHABLE_LEN else []
    suggestions = list(dict.fromkeys(t for key in close for t in _HINTS[key]))
    if suggestions:
        hint = "closest known words: " + ", ".join(repr(s) for s in suggestions)
    else:
        hint = "known words: " + ", ".join(VOCABULARY)
    return f"unknown word {_clip(word)!r}{why}; {hint}"


def _clip(text: str, limit: int = 40) -> str:
    return text if len(text) <= limit else text[: limit - 1] + "…"
