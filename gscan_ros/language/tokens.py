"""Command text -> gSCAN tokens, with one-line errors for anything that is not gSCAN.

gSCAN has 18 tokens (GSCAN_SPEC §5.3); the two-word adverbs "while spinning" and
"while zigzagging" are single tokens. The tokenizer is tolerant of case, punctuation
and the dataset's comma separators ("Walk, to a RED circle!" works), but strict about
words: an unknown word is reported with its closest known words.
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

# Runs of letters/digits; everything else (spaces, commas, punctuation, '_') separates words.
# The words are then joined into gSCAN tokens by the world's `split_command` (one rule
# for "while X"); this module adds the checks and the user-facing errors.
_WORD = re.compile(r"[^\W_]+")


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


def tokenize(text: str) -> tuple[str, ...]:
    """gSCAN tokens of `text`, lower-cased; raises CommandError naming the problem."""
    if not isinstance(text, str):
        raise CommandError(f"command must be a string, got {type(text).__name__}")
    if not text.isprintable():  # fast path in C; find the culprit only when needed
        for i, char in enumerate(text):
            if not (char.isprintable() or char in " \t\r\n"):
                raise CommandError(f"command contains a non-printable character {ord(char):#06x} at position {i}")
    # A token spans at most two words, so stop reading after 2 * MAX_TOKENS + 1 words.
    words = [m.group() for m in itertools.islice(_WORD.finditer(text.lower()), 2 * MAX_TOKENS + 1)]
    if not words:
        raise CommandError("command is empty" if not text.strip() else f"command {_clip(text)!r} has no words")
    tokens = split_command(" ".join(words))
    if len(tokens) > MAX_TOKENS:
        raise CommandError(f"command has more than {MAX_TOKENS} tokens")
    for token in tokens:
        if token not in _KNOWN:
            raise CommandError(_unknown_word_message(token))
    return tuple(tokens)


def _unknown_word_message(word: str) -> str:
    # Only words up to _MATCHABLE_LEN can have close matches: skipping difflib for longer
    # ones changes no message and keeps a 10 kB word from costing milliseconds.
    close = difflib.get_close_matches(word, _HINTS, n=3, cutoff=_CUTOFF) if len(word) <= _MATCHABLE_LEN else []
    suggestions = list(dict.fromkeys(t for key in close for t in _HINTS[key]))
    if suggestions:
        hint = "closest known words: " + ", ".join(repr(s) for s in suggestions)
    else:
        hint = "known words: " + ", ".join(VOCABULARY)
    return f"unknown word {_clip(word)!r}; {hint}"


def _clip(text: str, limit: int = 40) -> str:
    return text if len(text) <= limit else text[: limit - 1] + "…"
