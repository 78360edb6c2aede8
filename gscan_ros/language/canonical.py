"""Natural command text -> the gSCAN command it means, and what was rewritten to get there.

Every built-in parser canonicalizes before it parses, so `Policy.parse`, `gscan-ros
parse` and parser_node all read "Push the small blue cylinder" as the training command
"push a blue small cylinder" and build exactly its graph. The steps, after the shared
input check (`command_text`) and tokenization (case, punctuation, spaces):

1. determiners "the" and "an" become gSCAN's only determiner "a";
2. a word outside the vocabulary that WordNet ties to a trained word becomes that word
   (`synonyms.synonym_table`: "large" -> big); any other word is a CommandError that
   names it and suggests known words;
3. adjectives in a row are put in gSCAN's order, color before size ("big red" -> "red big").

Pure (no ROS): `canonicalize(text) -> Canonical(typed, tokens, mappings)`.
"""
from __future__ import annotations

from dataclasses import dataclass

from gscan_ros.errors import CommandError, LexiconError
from gscan_ros.language.graph import MAX_COMMAND_CHARS
from gscan_ros.language.synonyms import Synonym, synonym_table
from gscan_ros.language.tokens import command_text, command_words, is_known, unknown_word_message
from gscan_ros.world.types import COLOR_ADJECTIVES, SIZE_ADJECTIVES

DETERMINERS = ("a", "an", "the")
ADJECTIVE_ORDER = "adjective order: color before size"
_ADJECTIVE_RANK = {word: 0 for word in COLOR_ADJECTIVES} | {word: 1 for word in SIZE_ADJECTIVES}


@dataclass(frozen=True)
class WordMapping:
    """One rewrite: `typed` word(s) read as `canonical`, and why."""

    typed: str
    canonical: str
    reason: str

    def __str__(self) -> str:
        return f"{self.typed} → {self.canonical} ({self.reason})"


@dataclass(frozen=True)
class Canonical:
    typed: str  # the command as it arrived (after the input check)
    tokens: tuple[str, ...]  # gSCAN tokens of the canonical command
    mappings: tuple[WordMapping, ...] = ()  # rewrites in sentence order; () when only case/spacing differ

    @property
    def canonical(self) -> str:
        return " ".join(self.tokens)

    def explain(self) -> str:
        """One line saying what was understood, e.g. for a status topic."""
        line = f"understood {self.typed!r} as {self.canonical!r}"
        return line + (": " + "; ".join(map(str, self.mappings)) if self.mappings else "")


def canonicalize(text: str | bytes) -> Canonical:
    """The canonical gSCAN form of `text`; CommandError naming any word it cannot map.

    It does not check the grammar: "circle walk" stays "circle walk" for the parser to reject.
    """
    typed = command_text(text)
    if len(typed) > MAX_COMMAND_CHARS:
        raise CommandError(f"command has {len(typed)} characters, more than the maximum of {MAX_COMMAND_CHARS}")
    tokens = list(command_words(typed))
    mappings: list[WordMapping] = []
    for i, token in enumerate(tokens):
        if is_known(token):
            continue
        if token in DETERMINERS:
            tokens[i] = "a"
            mappings.append(WordMapping(token, "a", "determiner"))
            continue
        synonym = _synonym(token)
        tokens[i] = synonym.target
        mappings.append(WordMapping(token, synonym.target, synonym.reason))
    mappings += _order_adjectives(tokens)
    return Canonical(typed, tuple(tokens), tuple(mappings))


def _synonym(word: str) -> Synonym:
    try:
        table = synonym_table()
    except LexiconError as exc:
        raise CommandError(unknown_word_message(word, f" (no WordNet synonyms: {exc})")) from None
    synonym = table.lookup(word)
    if synonym is None:
        why = table.left_out.get(word)
        raise CommandError(unknown_word_message(word, f" (left out of the WordNet synonyms: {why})" if why else ""))
    return synonym


def _order_adjectives(tokens: list[str]) -> list[WordMapping]:
    """Sort each run of adjectives into gSCAN's order in place; one mapping per reordered run."""
    mappings = []
    start = 0
    while start < len(tokens):
        end = start
        while end < len(tokens) and tokens[end] in _ADJECTIVE_RANK:
            end += 1
        run = tokens[start:end]
        ordered = sorted(run, key=_ADJECTIVE_RANK.__getitem__)  # stable: "big small" stays for the parser
        if ordered != run:
            tokens[start:end] = ordered
            mappings.append(WordMapping(" ".join(run), " ".join(ordered), ADJECTIVE_ORDER))
        start = end + 1
    return mappings
